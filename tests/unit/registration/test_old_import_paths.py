"""The module paths ``registration/`` had before its sub-packages keep working for one release.

Each old path is the new module itself (so pickled benchmark caches and configs naming it load
the same classes); ``registration.calibration``, now a package, reads the solver's names lazily.
"""

from __future__ import annotations

import importlib

import pytest

MOVED = {
    "volume": "imaging.volume",
    "mar": "imaging.mar",
    "circles": "imaging.circles",
    "scan_geometry": "imaging.scan_geometry",
    "frames": "model.frames",
    "phantom": "model.phantom",
    "kinematics": "model.kinematics",
    "stillness": "model.stillness",
    "rigid": "matching.rigid",
    "correspondence": "matching.correspondence",
    "prereg": "matching.prereg",
    "icp": "matching.icp",
    "register": "matching.register",
    "quality": "matching.quality",
    "verification": "matching.verification",
    "pose_planner": "calibration.planner",
    "pose_sampling": "calibration.sampling",
    "urdf_writer": "calibration.urdf",
    "points_io": "io.points",
    "sro": "io.sro",
    "resources": "io.resources",
}


@pytest.mark.parametrize(("old", "new"), sorted(MOVED.items()))
def test_old_module_path_is_the_new_module(old: str, new: str) -> None:
    assert importlib.import_module(f"registration.{old}") is importlib.import_module(f"registration.{new}")


def test_old_calibration_module_names_come_from_the_solver() -> None:
    from registration.calibration import solver

    old = importlib.import_module("registration.calibration")
    assert old.calibrate is solver.calibrate
    assert old.CalibrationParams is solver.CalibrationParams
    assert old.PRIORS is importlib.import_module("registration.calibration.records").PRIORS
    with pytest.raises(AttributeError, match="no attribute 'no_such_name'"):
        _ = old.no_such_name
