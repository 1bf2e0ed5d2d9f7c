"""Many poses → a better robot model: the multi-pose calibration, its planner and its URDF.

:mod:`.solver` fits the robot's geometric errors, the rod and the O-arm placement to the
registrations of several scans (docs/calibration.md: method, priors, refusal on predicted error),
through :mod:`.records` (settings, priors, results), :mod:`.model` (the error model and its
Jacobian), :mod:`.fit` (the robust, regularised fit) and :mod:`.prediction` (the error to expect
over the working volume);
:mod:`.planner` proposes the poses that identify them inside the scan's real volume, on top of
:mod:`.sampling` (poses and inverse kinematics inside a volume); :mod:`.urdf` writes the
calibrated model as a URDF the service and Pinocchio load.
"""
