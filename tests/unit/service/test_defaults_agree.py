"""One source of truth for the gates: configs/oarmreg.toml, the service settings defaults and the
registration dataclass defaults must agree (issue #9 item 5)."""

from __future__ import annotations

import tomllib
from pathlib import Path

import pytest

from registration.matching.correspondence import DEFAULT_DISTINCT_ROTATION_DEG, find_hypotheses
from registration.matching.records import (
    RegistrationParams,
)
from registration.model.stillness import DEFAULT_MAX_DEVIATION_RAD, DEFAULT_MAX_GAP_S, assess_stillness
from service.settings import QualitySettings, StillnessSettings

REPO = Path(__file__).resolve().parents[3]
CONFIG = tomllib.loads((REPO / "configs" / "oarmreg.toml").read_text(encoding="utf-8"))

# (section, key in the TOML / settings model, registration default)
CASES = [
    ("quality", "max_fre_mm", RegistrationParams().max_fre_mm),
    ("quality", "min_matched_spheres", RegistrationParams().min_matched),
    ("quality", "min_symmetry_margin", RegistrationParams().min_runner_up_margin),
    ("stillness", "max_gap_s", DEFAULT_MAX_GAP_S),
    ("stillness", "max_deviation_rad", DEFAULT_MAX_DEVIATION_RAD),
]
MODELS = {"quality": QualitySettings, "stillness": StillnessSettings}


@pytest.mark.parametrize(("section", "key", "registration_default"), CASES)
def test_config_settings_and_dataclass_defaults_agree(
    section: str, key: str, registration_default: float
) -> None:
    settings_default = getattr(MODELS[section](), key)
    assert (CONFIG[section][key], settings_default) == (registration_default, registration_default)


def test_the_values_of_the_issue() -> None:
    # issue #9 item 5: the config's values win
    assert RegistrationParams().max_fre_mm == 0.5
    assert DEFAULT_MAX_GAP_S == 0.25
    assert RegistrationParams().distinct_rotation_deg == DEFAULT_DISTINCT_ROTATION_DEG == 5.0


def test_function_defaults_follow_the_constants() -> None:
    import inspect

    sig = inspect.signature(find_hypotheses)
    assert sig.parameters["distinct_rotation_deg"].default == RegistrationParams().distinct_rotation_deg
    assert inspect.signature(assess_stillness).parameters["max_gap_s"].default == DEFAULT_MAX_GAP_S
