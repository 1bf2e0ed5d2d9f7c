"""``oarmreg verify`` and ``oarmreg register`` keep the service's promises (issue 31 item 7 and
"the honest figure first"): PASS / FAIL against ``quality.max_verification_error_mm`` (the TOML
``--config``, ``--max-error-mm`` overriding it), exit 7 on FAIL (docs/cli.md); ``--pairing-gate-mm``
is the pairing gate, ``--gate-mm`` is refused naming it; register's summary opens with the chain
figure and uses the service's default targets; targets are robot-frame by name.  Runs the CLI's
``main`` on point files (no DICOM: the judgement is what is tested)."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from registration.io.points import write_json, write_points
from registration.model.frames import apply, transform_from_xyz_rpy
from service.cli.main import main
from service.error_map import EXIT_ACCURACY, EXIT_CONFIG, EXIT_INPUT, EXIT_OK, EXIT_USAGE

IMAGE_FROM_ROBOT = transform_from_xyz_rpy([-35.0, -420.0, 310.0], [180.0, 0.0, 90.0])
ROBOT_FROM_PHANTOM = transform_from_xyz_rpy([500.0, 40.0, 300.0], [0.0, 0.0, 30.0])
CapSys = pytest.CaptureFixture[str]
SHIFT_MM = np.array([2.0, 0.0, 0.0])  # the "registration off by 2 mm"


@pytest.fixture
def files(tmp_path: Path, phantom: Any) -> dict[str, Path]:
    robot = apply(ROBOT_FROM_PHANTOM, phantom.centres_phantom_mm)
    image = apply(IMAGE_FROM_ROBOT, robot)
    out = {
        "robot": write_points(tmp_path / "robot.json", robot),
        "exact": write_points(tmp_path / "image.json", image),
        "moved": write_points(tmp_path / "moved.json", image + SHIFT_MM),
        "reg": write_json(tmp_path / "reg.json", {"image_from_robot": IMAGE_FROM_ROBOT.tolist()}),
    }
    return out


def verify(files: dict[str, Path], image: str, *extra: str) -> list[str]:
    return ["verify", "--image-points", str(files[image]), "--robot-points", str(files["robot"]),
            "--registration", str(files["reg"]), *extra]  # fmt: skip


def test_verify_off_by_2_mm_fails_with_exit_7_and_says_fail(
    files: dict[str, Path], tmp_path: Path, capsys: CapSys, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.delenv("OARMREG_QUALITY__MAX_VERIFICATION_ERROR_MM", raising=False)
    out = tmp_path / "ver.json"
    rc = main(verify(files, "moved", "--json", str(out)))
    std = capsys.readouterr()
    assert rc == EXIT_ACCURACY, std
    assert "FAIL: max 2.000 mm > 1 mm (quality.max_verification_error_mm" in std.out
    assert "Verification failed" in std.err and "do not use this registration" in std.err
    doc = json.loads(out.read_text())
    assert doc["passed"] is False and doc["max_verification_error_mm"] == 1.0
    assert doc["max_mm"] == pytest.approx(2.0, abs=1e-6)
    # the same registration on the exact points passes (the control)
    assert main(verify(files, "exact")) == EXIT_OK
    assert "PASS: max 0.000 mm <= 1 mm" in capsys.readouterr().out


def test_the_limit_comes_from_the_toml_and_the_flag_overrides_it(
    files: dict[str, Path], tmp_path: Path, capsys: CapSys, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.delenv("OARMREG_QUALITY__MAX_VERIFICATION_ERROR_MM", raising=False)
    toml = tmp_path / "oarmreg.toml"
    toml.write_text("[quality]\nmax_verification_error_mm = 2.5\n")
    assert main(verify(files, "moved", "--config", str(toml))) == EXIT_OK
    want = f"PASS: max 2.000 mm <= 2.5 mm (quality.max_verification_error_mm ({toml}))"
    assert want in capsys.readouterr().out
    assert main(verify(files, "moved", "--config", str(toml), "--max-error-mm", "1.5")) == EXIT_ACCURACY
    assert "FAIL: max 2.000 mm > 1.5 mm (--max-error-mm)" in capsys.readouterr().out
    bad = tmp_path / "bad.toml"
    bad.write_text("[quality]\nmax_verification_error_mm = nan\n")
    assert main(verify(files, "moved", "--config", str(bad))) == EXIT_CONFIG
    assert "quality.max_verification_error_mm" in capsys.readouterr().err


def test_the_pairing_gate_is_named_apart(files: dict[str, Path], capsys: pytest.CaptureFixture[str]) -> None:
    assert main(verify(files, "exact", "--pairing-gate-mm", "3")) == EXIT_OK
    assert "(pairing gate 3 mm)" in capsys.readouterr().out
    with pytest.raises(SystemExit) as e:
        main(verify(files, "exact", "--gate-mm", "3"))
    assert e.value.code == EXIT_USAGE
    assert "use --pairing-gate-mm" in capsys.readouterr().err


# ---- register: the honest figure first, the service's default targets, one frame per name ----------


def register(files: dict[str, Path], *extra: str) -> list[str]:
    return ["register", "--image-points", str(files["exact"]), "--robot-points", str(files["robot"]), *extra]


def test_register_summary_shows_the_chain_figure_first_and_the_services_default_targets(
    files: dict[str, Path], tmp_path: Path, capsys: CapSys, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Issue 31 "the honest figure first": the CLI's summary opens with predicted_chain_error_mm and
    whether a calibration backs it; the one-scan TRE is labelled as such, at the service's 6 default
    targets (before: no chain figure without --joints, no predicted TRE without --targets)."""
    monkeypatch.delenv("OARMREG_QUALITY__DEFAULT_TARGET_DISTANCE_MM", raising=False)
    out = tmp_path / "reg.json"
    assert main(register(files, "--json", str(out))) == EXIT_OK
    lines = capsys.readouterr().out.splitlines()
    # issue 40: what backs the robot side first (no calibration given: unverified, with the action)
    assert lines[0].startswith("evidence: UNVERIFIED: ") and "verify at another pose" in lines[0]
    assert lines[1].startswith(
        "expected error at the robot's working poses: 1.000 mm (predicted_chain_error_mm"
    )
    assert "NOT calibrated" in lines[1]
    one_scan = next(ln for ln in lines if ln.startswith("one-scan TRE, this pose only"))
    assert "not the chain's error" in one_scan and "6 targets" in one_scan and "150 mm" in one_scan
    doc = json.loads(out.read_text())
    assert doc["predicted_chain_error_mm"] == 1.0 and "nominal" in doc["chain_error_source"]
    centre = ROBOT_FROM_PHANTOM[:3, 3]
    want = np.vstack([centre + 150.0 * np.eye(3), centre - 150.0 * np.eye(3)])
    np.testing.assert_allclose(doc["targets_robot_mm"], want, atol=1e-6)
    assert len(doc["predicted_tre_mm"]) == 6
    toml = tmp_path / "oarmreg.toml"
    toml.write_text("[quality]\ndefault_target_distance_mm = 80.0\n")
    assert main(register(files, "--json", str(out), "--config", str(toml))) == EXIT_OK
    capsys.readouterr()
    np.testing.assert_allclose(
        json.loads(out.read_text())["targets_robot_mm"][0], centre + np.array([80.0, 0.0, 0.0]), atol=1e-6
    )


def test_register_targets_are_robot_frame_by_name(
    files: dict[str, Path], tmp_path: Path, capsys: CapSys
) -> None:
    """``targets_robot_mm`` / ``--targets-robot`` in the CLI (the API's are ``targets_image_mm``): the
    old names are refused, naming the new ones."""
    from registration.io.points import write_targets

    given = write_targets(tmp_path / "t.json", [[550.0, 0.0, 300.0]])
    assert json.loads(given.read_text()) == {"targets_robot_mm": [[550.0, 0.0, 300.0]]}
    out = tmp_path / "reg.json"
    assert main(register(files, "--targets-robot", str(given), "--json", str(out))) == EXIT_OK
    assert json.loads(out.read_text())["targets_robot_mm"] == [[550.0, 0.0, 300.0]]
    capsys.readouterr()
    old = write_json(tmp_path / "old.json", {"targets_mm": [[550.0, 0.0, 300.0]]})
    assert main(register(files, "--targets-robot", str(old))) == EXIT_INPUT
    assert '"targets_mm" was renamed "targets_robot_mm"' in capsys.readouterr().err
    with pytest.raises(SystemExit) as e:
        main(register(files, "--targets", str(given)))
    assert e.value.code == EXIT_USAGE and "use --targets-robot" in capsys.readouterr().err
