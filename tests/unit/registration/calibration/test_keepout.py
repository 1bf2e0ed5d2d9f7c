"""registration/calibration/keepout.py: clearance to keep-out boxes, short-travel pose order."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from registration.calibration.keepout import (
    KeepOutBox,
    checked_points_robot_mm,
    keep_out_report,
    order_for_short_travel,
    travel_rad,
)
from registration.calibration.urdf import read_chain
from registration.model.frames import apply, transform_from_xyz_rpy
from registration.model.kinematics import RobotModel, default_tool0_from_phantom

CHAIN = read_chain(RobotModel.load("tx60").urdf_path)
ROD = default_tool0_from_phantom()
angle = st.floats(-1.5, 1.5, allow_nan=False)
joints = st.lists(angle, min_size=6, max_size=6).map(np.array)
coord = st.floats(-500, 500, allow_nan=False)


@settings(max_examples=40, deadline=None)
@given(q=joints)
def test_checked_points_end_at_tool0_and_the_phantom(q: np.ndarray) -> None:
    names, pts = checked_points_robot_mm(CHAIN, q, ROD)
    t = CHAIN.robot_from_tool0(q)
    assert names[-2:] == ["tool0", "phantom"] and len(pts) == CHAIN.n_joints + 2
    np.testing.assert_allclose(pts[-2], t[:3, 3], atol=1e-9)
    np.testing.assert_allclose(pts[-1], (t @ ROD)[:3, 3], atol=1e-9)


@settings(max_examples=60, deadline=None)
@given(
    lo=st.tuples(coord, coord, coord),
    size=st.tuples(*[st.floats(1, 300)] * 3),
    p=st.tuples(coord, coord, coord),
)
def test_signed_distance_matches_the_clamped_point(lo: tuple, size: tuple, p: tuple) -> None:  # type: ignore[type-arg]
    hi = tuple(a + s for a, s in zip(lo, size, strict=True))
    box = KeepOutBox("b", lo, hi)
    d = float(box.signed_distance_mm(np.array(p))[0])
    clamped = np.clip(p, lo, hi)
    inside = bool(np.all((np.array(p) > lo) & (np.array(p) < hi)))
    if inside:
        assert d <= 0
    else:
        assert d == pytest.approx(float(np.linalg.norm(np.array(p) - clamped)), abs=1e-9)


def test_a_box_around_the_phantom_is_reported_near() -> None:
    q = np.array([0.2, 0.3, 1.6, 0.1, 0.8, -0.3])
    y = transform_from_xyz_rpy([10.0, -20.0, 30.0], [5.0, 0.0, 90.0])
    centre = apply(y, (CHAIN.robot_from_tool0(q) @ ROD)[:3, 3][None, :])[0]
    table = KeepOutBox("table", tuple(centre - 20), tuple(centre + 20))
    far = KeepOutBox("far", tuple(centre + 5000), tuple(centre + 5100))
    (r,) = keep_out_report(y, CHAIN, ROD, q[None, :], [far, table])
    assert r.box == "table" and r.near and r.clearance_mm < 0
    (r,) = keep_out_report(y, CHAIN, ROD, q[None, :], [far])
    assert not r.near and r.clearance_mm > 4000
    assert keep_out_report(y, CHAIN, ROD, q[None, :], []) == []


def test_an_inverted_box_is_refused() -> None:
    with pytest.raises(ValueError, match="below"):
        KeepOutBox("bad", (0, 0, 0), (-1, 1, 1))


@settings(max_examples=30, deadline=None)
@given(start=joints, poses=st.lists(joints, min_size=2, max_size=7))
def test_short_travel_order_is_a_permutation_never_longer(start: np.ndarray, poses: list) -> None:  # type: ignore[type-arg]
    q = np.array(poses)
    order = order_for_short_travel(start, q)
    assert sorted(order) == list(range(len(q)))
    assert travel_rad(start, q, order) <= travel_rad(start, q, list(range(len(q)))) + 1e-12
