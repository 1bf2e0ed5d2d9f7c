"""``oarmreg calibrate plan|run`` and ``oarmreg register --joints`` (issue #10 CLI), without imaging."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from registration.calibration.planner import ScanVolume
from registration.model import frames
from registration.model.kinematics import RobotModel, default_tool0_from_phantom
from service.cli.main import main
from service.error_map import EXIT_INPUT, EXIT_OK
from service.settings import CalibrationSettings

START_JOINTS_RAD = [0.2, -0.15, 1.75, 0.3, 0.6, -0.9]


def _registration(tmp_path: Path, model: RobotModel) -> tuple[Path, Any]:
    rod = default_tool0_from_phantom()
    image_from_phantom = frames.transform_from_xyz_rpy([1.0, -2.0, 3.0], [10.0, -5.0, 30.0])
    y = image_from_phantom @ frames.invert(model.robot_from_tool0(START_JOINTS_RAD) @ rod)
    reg = tmp_path / "REG.json"
    reg.write_text(
        json.dumps({"image_from_robot": y.tolist(), "provenance": {"joints_rad": START_JOINTS_RAD}})
    )
    return reg, y


def test_plan_keeps_every_sphere_inside_the_volume_and_the_joints_inside_their_limits(
    tmp_path: Path, phantom: Any
) -> None:
    model = RobotModel.load("tx60")
    reg, y = _registration(tmp_path, model)
    out = tmp_path / "plan.json"
    assert main(["calibrate", "plan", "--registration", str(reg), "--json", str(out)]) == EXIT_OK
    plan = json.loads(out.read_text())
    # the planner chose the count (issue #33): the fewest from 10 meeting the target, or says why not
    assert len(plan["poses"]) == plan["n_poses"]
    assert plan["target_rms_mm"] == CalibrationSettings().target_rms_mm
    assert 10 <= plan["n_poses"] <= CalibrationSettings().max_poses
    assert plan["predicted_error_mm"] >= plan["predicted_rms_mm"] > 0.0
    assert plan["target_met"] == (plan["count_reason"] == "target")
    # the same pose set judged without planning gives the plan's own prediction
    judged = tmp_path / "judged.json"
    argv = ["calibrate", "plan", "--registration", str(reg), "--predict", str(out), "--json", str(judged)]
    assert main(argv) == EXIT_OK
    doc = json.loads(judged.read_text())
    assert doc["n_poses"] == plan["n_poses"]
    assert doc["predicted_rms_mm"] == pytest.approx(plan["predicted_rms_mm"], rel=1e-9)
    assert plan["predicted_condition_number"] <= 100.0
    c = plan["volume"]["centre_image_mm"]
    volume = ScanVolume(centre_image_mm=(c[0], c[1], c[2]))
    rod = default_tool0_from_phantom()
    tilts = []
    z0 = (y @ model.robot_from_tool0(START_JOINTS_RAD) @ rod)[:3, 2]
    for p in plan["poses"]:
        q = model.check_joints(p["joints_rad"])  # raises outside the limits
        assert np.all(q >= model.lower_rad + np.radians(4.99)) and np.all(
            q <= model.upper_rad - np.radians(4.99)
        )
        a = y @ model.robot_from_tool0(q) @ rod
        centres = frames.apply(a, phantom.centres_phantom_mm)
        assert float(volume.inside_margin_mm(centres[None])[0]) >= 5.0
        tilts.append(np.degrees(np.arccos(np.clip(a[:3, 2] @ z0, -1.0, 1.0))))
    assert max(tilts) >= 45.0, tilts  # orientations spread ≥ ±45°
    # ordered for short moves: it starts at the planned pose nearest to the registration's joints
    q_all = np.array([p["joints_rad"] for p in plan["poses"]])
    nearest = float(np.min(np.max(np.abs(q_all - START_JOINTS_RAD), axis=1)))
    assert plan["poses"][0]["max_joint_step_from_previous_rad"] == pytest.approx(nearest)


def test_plan_without_joints_is_refused_saying_how_to_get_them(tmp_path: Path, capsys: Any) -> None:
    reg = tmp_path / "REG.json"
    reg.write_text(json.dumps({"image_from_robot": np.eye(4).tolist()}))
    rc = main(["calibrate", "plan", "--registration", str(reg), "--json", str(tmp_path / "o.json")])
    assert rc == EXIT_INPUT
    assert "register --joints" in capsys.readouterr().err


def test_run_refuses_a_malformed_poses_file(tmp_path: Path, capsys: Any) -> None:
    poses = tmp_path / "POSES.json"
    poses.write_text(json.dumps({"robot_model": "tx60", "poses": [{"scan_dir": "a"}]}))
    assert main(["calibrate", "run", str(poses), "--out", str(tmp_path / "cal")]) == EXIT_INPUT
    assert 'poses[0] needs "scan_dir" and "joints_rad"' in capsys.readouterr().err
    assert not (tmp_path / "cal").exists()


def test_register_from_joints_equals_register_from_robot_points(tmp_path: Path, phantom: Any) -> None:
    model = RobotModel.load("tx60")
    rod = default_tool0_from_phantom()
    robot_mm = frames.apply(model.robot_from_tool0(START_JOINTS_RAD) @ rod, phantom.centres_phantom_mm)
    y = frames.transform_from_xyz_rpy([20.0, -30.0, 400.0], [170.0, 10.0, -60.0])
    image = tmp_path / "image.json"
    image.write_text(json.dumps({"spheres_mm": frames.apply(y, robot_mm)[::-1].tolist()}))
    joints = tmp_path / "JOINTS.json"
    joints.write_text(json.dumps({"joints_rad": START_JOINTS_RAD}))
    out = tmp_path / "reg.json"
    argv = ["register", "--image-points", str(image), "--joints", str(joints), "--json", str(out)]
    assert main(argv) == EXIT_OK
    doc = json.loads(out.read_text())
    np.testing.assert_allclose(np.array(doc["image_from_robot"]), y, atol=1e-6)
    assert doc["provenance"]["joints_rad"] == START_JOINTS_RAD
    assert doc["provenance"]["calibration"] is None


def test_register_needs_robot_points_or_joints(tmp_path: Path, capsys: Any) -> None:
    image = tmp_path / "image.json"
    image.write_text(json.dumps({"spheres_mm": [[0.0, 0.0, 0.0]] * 6}))
    assert main(["register", "--image-points", str(image)]) == EXIT_INPUT
    assert "--robot-points FILE.json or --joints JOINTS.json" in capsys.readouterr().err


def test_register_with_a_missing_calibration_is_a_config_error(tmp_path: Path, capsys: Any) -> None:
    joints = tmp_path / "JOINTS.json"
    joints.write_text(json.dumps({"joints_rad": START_JOINTS_RAD}))
    image = tmp_path / "image.json"
    image.write_text(json.dumps({"spheres_mm": [[0.0, 0.0, 0.0]] * 6}))
    rc = main(
        ["register", "--image-points", str(image), "--joints", str(joints), "--calibration", str(tmp_path)]
    )
    assert rc == 3
    assert "no calibration.json; run `oarmreg calibrate run`" in capsys.readouterr().err


@pytest.mark.parametrize(
    ("poses", "words"),
    [
        ([{"scan_dir": "p1", "joints_rad": [0.0, 0.0, 1.5, 0.0, 0.7]}] * 6, "must be 6 finite numbers"),
        ([{"scan_dir": "p1", "joints_rad": [0.0, 0.0, 1.5, 0.0, 0.7, True]}] * 6, "must be 6 finite numbers"),
        ([{"scan_dir": "p1", "joints_rad": START_JOINTS_RAD}] * 5, "needs at least 6 scans"),
    ],
)
def test_calibrate_run_refuses_a_bad_poses_file_before_reading_scans(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], poses: list[dict[str, Any]], words: str
) -> None:
    """The folders named do not exist: the file's own problem must be reported, not the scans'."""
    f = tmp_path / "POSES.json"
    f.write_text(json.dumps({"robot_model": "tx60", "poses": poses}))
    assert main(["calibrate", "run", str(f), "--out", str(tmp_path / "cal")]) == EXIT_INPUT
    err = capsys.readouterr().err
    assert "Invalid poses file" in err and words in err and "No CT series" not in err
    assert not (tmp_path / "cal").exists()


def test_plan_names_poses_in_a_keep_out_box_and_a_short_travel_order(
    tmp_path: Path, phantom: Any, capsys: pytest.CaptureFixture[str]
) -> None:
    """Issue 34: the plan said nothing of the gantry or table; a box around the start pose's phantom
    (the table, say) must be reported, and a scan order no longer in joint travel is proposed."""
    model = RobotModel.load("tx60")
    reg, y = _registration(tmp_path, model)
    c = (y @ model.robot_from_tool0(START_JOINTS_RAD) @ default_tool0_from_phantom())[:3, 3]
    box = ",".join(f"{v:.1f}" for v in [*(c - 400), *(c + 400)])
    out = tmp_path / "plan.json"
    argv = ["calibrate", "plan", "--registration", str(reg), "--json", str(out), "--keep-out", f"table:{box}"]
    assert main(argv) == EXIT_OK
    text = capsys.readouterr().out
    plan = json.loads(out.read_text())
    assert plan["keep_out"]["boxes"][0]["name"] == "table"
    assert all(p["near"] for p in plan["keep_out"]["poses"]) and "INSIDE" in text
    travel = plan["short_travel_order"]
    assert sorted(travel["order"]) == list(range(len(plan["poses"])))
    assert travel["travel_rad"] <= travel["planned_order_travel_rad"]
    assert main([*argv[:-2], "--keep-out", "bad:1,2,3"]) == EXIT_INPUT
