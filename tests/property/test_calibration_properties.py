"""Hypothesis property of the multi-pose calibration (issue #10 "Done when").

For any draw of joint-origin errors, zero offsets, rod error, O-arm placement and a pose set
spreading every joint, noise-free sphere centres are explained exactly: predictions at held-out
poses agree with the truth within 1e-6 mm.  Every number is drawn by hypothesis strategies.
"""

from __future__ import annotations

import math

import numpy as np
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from numpy.typing import NDArray

from mocks.cell import SPREAD_BASE_JOINTS_RAD, SPREAD_OFFSETS_RAD
from registration.calibration.model import (
    predict_image_mm,
)
from registration.calibration.records import (
    CalibrationParams,
    MatchedPose,
)
from registration.calibration.solver import (
    calibrate,
)
from registration.calibration.urdf import read_chain, rotation_about
from registration.model import frames
from registration.model.kinematics import RobotModel, default_tool0_from_phantom
from registration.model.phantom import load_phantom
from tests.helpers.paths import CONFIGS

F64 = NDArray[np.float64]
SETTINGS = settings(max_examples=15, deadline=None, suppress_health_check=[HealthCheck.too_slow])
EXACT_MM = 1e-6
NOMINAL = read_chain(RobotModel.load("tx60").urdf_path)
PTS = load_phantom(CONFIGS / "phantoms" / "bai2018_cube.toml").centres_phantom_mm
BASE_JOINTS_RAD = SPREAD_BASE_JOINTS_RAD
TEMPLATE_RAD = SPREAD_OFFSETS_RAD
"""A spread of every joint by ≥ ±1 rad; each drawn pose set moves these by up to ±0.35 rad per joint
(a pose set with all poses alike is a refusal case, tested in tests/unit)."""
POSE_JITTER_RAD = 0.35
LOOSE = CalibrationParams(max_condition=1e5, leave_one_out=False)
"""Identifiability is not under test here (random pose sets); exactness is."""


def _motion(v: list[float], rot_scale_rad: float, trans_scale_mm: float) -> F64:
    w = np.asarray(v[:3]) * rot_scale_rad
    ang = float(np.linalg.norm(w))
    axis = w / ang if ang > 0 else np.array([0.0, 0.0, 1.0])
    return frames.make_transform(rotation_about(axis, np.array([ang]))[0], np.asarray(v[3:]) * trans_scale_mm)


unit = st.floats(min_value=-1.0, max_value=1.0, allow_nan=False)
six = st.lists(unit, min_size=6, max_size=6)
origin_errors = st.lists(six, min_size=6, max_size=6)
offsets = st.lists(unit, min_size=6, max_size=6)
pose_sets = st.lists(six, min_size=10, max_size=12)
held_out = st.lists(six, min_size=5, max_size=5)
placements = st.tuples(
    st.lists(st.floats(min_value=-500.0, max_value=500.0), min_size=3, max_size=3),
    st.lists(st.floats(min_value=-180.0, max_value=180.0), min_size=3, max_size=3),
)


@SETTINGS
@given(errors=origin_errors, offs=offsets, rod_err=six, poses=pose_sets, held=held_out, place=placements)
def test_noise_free_errors_are_recovered_at_held_out_poses(
    errors: list[list[float]],
    offs: list[float],
    rod_err: list[float],
    poses: list[list[float]],
    held: list[list[float]],
    place: tuple[list[float], list[float]],
) -> None:
    # errors up to 0.3 mm / 0.03° per axis and 0.03° offsets (2.5 × the σ), rod ≤ 1 mm / 0.6°
    m = np.stack(
        [
            mi
            @ _motion(e, math.radians(0.03), 0.3)
            @ frames.make_transform(rotation_about(a, np.array([math.radians(0.03) * d]))[0], np.zeros(3))
            for mi, e, a, d in zip(NOMINAL.parent_from_joint, errors, NOMINAL.axes, offs, strict=True)
        ]
    )
    true = NOMINAL.with_origins(m)
    rod = default_tool0_from_phantom() @ _motion(rod_err, math.radians(0.35), 0.6)
    y = frames.transform_from_xyz_rpy(place[0], place[1])
    obs = []
    for i, p in enumerate(poses):
        q = BASE_JOINTS_RAD + TEMPLATE_RAD[i] + POSE_JITTER_RAD * np.asarray(p)
        obs.append(
            MatchedPose(
                f"p{i}", q, np.arange(len(PTS)), frames.apply(y @ true.robot_from_tool0(q) @ rod, PTS)
            )
        )
    result = calibrate(obs, NOMINAL, default_tool0_from_phantom(), PTS, LOOSE)
    for h in held:
        q = BASE_JOINTS_RAD + np.asarray(h) * [1.5, 1.0, 0.8, 2.5, 1.2, 2.5]  # anywhere within the limits
        truth = frames.apply(y @ true.robot_from_tool0(q) @ rod, PTS)
        assert float(np.abs(predict_image_mm(result, q, PTS) - truth).max()) <= EXACT_MM
