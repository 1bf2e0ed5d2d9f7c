"""FK is a rigid motion and composes like the chain it models (issue #5)."""

from __future__ import annotations

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from registration.model.frames import invert
from registration.model.kinematics import RobotModel

TX60 = RobotModel.load("tx60")
TX2_60 = RobotModel.load("tx2_60")


def joints(model: RobotModel) -> st.SearchStrategy[np.ndarray]:
    return st.tuples(
        *[st.floats(float(lo), float(hi)) for lo, hi in zip(model.lower_rad, model.upper_rad, strict=True)]
    ).map(np.array)


@settings(max_examples=60, deadline=None)
@given(q=joints(TX60))
def test_fk_is_rigid(q: np.ndarray) -> None:
    t = TX60.robot_from_tool0(q)
    r = t[:3, :3]
    assert np.allclose(r.T @ r, np.eye(3), atol=1e-12)
    assert abs(np.linalg.det(r) - 1.0) < 1e-12
    assert np.array_equal(t[3], [0, 0, 0, 1])
    # the wrist centre stays within the arm's reach: |p_wrist - shoulder| <= 290 + 310 (+ 20 offset)
    wrist = t[:3, 3] - 70.0 * t[:3, 2]
    assert np.linalg.norm(wrist) <= np.hypot(600.0, 20.0) + 1e-9


@settings(max_examples=60, deadline=None)
@given(q=joints(TX2_60), dq6=st.floats(-1.0, 1.0))
def test_joint6_composes_as_rotation_about_tool_z(q: np.ndarray, dq6: float) -> None:
    q2 = q.copy()
    q2[5] = np.clip(q[5] + dq6, TX2_60.lower_rad[5], TX2_60.upper_rad[5])
    d = q2[5] - q[5]
    rz = np.eye(4)
    rz[:2, :2] = [[np.cos(d), -np.sin(d)], [np.sin(d), np.cos(d)]]
    assert np.allclose(TX2_60.robot_from_tool0(q2), TX2_60.robot_from_tool0(q) @ rz, atol=1e-9)


@settings(max_examples=60, deadline=None)
@given(q=joints(TX60), dq1=st.floats(-1.0, 1.0))
def test_joint1_composes_as_rotation_about_robot_z(q: np.ndarray, dq1: float) -> None:
    q2 = q.copy()
    q2[0] = np.clip(q[0] + dq1, TX60.lower_rad[0], TX60.upper_rad[0])
    d = q2[0] - q[0]
    rz = np.eye(4)
    rz[:2, :2] = [[np.cos(d), -np.sin(d)], [np.sin(d), np.cos(d)]]
    t1, t2 = TX60.robot_from_tool0(q), TX60.robot_from_tool0(q2)
    assert np.allclose(t2, rz @ t1, atol=1e-9)
    assert np.allclose(invert(t1) @ t1, np.eye(4), atol=1e-12)
