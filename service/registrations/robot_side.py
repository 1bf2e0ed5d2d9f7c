"""What a registration's robot side rests on, and whether the settings still say the same.

One scan cannot see an error on the robot side (model, rod, mount): every sphere moves together and
FRE stays small.  A registration is therefore bound to the robot settings it was made with: each
records a fingerprint of them in its provenance (``robot_settings``: the robot model and its URDF's
bytes, ``robot.tool0_from_phantom``, the phantom file's bytes) beside the active calibration
(``calibration``), and each calibration records the fingerprint it was made under (its ``params``).
At start-up a current registration, or an active calibration, whose fingerprint differs from the
settings in force is not used: the registration is withdrawn with a reason naming the setting that
changed, the calibration stays inactive (docs/safety.md, "Robot settings bind what was made with
them").
"""

from __future__ import annotations

import hashlib
import json
from pathlib import Path
from typing import Any

import numpy as np

from registration.model.kinematics import RobotModel
from service.settings import Settings

FINGERPRINT_KEY = "robot_settings"
"""The key of the fingerprint in a registration's provenance and a calibration's params."""


def _file_digest(path: Path) -> str:
    """SHA-256 (first 16 hex) of a regular file's bytes; a file that cannot be read says so."""
    from registration.dicom.errors import NotRegularFileError
    from registration.dicom.files import open_regular

    try:
        with open_regular(path) as f:
            return hashlib.sha256(f.read()).hexdigest()[:16]
    except (OSError, NotRegularFileError):
        return "<unreadable>"


def robot_settings_fingerprint(settings: Settings, robot_model: RobotModel) -> dict[str, str]:
    """The robot-side settings a registration rests on, one entry per setting (name → digest)."""
    rod = settings.robot.tool0_from_phantom
    return {
        "robot.model": f"{settings.robot.model} {_file_digest(robot_model.urdf_path)}",
        "robot.tool0_from_phantom": json.dumps(
            {"translation_mm": list(rod.translation_mm), "rpy_deg": list(rod.rpy_deg)}, sort_keys=True
        ),
        "phantom_file": _file_digest(Path(settings.phantom_file)),
    }


def changed_settings(recorded: Any, now: dict[str, str]) -> list[str]:
    """The settings whose fingerprint differs (none when nothing was recorded: no evidence)."""
    if not isinstance(recorded, dict):
        return []
    return [k for k in now if k in recorded and recorded[k] != now[k]]


def _calibration_id(calibration: Any) -> int | None:
    return calibration.get("calibration_id") if isinstance(calibration, dict) else None


def stale_reasons(
    provenance: dict[str, Any],
    now: dict[str, str],
    active_calibration: dict[str, Any] | None,
    tool0_from_phantom: np.ndarray,
) -> list[str]:
    """Why a registration with ``provenance`` no longer rests on the robot side in force.

    ``tool0_from_phantom`` is the rod in force (the active calibration's, or the settings'); it is
    compared with the provenance's for registrations recorded before the fingerprint existed.
    """
    reasons = changed_settings(provenance.get(FINGERPRINT_KEY), now)
    if FINGERPRINT_KEY not in provenance:
        rod = provenance.get("tool0_from_phantom")
        if rod is not None and not np.allclose(
            np.asarray(rod, dtype=np.float64), tool0_from_phantom, atol=1e-9
        ):
            reasons.append("robot.tool0_from_phantom")
    was, is_ = _calibration_id(provenance.get("calibration")), _calibration_id(active_calibration)
    if was != is_:
        reasons.append(
            "the active calibration ("
            + (f"{was}" if was is not None else "none")
            + " → "
            + (f"{is_}" if is_ is not None else "none")
            + ")"
        )
    return reasons
