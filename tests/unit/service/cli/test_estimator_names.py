"""Issue #35, one home per setting: the estimator names come from the estimator table
(:data:`registration.detection.estimators.METHODS`); ``[detection] method`` and
``oarmreg detect/register --method`` accept every estimator in it (``model`` was missing from both)."""

from __future__ import annotations

import pytest

from registration.detection.estimators import ESTIMATOR_MODULES, METHODS
from service.cli.main import build_parser
from service.settings import DetectionSettings, load_settings


@pytest.mark.parametrize("method", list(ESTIMATOR_MODULES))
def test_every_estimator_of_the_table_is_a_setting_and_a_flag(method: str) -> None:
    assert DetectionSettings(method=method).method == method
    assert load_settings(overrides={"detection.method": method}).detection.method == method
    argvs = (["detect", "scan"], ["register", "scan", "--robot-points", "points.json"])
    for argv in argvs:
        args = build_parser(argv[0]).parse_args([*argv, "--method", method])
        assert args.method == method


def test_an_unknown_method_is_refused_naming_the_table() -> None:
    with pytest.raises(ValueError, match="use one of default, " + ", ".join(METHODS)):
        DetectionSettings(method="centroid")
