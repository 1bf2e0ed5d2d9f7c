"""What the numbers mean: frames, the phantom, the robot's kinematics, and whether it held still.

Used by every stage: :mod:`.frames` (4 × 4 transforms named ``a_from_b``, docs/design.md §3),
:mod:`.phantom` (the sphere layout and its symmetry group — the symmetry trap, docs/design.md §4),
:mod:`.kinematics` (the Stäubli arm through Pinocchio: joints → ``robot_from_tool0``, and the
sphere centres in the robot frame), :mod:`.stillness` (the joint history of a scan's acquisition
window judged still / moved / incomplete, docs/safety.md).
"""
