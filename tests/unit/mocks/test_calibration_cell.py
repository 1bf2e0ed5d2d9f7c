"""The true / exact cell of the simulator (mocks/cell.py, design.md §8)."""

from __future__ import annotations

import math
from dataclasses import replace
from typing import Any

import numpy as np
import pytest

from mocks.cell import SPREAD_JOINTS_RAD, CellErrorSizes, ExactCell, TrueCell
from registration.calibration.records import (
    MatchedPose,
)
from registration.calibration.solver import (
    calibrate,
)
from registration.calibration.urdf import read_chain
from registration.matching.rigid import rotation_difference_deg
from registration.model import frames
from registration.model.kinematics import RobotModel, default_tool0_from_phantom

Y = frames.transform_from_xyz_rpy([300.0, -100.0, 500.0], [10.0, 80.0, -30.0])
JOINTS = SPREAD_JOINTS_RAD
NO_NOISE = CellErrorSizes(sag_j2j3_rms_deg=0.0, repeatability_mm=0.0, encoder_noise_rad=0.0)


@pytest.fixture(scope="module")
def model() -> RobotModel:
    return RobotModel.load("tx60")


def test_exact_cell_is_the_nominal_robot_and_rod(model: RobotModel) -> None:
    rod = default_tool0_from_phantom()
    cell = ExactCell.sample(5, model, rod)
    gen = np.random.default_rng(0)
    for q in np.clip(JOINTS, model.lower_rad, model.upper_rad):
        np.testing.assert_allclose(
            cell.image_from_phantom_true(Y, q, gen), Y @ model.robot_from_tool0(q) @ rod, atol=1e-9
        )
        np.testing.assert_array_equal(cell.reported_joints(q, gen), q)


def test_true_cell_is_seeded_and_sized_as_configured(model: RobotModel) -> None:
    rod = default_tool0_from_phantom()
    a, b, c = (TrueCell.sample(s, model, rod) for s in (3, 3, 4))
    np.testing.assert_array_equal(a.chain.parent_from_joint, b.chain.parent_from_joint)
    assert not np.allclose(a.chain.parent_from_joint, c.chain.parent_from_joint)
    rod_err = frames.invert(rod) @ a.tool0_from_phantom
    assert np.linalg.norm(rod_err[:3, 3]) == pytest.approx(0.8)
    assert rotation_difference_deg(rod_err[:3, :3], np.eye(3)) == pytest.approx(0.4)
    # the cell matters: the nominal model is off by ≥ 0.3 mm on average at the phantom
    nominal = read_chain(model.urdf_path)
    off = [
        np.linalg.norm(
            (a.robot_from_tool0_true(q) @ a.tool0_from_phantom)[:3, 3]
            - (nominal.robot_from_tool0(q) @ rod)[:3, 3]
        )
        for q in JOINTS
    ]
    assert 0.3 <= float(np.mean(off)) <= 5.0, off


def test_encoder_noise_and_repeatability_have_their_sizes(model: RobotModel) -> None:
    cell = TrueCell.sample(3, model, default_tool0_from_phantom())
    gen = np.random.default_rng(1)
    q = JOINTS[1]
    reported = np.stack([cell.reported_joints(q, gen) for _ in range(2000)])
    assert float(np.std(reported - q)) == pytest.approx(1e-5, rel=0.1)
    ideal = cell.robot_from_tool0_true(q)
    scatter = np.stack([cell.robot_from_tool0_true(q, gen)[:3, 3] - ideal[:3, 3] for _ in range(2000)])
    assert math.sqrt(float(np.mean(np.sum(scatter**2, axis=1)))) == pytest.approx(0.02, rel=0.1)


def test_sag_is_not_captured_by_the_geometric_model(model: RobotModel, phantom: Any) -> None:
    """With only geometric errors the fit is exact; the J2/J3 sag leaves a residual."""
    rod = default_tool0_from_phantom()
    pts = phantom.centres_phantom_mm
    nominal = read_chain(model.urdf_path)
    rms = {}
    for label, sizes in (("geometric", NO_NOISE), ("with sag", replace(NO_NOISE, sag_j2j3_rms_deg=0.003))):
        cell = TrueCell.sample(3, model, rod, sizes)
        poses = [
            MatchedPose(
                f"p{i}", q, np.arange(len(pts)), frames.apply(cell.image_from_phantom_true(Y, q), pts)
            )
            for i, q in enumerate(JOINTS)
        ]
        rms[label] = calibrate(poses, nominal, rod, pts).fit_rms_mm
    assert rms["geometric"] < 1e-7
    assert rms["with sag"] > 1e-3, rms
