"""The planner's poses, rendered: every pose images every sphere ≥ 5 mm inside (issue #20).

A seeded :class:`mocks.cell.TrueCell` (issue #10 error sizes) holds the phantom ~25 mm off the
centre of a small scan volume (0.8 mm pixels, 190 × 190 (76 mm FOV radius) × 110 slices of 1 mm,
90 views, so 7 scans simulate in ~10 s).  The first scan is written as DICOM, reloaded, detected
and registered with the nominal model; the planner gets the scan's real volume from the loaded
series' geometry (what ``oarmreg register`` writes as ``series_geometry``).  Every planned pose is
then simulated through the true cell, written, reloaded and detected: each of the 28 spheres must be
detected within 1 mm of its true centre, and its true centre ≥ 5 mm inside the volume.

Control (geometry only, no rendering): planning in a volume centred on the phantom instead — what
the planner did before issue #20 — puts some sphere of some pose less than 5 mm from the edge (or
outside), so the test above could fail.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from mocks.cell import CellErrorSizes, TrueCell, simulate_pose_scan
from mocks.oarm.simulator import AcquisitionSettings
from registration.calibration.planner import PlannerParams, ScanVolume, plan_poses
from registration.calibration.urdf import read_chain
from registration.dicom import load_series
from registration.imaging.scan_geometry import series_geometry
from registration.matching.register import register_points
from registration.model import frames
from registration.model.kinematics import RobotModel, default_tool0_from_phantom

START_JOINTS_RAD = np.array([0.2, -0.15, 1.75, 0.3, 0.6, -0.9])
FOR_UID = "1.2.826.0.1.3680043.8.498.2020"
PHANTOM_OFFSET_MM = (20.0, -12.0, 8.0)
"""Where the phantom sits relative to the volume centre at the start pose (24.7 mm off)."""
N_POSES = 6
MIN_INSIDE_MM = 5.0
"""Issue #10: every sphere ≥ 5 mm inside the scan volume and FOV."""
MATCH_MM = 1.0
"""A detection within this of a true centre images that sphere (detection error ≈ 0.07 mm)."""


def _settings() -> AcquisitionSettings:
    return AcquisitionSettings.preset("small", rows=190, columns=190, pixel_mm=0.8, n_slices=110, n_views=90)


def test_planned_poses_image_every_sphere_in_an_off_centre_volume(phantom: Any, tmp_path: Path) -> None:
    model = RobotModel.load("tx60")
    chain = read_chain(model.urdf_path)
    rod = default_tool0_from_phantom()
    cell = TrueCell.sample(5, model, rod, CellErrorSizes())
    rng = np.random.default_rng(5)
    pts = phantom.centres_phantom_mm
    s = _settings()
    y = frames.transform_from_xyz_rpy(PHANTOM_OFFSET_MM, [10.0, -5.0, 30.0]) @ frames.invert(
        cell.robot_from_tool0_true(START_JOINTS_RAD) @ cell.tool0_from_phantom
    )
    first = simulate_pose_scan(
        cell, y, START_JOINTS_RAD, phantom, s, tmp_path / "start", rng, frame_of_reference_uid=FOR_UID
    )
    volume = series_geometry(load_series(tmp_path / "start")).scan_volume()
    reg0 = register_points(
        frames.apply(model.robot_from_tool0(first.joints_reported_rad) @ rod, pts),
        first.detections_image_mm,
        phantom=phantom,
    )
    params = PlannerParams(n_poses=N_POSES, shift_mm=12.0)
    plan = plan_poses(
        reg0.image_from_robot, chain, rod, pts, first.joints_reported_rad, volume=volume, params=params
    )
    assert len(plan.joints_rad) == N_POSES

    # control: a volume of the same size centred on the phantom (the old planner) leaves spheres short
    phantom_centre = frames.apply(reg0.image_from_robot @ model.robot_from_tool0(START_JOINTS_RAD) @ rod, pts)
    wrong = ScanVolume(
        tuple(float(v) for v in phantom_centre.mean(axis=0)),
        volume.fov_radius_mm,
        volume.half_length_mm,
        volume.axis_image,
    )
    bad = plan_poses(
        reg0.image_from_robot, chain, rod, pts, first.joints_reported_rad, volume=wrong, params=params
    )
    bad_margins = [
        float(volume.inside_margin_mm(frames.apply(cell.image_from_phantom_true(y, q), pts)[None])[0])
        for q in bad.joints_rad
    ]
    assert min(bad_margins) < MIN_INSIDE_MM, bad_margins

    for i, q in enumerate(plan.joints_rad):
        scan = simulate_pose_scan(
            cell, y, q, phantom, s, tmp_path / f"pose-{i:02d}", rng, frame_of_reference_uid=FOR_UID
        )
        truth = frames.apply(scan.truth_image_from_phantom, pts)
        margin = float(volume.inside_margin_mm(truth[None])[0])
        assert margin >= MIN_INSIDE_MM, f"pose {i}: a sphere only {margin:.1f} mm inside"
        det = scan.detections_image_mm
        nearest = np.linalg.norm(truth[:, None] - det[None], axis=-1).min(axis=1)
        missing = np.flatnonzero(nearest > MATCH_MM)
        assert not missing.size, (
            f"pose {i}: spheres {missing.tolist()} not imaged (nearest {nearest[missing]})"
        )


def test_every_pose_of_a_default_plan_keeps_every_sphere_inside_and_one_renders(
    phantom: Any, tmp_path: Path
) -> None:
    """Issue #33: the planner's own count (no ``n_poses``) in an O-arm-sized volume (212 mm FOV ×
    160 mm; 1.06 mm pixels, 1 mm slices, 90 views so one scan simulates in seconds), from a registration of
    the first scan (its detections: truth + 0.05 mm noise): every sphere of every planned pose
    ≥ 5 mm inside by the TRUE cell, and the pose with the least margin, rendered (simulator →
    DICOM → detection), images all 28 spheres."""
    model = RobotModel.load("tx60")
    chain = read_chain(model.urdf_path)
    rod = default_tool0_from_phantom()
    cell = TrueCell.sample(33, model, rod, CellErrorSizes())
    rng = np.random.default_rng(33)
    pts = phantom.centres_phantom_mm
    s = AcquisitionSettings.preset(
        "small", rows=200, columns=200, pixel_mm=1.06, n_slices=160, slice_spacing_mm=1.0, n_views=90
    )
    volume = ScanVolume(fov_radius_mm=s.fov_radius_mm, half_length_mm=s.n_slices * s.slice_spacing_mm / 2)
    y = frames.transform_from_xyz_rpy(PHANTOM_OFFSET_MM, [10.0, -5.0, 30.0]) @ frames.invert(
        cell.robot_from_tool0_true(START_JOINTS_RAD) @ cell.tool0_from_phantom
    )
    detected = frames.apply(cell.image_from_phantom_true(y, START_JOINTS_RAD, rng), pts)
    q_rep = cell.reported_joints(START_JOINTS_RAD, rng)
    reg0 = register_points(
        frames.apply(model.robot_from_tool0(q_rep) @ rod, pts),
        detected + rng.normal(0.0, 0.05 / np.sqrt(3.0), detected.shape),
        phantom=phantom,
    )
    plan = plan_poses(reg0.image_from_robot, chain, rod, pts, q_rep, volume=volume)
    assert plan.count_reason != "forced" and len(plan.joints_rad) >= 10
    margins = [
        float(volume.inside_margin_mm(frames.apply(cell.image_from_phantom_true(y, q), pts)[None])[0])
        for q in plan.joints_rad
    ]
    assert min(margins) >= MIN_INSIDE_MM, margins
    q = plan.joints_rad[int(np.argmin(margins))]
    scan = simulate_pose_scan(
        cell, y, q, phantom, s, tmp_path / "tightest", rng, frame_of_reference_uid=FOR_UID
    )
    truth = frames.apply(scan.truth_image_from_phantom, pts)
    assert float(volume.inside_margin_mm(truth[None])[0]) >= MIN_INSIDE_MM
    nearest = np.linalg.norm(truth[:, None] - scan.detections_image_mm[None], axis=-1).min(axis=1)
    assert np.all(nearest <= MATCH_MM), nearest
