"""The robust solve of the calibration: scipy ``least_squares`` with a per-sphere soft-L1 loss."""

from __future__ import annotations

from typing import Any

import numpy as np

from mocks.cell import SPREAD_JOINTS_RAD
from registration.calibration.fit import (
    _sphere_soft_l1,
)
from registration.calibration.records import (
    CalibrationParams,
    MatchedPose,
)
from registration.calibration.solver import (
    calibrate,
)
from registration.calibration.urdf import read_chain
from registration.model import frames
from registration.model.kinematics import RobotModel, default_tool0_from_phantom

JOINTS_RAD = SPREAD_JOINTS_RAD
"""The poses of ``test_calibration.py`` beside this file (well-conditioned for the full set)."""


def test_sphere_soft_l1_is_soft_l1_of_each_sphere_distance() -> None:
    z = np.random.default_rng(0).uniform(0.0, 30.0, 3 * 7)
    rho = _sphere_soft_l1(z)
    assert rho.shape == (3, z.size)
    s = z.reshape(-1, 3).sum(axis=1)
    np.testing.assert_allclose(rho[0].reshape(-1, 3).sum(axis=1), 2.0 * (np.sqrt(1.0 + s) - 1.0), rtol=1e-14)
    # ρ′ is the derivative of the sphere's ρ with respect to its s, shared by its three components
    h = 1e-6
    d = (2.0 * (np.sqrt(1.0 + s + h) - 1.0) - 2.0 * (np.sqrt(1.0 + s - h) - 1.0)) / (2 * h)
    np.testing.assert_allclose(rho[1], np.repeat(d, 3), rtol=1e-8)


def test_fit_with_a_wrong_sphere_does_not_depend_on_the_image_axes(phantom: Any) -> None:
    """A per-sphere loss weighs a 3-D distance: rotating the image frame changes nothing."""
    chain = read_chain(RobotModel.load("tx60").urdf_path)
    rod = default_tool0_from_phantom()
    pts = np.asarray(phantom.centres_phantom_mm)
    gen = np.random.default_rng(4)
    y = frames.transform_from_xyz_rpy([300.0, -100.0, 500.0], [10.0, 80.0, -30.0])
    meas = [
        frames.apply(y @ chain.robot_from_tool0(q) @ rod, pts) + gen.normal(0, 0.04, pts.shape)
        for q in JOINTS_RAD
    ]
    meas[2][5] += [1.5, -1.0, 0.8]  # a wrong match: ≫ robust_scale_mm
    turn = frames.transform_from_xyz_rpy([5.0, -3.0, 2.0], [35.0, -20.0, 60.0])
    params = CalibrationParams(leave_one_out=False)
    out = []
    for a in (np.eye(4), turn):
        poses = [
            MatchedPose(f"p{i}", q, np.arange(len(pts)), frames.apply(a, m))
            for i, (q, m) in enumerate(zip(JOINTS_RAD, meas, strict=True))
        ]
        out.append(calibrate(poses, chain, rod, pts, params))
    np.testing.assert_allclose(out[1].values, out[0].values, atol=1e-7)
    np.testing.assert_allclose(out[1].pose_rms_mm, out[0].pose_rms_mm, atol=1e-7)
    np.testing.assert_allclose(out[1].std_errors, out[0].std_errors, rtol=1e-5)
    assert out[0].sphere_residuals_mm[2][5] > 1.0  # the wrong sphere is not pulled onto the model
