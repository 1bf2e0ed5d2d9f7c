"""From a recorded scan to a registration: capture of the robot's joints, the orchestrator that runs
MAR, detection and matching (``registration.pipeline``), verification, calibration jobs, auto-
register and the figures and plots that go with a result.

Enters: scan records and joint snapshots; API calls (register, verify, calibrate).
Leaves: registration, verification and calibration records in the store; events on the bus.
"""
