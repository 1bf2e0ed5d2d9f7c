"""Calibration through simulated DICOM on a true cell and the CLI (issue #10 "Done when", CI-sized).

A seeded :class:`mocks.cell.TrueCell` (issue defaults: joint origins σ 0.12 mm / 0.012°, offsets
0.012°, rod 0.8 mm / 0.4°, J2/J3 sag, repeatability, encoder noise).  A first scan at the start
pose is registered with the nominal model and the pose planner proposes 10 calibration poses;
each is simulated, written as DICOM (one FrameOfReferenceUID), and ``oarmreg calibrate run
--drop-weak`` calibrates from POSES.json.  The O-arm is then moved and one scan registered with
``oarmreg register --joints --calibration`` (and without ``--calibration``, nominal); sphere
centres at 10 held-out poses are predicted through the written URDF (Pinocchio) and compared
with the truth.  Reduced volume (0.7 mm pixels, 200 × 200 × 120 slices of 1 mm, 120 views) to
fit CI; the full-size figures (10 poses, O-arm FOV) are in ``benchmarks/bench_calibration.py``.

In this 70-mm-radius volume the phantom can shift by only ~18 mm, so the link-length / rod-length
direction is weakly excited (planned condition number ≈ 140 > 100): ``--drop-weak`` drops it,
which the test checks is reported.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from numpy.typing import NDArray

from mocks.cell import CellErrorSizes, SimulatedPose, TrueCell, simulate_pose_scan
from mocks.oarm.simulator import AcquisitionSettings
from registration.calibration.planner import PlannerParams, ScanVolume, feasible_poses, plan_poses
from registration.calibration.urdf import read_chain
from registration.matching.register import register_points
from registration.model import frames
from registration.model.kinematics import RobotModel, default_tool0_from_phantom
from service.cli.main import main

F64 = NDArray[np.float64]
START_JOINTS_RAD = np.array([0.2, -0.15, 1.75, 0.3, 0.6, -0.9])
FOR_UID = "1.2.826.0.1.3680043.8.498.20"
N_POSES = 10
N_HELD_OUT = 10
MAX_MEAN_MM = 0.10
MAX_MAX_MM = 0.25
"""Issue #10 targets for held-out poses after calibration (mean / max per sphere centre)."""
MIN_IMPROVEMENT = 5.0
"""The nominal model is ≈ 1 mm off on this cell; calibration must cut the mean error ≥ 5 ×."""
LOPO_FACTOR = 1.5
"""Issue #10: leave-one-pose-out predicts the held-out error within a factor 1.5."""


@dataclass
class Outcome:
    calibrated_mm: F64
    nominal_mm: F64
    calibration: dict[str, Any]
    caldir: Path
    scans: list[SimulatedPose]


def _settings() -> AcquisitionSettings:
    return AcquisitionSettings.preset("small", rows=200, columns=200, n_slices=120, n_views=120)


def _write_json(path: Path, obj: Any) -> Path:
    path.write_text(json.dumps(obj), encoding="utf-8")
    return path


@pytest.fixture(scope="module")
def outcome(phantom: Any, tmp_path_factory: pytest.TempPathFactory) -> Outcome:
    work = tmp_path_factory.mktemp("calibration-session")
    model = RobotModel.load("tx60")
    chain = read_chain(model.urdf_path)
    rod = default_tool0_from_phantom()
    cell = TrueCell.sample(2, model, rod, CellErrorSizes())
    rng = np.random.default_rng(2)  # the cell's noise draws (repeatability, encoders)
    pts = phantom.centres_phantom_mm
    s = _settings()
    volume = ScanVolume(fov_radius_mm=s.fov_radius_mm, half_length_mm=s.n_slices * s.slice_spacing_mm / 2)
    y = frames.transform_from_xyz_rpy([1.0, -2.0, 3.0], [10.0, -5.0, 30.0]) @ frames.invert(
        cell.robot_from_tool0_true(START_JOINTS_RAD) @ cell.tool0_from_phantom
    )
    first = simulate_pose_scan(
        cell, y, START_JOINTS_RAD, phantom, s, work / "start", rng, frame_of_reference_uid=FOR_UID
    )
    nominal_mm = frames.apply(model.robot_from_tool0(first.joints_reported_rad) @ rod, pts)
    reg0 = register_points(nominal_mm, first.detections_image_mm, phantom=phantom)
    plan = plan_poses(
        reg0.image_from_robot,
        chain,
        rod,
        pts,
        first.joints_reported_rad,
        volume=volume,
        params=PlannerParams(n_poses=N_POSES, shift_mm=18.0),
    )
    scans, entries = [], []
    for i, q in enumerate(plan.joints_rad):
        scans.append(
            simulate_pose_scan(
                cell, y, q, phantom, s, work / f"pose-{i:02d}" / "dicom", rng, frame_of_reference_uid=FOR_UID
            )
        )
        entries.append(
            {"scan_dir": f"pose-{i:02d}/dicom", "joints_rad": scans[-1].joints_reported_rad.tolist()}
        )
    poses_file = _write_json(work / "POSES.json", {"robot_model": "tx60", "poses": entries})
    caldir = work / "cal"
    assert main(["calibrate", "run", str(poses_file), "--out", str(caldir), "--drop-weak"]) == 0
    # the O-arm is moved; one registration scan at a pose of its own
    y2 = frames.transform_from_xyz_rpy([8.0, -6.0, 4.0], [2.0, -3.0, 4.0]) @ y
    cand, _, _ = feasible_poses(
        y2,
        chain,
        rod,
        pts,
        START_JOINTS_RAD,
        volume=volume,
        params=PlannerParams(tilts_deg=(0.0, 20.0, 40.0), shift_mm=10.0),
    )
    moved = simulate_pose_scan(
        cell, y2, cand[len(cand) // 2], phantom, s, work / "moved", rng, frame_of_reference_uid=FOR_UID + ".1"
    )
    joints_file = _write_json(work / "JOINTS.json", {"joints_rad": moved.joints_reported_rad.tolist()})
    reg_cal, reg_nom = work / "reg-cal.json", work / "reg-nom.json"
    assert (
        main(
            [
                "register",
                str(work / "moved"),
                "--joints",
                str(joints_file),
                "--calibration",
                str(caldir),
                "--json",
                str(reg_cal),
            ]
        )
        == 0
    )
    assert main(["register", str(work / "moved"), "--joints", str(joints_file), "--json", str(reg_nom)]) == 0
    y_cal = np.array(json.loads(reg_cal.read_text())["image_from_robot"])
    y_nom = np.array(json.loads(reg_nom.read_text())["image_from_robot"])
    calibration = json.loads((caldir / "calibration.json").read_text())
    cal_model = RobotModel.load(caldir / "robot.urdf")
    cal_rod = np.array(calibration["tool0_from_phantom"])
    planned = {tuple(np.round(q, 6)) for q in plan.joints_rad}
    others = [q for q in cand if tuple(np.round(q, 6)) not in planned]
    held = [others[int(i)] for i in np.linspace(0, len(others) - 1, N_HELD_OUT).round()]
    cal_err, nom_err = [], []
    for q in held:
        truth = frames.apply(cell.image_from_phantom_true(y2, q, rng), pts)
        q_rep = cell.reported_joints(q, rng)
        cal_err.append(
            np.linalg.norm(
                frames.apply(y_cal @ cal_model.robot_from_tool0(q_rep) @ cal_rod, pts) - truth, axis=1
            )
        )
        nom_err.append(
            np.linalg.norm(frames.apply(y_nom @ model.robot_from_tool0(q_rep) @ rod, pts) - truth, axis=1)
        )
    return Outcome(np.concatenate(cal_err), np.concatenate(nom_err), calibration, caldir, scans)


def test_every_pose_was_detected_and_matched(outcome: Outcome) -> None:
    assert len(outcome.calibration["poses"]) == N_POSES
    assert all(len(p["sphere_residuals_mm"]) >= 26 for p in outcome.calibration["poses"])
    assert outcome.calibration["outlier_poses"] == []


def test_held_out_error_after_calibration_meets_the_issue_targets(outcome: Outcome) -> None:
    cal, nom = outcome.calibrated_mm, outcome.nominal_mm
    assert cal.shape == (N_HELD_OUT * 28,)
    assert float(cal.mean()) <= MAX_MEAN_MM, (float(cal.mean()), float(nom.mean()))
    assert float(cal.max()) <= MAX_MAX_MM, float(cal.max())
    assert float(nom.mean()) >= MIN_IMPROVEMENT * float(cal.mean()), (float(cal.mean()), float(nom.mean()))


def test_leave_one_pose_out_predicts_the_held_out_error(outcome: Outcome) -> None:
    # LOPO without FLE, + re-registration; the held-out poses here are like the calibration's
    # (predicted_held_out_rms_mm is now the posterior over the larger working volume).
    lopo = outcome.calibration["lopo_predicted_rms_mm"]
    held_rms = math.sqrt(float(np.mean(outcome.calibrated_mm**2)))
    assert held_rms / LOPO_FACTOR <= lopo <= held_rms * LOPO_FACTOR, (lopo, held_rms)


def test_calibration_files_carry_figures_and_provenance(outcome: Outcome) -> None:
    c = outcome.calibration
    prov = c["provenance"]
    assert [s["series_uid"] for s in prov["scans"]] == [s.series_uid for s in outcome.scans]
    assert prov["frame_of_reference_uid"] == FOR_UID
    assert len(prov["config_sha256"]) == 64 and prov["software"].startswith("oarmreg ")
    assert c["identification"]["condition_number"] <= 100.0
    assert c["dropped_parameters"], (
        "the small volume cannot excite every parameter; the drop must be reported"
    )
    assert all(p["std_error"] > 0 for p in c["parameters"])
    assert prov["calibration_id"] in (outcome.caldir / "robot.urdf").read_text(encoding="utf-8")
