"""The pose planner's target and pose budget: the defaults of the ``[calibration]`` settings and of
the planner (light: the service's settings import it without the calibration's numerics)."""

from __future__ import annotations

from typing import Final

__all__ = ["MAX_PLANNED_POSES", "TARGET_RMS_MM"]

TARGET_RMS_MM: Final = 0.075
"""The pose planner's default target: predicted RMS sphere error over the working volume after
calibrating (what held-out poses measure), mm.  Origin (simulated): 20 planned poses gave 0.072 mm
held-out mean on an unseen simulated TX60 cell whose floor (true geometric model, oracle
registration) was 0.050 mm, 10 gave 0.106 mm; 0.075 mm is 1.5 × that floor, what enough poses
deliver there.  Setting ``calibration.target_rms_mm``."""
MAX_PLANNED_POSES: Final = 30
"""Most poses the planner proposes on its own (each costs one O-arm spin of the phantom, no
patient).  Setting ``calibration.max_poses``."""
