"""Stillness coverage (issue 19 item 7): streamed links are judged by frame count, polled links by
receive gaps; a window the link did not watch, a reconnect and missing frames are ``incomplete``,
never ``moved``."""

from __future__ import annotations

from typing import Any

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from registration.model.stillness import (
    VERDICT_INCOMPLETE,
    VERDICT_MOVED,
    VERDICT_STILL,
    StillnessResult,
    assess_stillness,
    stream_period_s,
)

PERIOD_S = 0.02
WINDOW_S = 2.0
END_T_S = 100.0
Q = (0.1, -0.3, 1.9, 0.0, 0.8, 0.0)


def stream(t0: float, t1: float) -> np.ndarray:
    """Send times of a 50 Hz stream in [t0, t1]."""
    return np.arange(t0, t1 + 1e-9, PERIOD_S)


def late_burst(sent: np.ndarray, at_t_s: float, delay_s: float) -> np.ndarray:
    """Receive times when the receiver could not read for ``delay_s`` from ``at_t_s``: every frame sent
    meanwhile arrives intact, in order, in one burst at the end (what TCP does)."""
    recv = sent.copy()
    held = (sent >= at_t_s) & (sent < at_t_s + delay_s)
    recv[held] = at_t_s + delay_s + np.arange(int(held.sum())) * 1e-5
    return np.maximum.accumulate(recv)


def still_joints(n: int) -> np.ndarray:
    return np.tile(Q, (n, 1))


def judge(t: np.ndarray, **kw: Any) -> StillnessResult:
    return assess_stillness(
        t, still_joints(t.size), window_end_t_s=END_T_S, window_s=WINDOW_S, max_gap_s=0.25, **kw
    )


def test_a_receive_delay_of_a_streamed_link_is_not_a_hole_in_the_history() -> None:
    t = late_burst(stream(90.0, END_T_S + 0.5), at_t_s=99.0, delay_s=0.35)
    res = judge(t, period_s=PERIOD_S)
    assert res.verdict == VERDICT_STILL and res.still, res.reason
    assert res.max_receive_gap_s > 0.3
    # the same receive times from a polled link: the poller did not run, nobody watched
    polled = judge(t)
    assert polled.verdict == VERDICT_INCOMPLETE and not polled.still
    assert polled.reason.startswith("joint history incomplete")


def test_frames_genuinely_missing_from_a_stream_are_incomplete() -> None:
    sent = stream(90.0, END_T_S + 0.5)
    t = sent[(sent < 99.0) | (sent >= 99.4)]  # the controller sent nothing for 0.4 s
    res = judge(t, period_s=PERIOD_S)
    assert res.verdict == VERDICT_INCOMPLETE, res.reason
    assert "missing" in res.reason and res.missing_frames == pytest.approx(20, abs=1.5)


def test_a_window_that_starts_before_the_link_connected_is_incomplete_not_moved() -> None:
    connected = END_T_S - 0.5
    t = stream(connected, END_T_S)
    res = judge(t, period_s=PERIOD_S, watched_from_t_s=connected)
    assert res.verdict == VERDICT_INCOMPLETE
    assert "before the robot link connected" in res.reason


def test_a_reconnect_inside_the_window_is_incomplete() -> None:
    t = stream(90.0, END_T_S)
    sessions = np.where(t < 99.5, 1, 2)
    res = judge(t, period_s=PERIOD_S, sessions=sessions)
    assert res.verdict == VERDICT_INCOMPLETE and "reconnected" in res.reason


def test_motion_is_moved_even_where_the_history_has_a_hole() -> None:
    sent = stream(90.0, END_T_S)
    t = sent[(sent < 99.0) | (sent >= 99.5)]
    q = still_joints(t.size)
    q[t < 98.8, 1] += 0.01  # J2 was 0.01 rad elsewhere early in the window
    res = assess_stillness(t, q, window_end_t_s=END_T_S, window_s=WINDOW_S, period_s=PERIOD_S)
    assert res.verdict == VERDICT_MOVED and res.reason.startswith("robot moved")
    assert "joint 2" in res.reason


@settings(max_examples=50, deadline=None)
@given(
    stall_s=st.floats(0.0, 0.5),
    n_bursts=st.integers(0, 30),
    jitter_s=st.floats(0.0, 0.004),
    seed=st.integers(0, 2**16),
)
def test_the_measured_period_ignores_stalls_bursts_and_jitter(
    stall_s: float, n_bursts: int, jitter_s: float, seed: int
) -> None:
    rng = np.random.default_rng(seed)
    sent = stream(0.0, 60.0)
    sent = sent[(sent < 30.0) | (sent >= 30.0 + stall_s)]
    recv = sent + rng.uniform(0.0, jitter_s, sent.size)
    for at in rng.uniform(1.0, 59.0, n_bursts):
        recv = late_burst(recv, at_t_s=float(at), delay_s=0.3)
    period = stream_period_s(np.sort(recv))
    assert period is not None and abs(period - PERIOD_S) < 0.002


def test_too_short_a_stream_has_no_measured_period() -> None:
    assert stream_period_s(stream(0.0, 0.1)) is None
    with pytest.raises(ValueError, match="period_s"):
        judge(stream(90.0, END_T_S), period_s=0.0)
