"""The pose planner plans from any scan it can register (issue #33).

Before: ``solve_ik`` raised ``numpy.linalg.LinAlgError: Singular matrix`` from the registrations of
some scans, since the rotation residual divided by sin θ, which vanishes at 180° (candidates whose
orientation is turned half a turn from the start pose's).  The registrations here are taken at the
demo's home pose, the benches' start pose, and two poses the planner itself proposed from those
two, where the old IK raised; all four must plan, and a volume nothing reaches must be refused
with the reason.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from numpy.typing import NDArray

from registration.calibration.planner import PlannerParams, ScanVolume, plan_poses
from registration.calibration.sampling import _pose_error, solve_ik
from registration.calibration.urdf import read_chain, rotation_about
from registration.errors import PlanningError
from registration.model import frames
from registration.model.kinematics import RobotModel, default_tool0_from_phantom
from registration.model.phantom import load_phantom
from tests.helpers.paths import CONFIGS

F64 = NDArray[np.float64]
CHAIN = read_chain(RobotModel.load("tx60").urdf_path)
ROD = default_tool0_from_phantom()
PTS = load_phantom(CONFIGS / "phantoms" / "bai2018_cube.toml").centres_phantom_mm
HOME_RAD = (0.0, 0.0, math.pi / 2, 0.0, math.pi / 4, 0.0)
"""``oarmreg demo``'s first pose (service/cli/commands/demo.py Q1_RAD)."""
BENCH_START_RAD = (0.2, -0.15, 1.75, 0.3, 0.6, -0.9)
"""The calibration benches' and the render test's first pose."""
CRASHED_FROM_RAD = (
    (0.2913, 0.6182, 2.0051, 0.1585, -1.7385, 0.9515),
    (-0.463, 0.4314, 1.1885, -2.0933, -1.4142, -0.9215),
)
"""Poses of the 10-pose plans from the two poses above (the 4th from the bench start, the 5th from
home) whose registrations the old IK raised on."""
PHANTOM_IN_VOLUME_MM = (28.0, -20.0, 12.0)
"""The phantom 36 mm off the volume centre at the first pose (the test bed's placement)."""


def _image_from_robot(q0: tuple[float, ...]) -> F64:
    return frames.transform_from_xyz_rpy(PHANTOM_IN_VOLUME_MM, [10.0, -5.0, 30.0]) @ frames.invert(
        CHAIN.robot_from_tool0(np.array(q0)) @ ROD
    )


@pytest.mark.parametrize(
    ("first", "start"),
    [
        (HOME_RAD, HOME_RAD),
        (BENCH_START_RAD, BENCH_START_RAD),
        (BENCH_START_RAD, CRASHED_FROM_RAD[0]),
        (HOME_RAD, CRASHED_FROM_RAD[1]),
    ],
)
def test_plans_from_registrations_at_varied_start_poses(
    first: tuple[float, ...], start: tuple[float, ...]
) -> None:
    """The O-arm placed with the phantom 36 mm off its centre at ``first``; a scan at ``start``."""
    y = _image_from_robot(first)
    rng = np.random.default_rng(33)
    # a registration of the scan at ``start``: the placement seen through 0.05 mm detection noise
    y_reg = y @ frames.transform_from_xyz_rpy(rng.normal(0.0, 0.03, 3), rng.normal(0.0, 0.01, 3))
    q0 = np.array(start)
    plan = plan_poses(y_reg, CHAIN, ROD, PTS, q0, volume=ScanVolume(), params=PlannerParams(n_poses=8))
    assert plan.joints_rad.shape == (8, 6)
    assert np.all(np.isfinite(plan.joints_rad))
    assert math.isfinite(plan.predicted_error_mm)
    margin = PlannerParams().margin_mm + PlannerParams().model_error_mm
    for q in plan.joints_rad:
        centres = frames.apply(y_reg @ CHAIN.robot_from_tool0(q) @ ROD, PTS)
        assert float(ScanVolume().inside_margin_mm(centres[None])[0]) >= margin - 1e-9


def test_a_volume_out_of_reach_is_refused_with_the_reason() -> None:
    y = _image_from_robot(BENCH_START_RAD)
    far = ScanVolume(centre_image_mm=(2000.0, 0.0, 0.0))
    with pytest.raises(PlanningError, match=r"out of the arm's reach.*Centre the O-arm"):
        plan_poses(y, CHAIN, ROD, PTS, np.array(BENCH_START_RAD), volume=far)


@settings(max_examples=25, deadline=None)
@given(
    axis=st.tuples(*[st.floats(-1.0, 1.0)] * 3).filter(lambda a: math.hypot(*a) > 0.1),
    off_deg=st.floats(-1e-3, 1e-3),
)
def test_rotation_residual_is_the_angle_up_to_half_a_turn(
    axis: tuple[float, float, float], off_deg: float
) -> None:
    """At (and within 0.001° of) 180° the rotation residual is still θ × the weight (the old one was
    0 exactly at 180° and amplified rounding by 1 / sin θ next to it)."""
    q = np.array([BENCH_START_RAD])
    t = CHAIN.robot_from_tool0_batch(q)
    theta = math.pi - abs(math.radians(off_deg))
    turn = rotation_about(np.array(axis) / math.hypot(*axis), np.array([theta]))[0]
    target = t.copy()
    target[0, :3, :3] = t[0, :3, :3] @ turn
    r = _pose_error(CHAIN, q, target)[0]
    assert np.allclose(r[:3], 0.0, atol=1e-9)
    assert float(np.linalg.norm(r[3:])) == pytest.approx(100.0 * theta, rel=1e-6)


@settings(max_examples=8, deadline=None)
@given(seed=st.integers(0, 2**32 - 1))
def test_ik_never_raises_and_reaches_reachable_targets(seed: int) -> None:
    """Any seeds (singular wrist, J5 = 0, included) and targets half a turn away: no exception, and
    the targets made by the forward kinematics of joints within the limits are reached from a seed
    within 0.5 rad of them."""
    rng = np.random.default_rng(seed)
    lo, hi = CHAIN.lower_rad + 0.2, CHAIN.upper_rad - 0.2
    truth = rng.uniform(lo, hi, (8, 6))
    seeds = np.clip(truth + rng.uniform(-0.5, 0.5, truth.shape), lo, hi)
    seeds[:2, 4] = 0.0  # wrist singular
    targets = CHAIN.robot_from_tool0_batch(truth)
    flipped = targets.copy()
    flipped[:, :3, :3] = (
        targets[:, :3, :3] @ rotation_about(np.array([0.0, 0.0, 1.0]), np.array([math.pi]))[0]
    )
    _, err_far = solve_ik(CHAIN, flipped, seeds)
    assert not np.any(np.isnan(err_far))
    q, err = solve_ik(CHAIN, targets, seeds)
    assert np.all(np.isfinite(q))
    assert float(np.median(err)) < 1e-4, err
