"""``registration.calibration``, one module before it became a package, reads the solver's names
lazily for one release (its ``__init__``; the top-level alias modules are gone, CHANGELOG.md)."""

from __future__ import annotations

import importlib

import pytest


def test_old_calibration_module_names_come_from_the_solver() -> None:
    from registration.calibration import solver

    old = importlib.import_module("registration.calibration")
    assert old.calibrate is solver.calibrate
    assert old.CalibrationParams is solver.CalibrationParams
    assert old.PRIORS is importlib.import_module("registration.calibration.records").PRIORS
    with pytest.raises(AttributeError, match="no attribute 'no_such_name'"):
        _ = old.no_such_name
