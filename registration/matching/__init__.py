"""Stage 4 of the flow: robot points ↔ image points → ``image_from_robot`` and its quality.

After :mod:`registration.detection` has found the sphere centres in the image and
:mod:`registration.model.kinematics` has put the phantom's spheres in the robot frame, this stage
pairs them and fits the transform: :mod:`.correspondence` (hypotheses that respect the phantom's
symmetry), :mod:`.prereg` (Bai 2018's 4-point pre-registration), :mod:`.icp`, :mod:`.rigid`
(the closed-form fit), :mod:`.register` (the whole step with its refusals: mirrored, ambiguous,
too few spheres), :mod:`.quality` (FRE, FLE, predicted TRE — docs/design.md §5) and
:mod:`.verification` (a later scan against a registration).  :mod:`registration.pipeline` runs
the stages in order.
"""
