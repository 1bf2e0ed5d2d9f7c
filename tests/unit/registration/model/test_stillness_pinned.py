"""assess_stillness pinned field by field before its split into named steps (issue #35).

Each case drives one branch of the rule (docs/safety.md, "Stillness and health"): still; moved by
deviation; moved by a controller ``in_motion`` report; incomplete by no samples, non-finite values, a
late-connected or reconnected link, a receive gap (polled) or missing frames (streamed); the order in
which they win; and each threshold hit exactly (inclusive) and just passed. An ``in_motion`` of
UNKNOWN never reaches this function (only TRUE reports' times do), so "unknown" is ``None`` / empty.
Sample times are multiples of 1/8 s, so the thresholds are hit exactly in binary floating point.
The expected results are the code's answers before the split; any change of behaviour fails here.
The streamed cases are issue 40's rule (a long receive gap not followed by its frames), re-pinned.
"""

# ruff: noqa: E501  (the pinned reasons are compared verbatim)

from __future__ import annotations

import math
from typing import Any

import numpy as np
import pytest

from registration.model.stillness import StillnessResult, assess_stillness

NAN = math.nan

END = 10.0
WIN = 2.0
START = END - WIN  # 8.0
STEP = 0.125  # binary-exact sample times: the thresholds below are hit exactly


def _grid(t0: float = START, t1: float = END, step: float = STEP) -> np.ndarray:
    return np.arange(t0, t1 + step / 2, step)


def _q(t: np.ndarray) -> np.ndarray:
    return np.tile([0.1, 0.2, 1.5, 0.0, 0.7, 0.0], (t.size, 1))


def _kw(t: np.ndarray, q: np.ndarray, **extra: Any) -> dict[str, Any]:
    base: dict[str, Any] = {
        "t_s": t,
        "joints_rad": q,
        "window_end_t_s": END,
        "window_s": WIN,
        "max_deviation_rad": 0.0005,
        "max_gap_s": 0.25,
    }
    return {**base, **extra}


def _moved_joint(delta: float, joint: int = 2) -> dict[str, Any]:
    t = _grid()
    q = _q(t)
    q[t < 9.0, joint] += delta
    return _kw(t, q)


def _with_hole(hole_from: float, hole_to: float, **extra: Any) -> dict[str, Any]:
    t = _grid()
    t = t[(t <= hole_from) | (t >= hole_to)]
    return _kw(t, _q(t), **extra)


def _nonfinite() -> dict[str, Any]:
    t = _grid()
    q = _q(t)
    q[3, 1] = np.nan
    return _kw(t, q)


def _sessions(split_at: float, **extra: Any) -> dict[str, Any]:
    t = _grid()
    return _kw(t, _q(t), sessions=(t >= split_at).astype(int), **extra)


def _streamed(n_frames: int) -> dict[str, Any]:
    t = np.linspace(START, END, n_frames)
    return _kw(t, _q(t), period_s=STEP)


def _streamed_hole(backlog: int) -> dict[str, Any]:
    """A 0.5 s receive gap (8.5 → 9.0 s) followed by ``backlog`` late frames stamped at 9.0 s."""
    t = np.sort(np.concatenate((_grid()[(_grid() <= 8.5) | (_grid() >= 9.0)], np.full(backlog, 9.0))))
    return _kw(t, _q(t), period_s=STEP)


def _before_window_only() -> dict[str, Any]:
    t = _grid(0.0, 7.875)
    return _kw(t, _q(t))


CASES: dict[str, dict[str, Any]] = {
    "still_polled": _kw(_grid(), _q(_grid())),
    "still_unknown_in_motion_none": _kw(_grid(), _q(_grid()), in_motion_t_s=None),
    "still_empty_in_motion": _kw(_grid(), _q(_grid()), in_motion_t_s=[]),
    "still_deviation_exactly_at_limit": _moved_joint(0.0005, joint=3),
    "moved_deviation_just_over_limit": _moved_joint(0.000500001, joint=3),
    "moved_deviation_joint_5": _moved_joint(-0.01, joint=4),
    "moved_in_motion_inside": _kw(_grid(), _q(_grid()), in_motion_t_s=[9.5, 9.75]),
    "moved_in_motion_at_window_start": _kw(_grid(), _q(_grid()), in_motion_t_s=[START]),
    "moved_in_motion_at_window_end": _kw(_grid(), _q(_grid()), in_motion_t_s=[END]),
    "still_in_motion_before_and_after": _kw(_grid(), _q(_grid()), in_motion_t_s=[7.875, 10.125]),
    "moved_deviation_wins_over_in_motion": {**_moved_joint(0.01), "in_motion_t_s": [9.5]},
    "moved_wins_over_reconnect": {**_moved_joint(0.01), "sessions": (_grid() >= 9.0).astype(int)},
    "moved_in_motion_wins_over_watched_late": _kw(
        _grid(), _q(_grid()), in_motion_t_s=[9.5], watched_from_t_s=9.0
    ),
    "incomplete_no_samples": _before_window_only(),
    "incomplete_nonfinite": _nonfinite(),
    "incomplete_watched_late": _kw(_grid(), _q(_grid()), watched_from_t_s=8.5),
    "still_watched_exactly_from_start": _kw(_grid(), _q(_grid()), watched_from_t_s=START),
    "incomplete_reconnect": _sessions(9.0),
    "still_one_session": _sessions(100.0),
    "still_gap_exactly_at_limit": _with_hole(9.0, 9.25),
    "incomplete_gap_over_limit": _with_hole(9.0, 9.375),
    "incomplete_gap_at_window_start": _kw(_grid(8.375), _q(_grid(8.375))),
    "still_gap_at_window_start_exactly_at_limit": _kw(_grid(8.25), _q(_grid(8.25))),
    "incomplete_gap_at_window_end": _kw(_grid(START, 9.625), _q(_grid(START, 9.625))),
    "still_streamed_all_frames": _streamed(17),
    "still_streamed_sparse_without_long_gap": _streamed(13),
    "still_streamed_gap_followed_by_its_frames": _streamed_hole(3),
    "still_streamed_gap_missing_exactly_at_limit": _streamed_hole(1),
    "incomplete_streamed_gap_not_followed": _streamed_hole(0),
    "still_streamed_late_burst": _kw(
        np.concatenate((np.linspace(START, 8.5, 5), np.full(12, 9.9))),
        _q(np.zeros(17)),
        period_s=STEP,
    ),
    "still_single_sample_at_end_window_within_gap": _kw(np.array([9.9]), _q(np.zeros(1)), window_s=0.2),
}

BAD_INPUT: dict[str, dict[str, Any]] = {
    "shape_mismatch": _kw(_grid(), _q(_grid())[:-1]),
    "one_dimensional_joints": _kw(_grid(), np.zeros(_grid().size)),
    "decreasing_times": _kw(_grid()[::-1], _q(_grid())),
    "zero_window": _kw(_grid(), _q(_grid()), window_s=0.0),
    "zero_max_gap": _kw(_grid(), _q(_grid()), max_gap_s=0.0),
    "negative_deviation": _kw(_grid(), _q(_grid()), max_deviation_rad=-1e-9),
    "nan_period": _kw(_grid(), _q(_grid()), period_s=float("nan")),
    "zero_period": _kw(_grid(), _q(_grid()), period_s=0.0),
    "sessions_shape": _kw(_grid(), _q(_grid()), sessions=[0, 0]),
}


EXPECTED: dict[str, StillnessResult] = {
    "still_polled": StillnessResult(
        still=True,
        max_deviation_rad=0.0,
        covered_s=2.0,
        n_samples=17,
        reason="",
        verdict="still",
        max_receive_gap_s=0.125,
        missing_frames=NAN,
    ),
    "still_unknown_in_motion_none": StillnessResult(
        still=True,
        max_deviation_rad=0.0,
        covered_s=2.0,
        n_samples=17,
        reason="",
        verdict="still",
        max_receive_gap_s=0.125,
        missing_frames=NAN,
    ),
    "still_empty_in_motion": StillnessResult(
        still=True,
        max_deviation_rad=0.0,
        covered_s=2.0,
        n_samples=17,
        reason="",
        verdict="still",
        max_receive_gap_s=0.125,
        missing_frames=NAN,
    ),
    "still_deviation_exactly_at_limit": StillnessResult(
        still=True,
        max_deviation_rad=0.0005,
        covered_s=2.0,
        n_samples=17,
        reason="",
        verdict="still",
        max_receive_gap_s=0.125,
        missing_frames=NAN,
    ),
    "moved_deviation_just_over_limit": StillnessResult(
        still=False,
        max_deviation_rad=0.000500001,
        covered_s=2.0,
        n_samples=17,
        reason="robot moved: joint 4 deviated 0.0286° (0.000500 rad > 0.0005 rad) during the 2 s window",
        verdict="moved",
        max_receive_gap_s=0.125,
        missing_frames=NAN,
    ),
    "moved_deviation_joint_5": StillnessResult(
        still=False,
        max_deviation_rad=0.010000000000000009,
        covered_s=2.0,
        n_samples=17,
        reason="robot moved: joint 5 deviated 0.5730° (0.010000 rad > 0.0005 rad) during the 2 s window",
        verdict="moved",
        max_receive_gap_s=0.125,
        missing_frames=NAN,
    ),
    "moved_in_motion_inside": StillnessResult(
        still=False,
        max_deviation_rad=0.0,
        covered_s=2.0,
        n_samples=17,
        reason="robot moved: the controller reported in_motion at t=1.500 s into the 2 s window (2 status report(s) in the window) while the joints deviated 0.000000 rad at most",
        verdict="moved",
        max_receive_gap_s=0.125,
        missing_frames=NAN,
    ),
    "moved_in_motion_at_window_start": StillnessResult(
        still=False,
        max_deviation_rad=0.0,
        covered_s=2.0,
        n_samples=17,
        reason="robot moved: the controller reported in_motion at t=0.000 s into the 2 s window (1 status report(s) in the window) while the joints deviated 0.000000 rad at most",
        verdict="moved",
        max_receive_gap_s=0.125,
        missing_frames=NAN,
    ),
    "moved_in_motion_at_window_end": StillnessResult(
        still=False,
        max_deviation_rad=0.0,
        covered_s=2.0,
        n_samples=17,
        reason="robot moved: the controller reported in_motion at t=2.000 s into the 2 s window (1 status report(s) in the window) while the joints deviated 0.000000 rad at most",
        verdict="moved",
        max_receive_gap_s=0.125,
        missing_frames=NAN,
    ),
    "still_in_motion_before_and_after": StillnessResult(
        still=True,
        max_deviation_rad=0.0,
        covered_s=2.0,
        n_samples=17,
        reason="",
        verdict="still",
        max_receive_gap_s=0.125,
        missing_frames=NAN,
    ),
    "moved_deviation_wins_over_in_motion": StillnessResult(
        still=False,
        max_deviation_rad=0.010000000000000009,
        covered_s=2.0,
        n_samples=17,
        reason="robot moved: joint 3 deviated 0.5730° (0.010000 rad > 0.0005 rad) during the 2 s window",
        verdict="moved",
        max_receive_gap_s=0.125,
        missing_frames=NAN,
    ),
    "moved_wins_over_reconnect": StillnessResult(
        still=False,
        max_deviation_rad=0.010000000000000009,
        covered_s=2.0,
        n_samples=17,
        reason="robot moved: joint 3 deviated 0.5730° (0.010000 rad > 0.0005 rad) during the 2 s window",
        verdict="moved",
        max_receive_gap_s=0.125,
        missing_frames=NAN,
    ),
    "moved_in_motion_wins_over_watched_late": StillnessResult(
        still=False,
        max_deviation_rad=0.0,
        covered_s=2.0,
        n_samples=17,
        reason="robot moved: the controller reported in_motion at t=1.500 s into the 2 s window (1 status report(s) in the window) while the joints deviated 0.000000 rad at most",
        verdict="moved",
        max_receive_gap_s=0.125,
        missing_frames=NAN,
    ),
    "incomplete_no_samples": StillnessResult(
        still=False,
        max_deviation_rad=NAN,
        covered_s=0.0,
        n_samples=0,
        reason="joint history incomplete: no joint samples in the 2 s window",
        verdict="incomplete",
        max_receive_gap_s=NAN,
        missing_frames=NAN,
    ),
    "incomplete_nonfinite": StillnessResult(
        still=False,
        max_deviation_rad=NAN,
        covered_s=0.0,
        n_samples=17,
        reason="joint history incomplete: non-finite joint values in the window",
        verdict="incomplete",
        max_receive_gap_s=NAN,
        missing_frames=NAN,
    ),
    "incomplete_watched_late": StillnessResult(
        still=False,
        max_deviation_rad=0.0,
        covered_s=1.5,
        n_samples=17,
        reason="joint history incomplete: the 2 s window began 0.500 s before the robot link connected, so nobody watched the robot then",
        verdict="incomplete",
        max_receive_gap_s=0.125,
        missing_frames=NAN,
    ),
    "still_watched_exactly_from_start": StillnessResult(
        still=True,
        max_deviation_rad=0.0,
        covered_s=2.0,
        n_samples=17,
        reason="",
        verdict="still",
        max_receive_gap_s=0.125,
        missing_frames=NAN,
    ),
    "incomplete_reconnect": StillnessResult(
        still=False,
        max_deviation_rad=0.0,
        covered_s=0.0,
        n_samples=17,
        reason="joint history incomplete: the robot link reconnected 1 time(s) inside the 2 s window, so frames may be lost",
        verdict="incomplete",
        max_receive_gap_s=0.125,
        missing_frames=NAN,
    ),
    "still_one_session": StillnessResult(
        still=True,
        max_deviation_rad=0.0,
        covered_s=2.0,
        n_samples=17,
        reason="",
        verdict="still",
        max_receive_gap_s=0.125,
        missing_frames=NAN,
    ),
    "still_gap_exactly_at_limit": StillnessResult(
        still=True,
        max_deviation_rad=0.0,
        covered_s=2.0,
        n_samples=16,
        reason="",
        verdict="still",
        max_receive_gap_s=0.25,
        missing_frames=NAN,
    ),
    "incomplete_gap_over_limit": StillnessResult(
        still=False,
        max_deviation_rad=0.0,
        covered_s=1.625,
        n_samples=15,
        reason="joint history incomplete: a 0.375 s gap (> 0.25 s) at 1.000 s into the 2 s window: the link did not watch the whole window",
        verdict="incomplete",
        max_receive_gap_s=0.375,
        missing_frames=NAN,
    ),
    "incomplete_gap_at_window_start": StillnessResult(
        still=False,
        max_deviation_rad=0.0,
        covered_s=1.625,
        n_samples=14,
        reason="joint history incomplete: a 0.375 s gap (> 0.25 s) at 0.000 s into the 2 s window: the link did not watch the whole window",
        verdict="incomplete",
        max_receive_gap_s=0.375,
        missing_frames=NAN,
    ),
    "still_gap_at_window_start_exactly_at_limit": StillnessResult(
        still=True,
        max_deviation_rad=0.0,
        covered_s=2.0,
        n_samples=15,
        reason="",
        verdict="still",
        max_receive_gap_s=0.25,
        missing_frames=NAN,
    ),
    "incomplete_gap_at_window_end": StillnessResult(
        still=False,
        max_deviation_rad=0.0,
        covered_s=1.625,
        n_samples=14,
        reason="joint history incomplete: a 0.375 s gap (> 0.25 s) at 1.625 s into the 2 s window: the link did not watch the whole window",
        verdict="incomplete",
        max_receive_gap_s=0.375,
        missing_frames=NAN,
    ),
    "still_streamed_all_frames": StillnessResult(
        still=True,
        max_deviation_rad=0.0,
        covered_s=2.0,
        n_samples=17,
        reason="",
        verdict="still",
        max_receive_gap_s=0.125,
        missing_frames=0.0,
    ),
    "still_streamed_sparse_without_long_gap": StillnessResult(
        still=True,
        max_deviation_rad=0.0,
        covered_s=2.0,
        n_samples=13,
        reason="",
        verdict="still",
        max_receive_gap_s=0.16666666666666785,
        missing_frames=0.0,
    ),
    "still_streamed_gap_followed_by_its_frames": StillnessResult(
        still=True,
        max_deviation_rad=0.0,
        covered_s=2.0,
        n_samples=17,
        reason="",
        verdict="still",
        max_receive_gap_s=0.5,
        missing_frames=0.0,
    ),
    "still_streamed_gap_missing_exactly_at_limit": StillnessResult(
        still=True,
        max_deviation_rad=0.0,
        covered_s=1.75,
        n_samples=15,
        reason="",
        verdict="still",
        max_receive_gap_s=0.5,
        missing_frames=2.0,
    ),
    "incomplete_streamed_gap_not_followed": StillnessResult(
        still=False,
        max_deviation_rad=0.0,
        covered_s=1.625,
        n_samples=14,
        reason="joint history incomplete: no joint frame for 0.500 s from 0.500 s into the 2 s window, and the frames sent meanwhile did not follow: 0.375 s of frames missing (> 0.25 s) at the stream's long-run rate of 8.0 Hz: the controller stopped sending",
        verdict="incomplete",
        max_receive_gap_s=0.5,
        missing_frames=3.0,
    ),
    "still_streamed_late_burst": StillnessResult(
        still=True,
        max_deviation_rad=0.0,
        covered_s=2.0,
        n_samples=17,
        reason="",
        verdict="still",
        max_receive_gap_s=1.4000000000000004,
        missing_frames=0.0,
    ),
    "still_single_sample_at_end_window_within_gap": StillnessResult(
        still=True,
        max_deviation_rad=0.0,
        covered_s=0.1999999999999993,
        n_samples=1,
        reason="",
        verdict="still",
        max_receive_gap_s=0.09999999999999964,
        missing_frames=NAN,
    ),
}

BAD_INPUT_MESSAGES: dict[str, str] = {
    "shape_mismatch": "joints_rad must have shape (17, n_joints), got (16, 6)",
    "one_dimensional_joints": "joints_rad must have shape (17, n_joints), got (17,)",
    "decreasing_times": "t_s must be non-decreasing",
    "zero_window": "window_s and max_gap_s must be > 0 and max_deviation_rad >= 0",
    "zero_max_gap": "window_s and max_gap_s must be > 0 and max_deviation_rad >= 0",
    "negative_deviation": "window_s and max_gap_s must be > 0 and max_deviation_rad >= 0",
    "nan_period": "period_s must be a positive number of seconds, got nan",
    "zero_period": "period_s must be a positive number of seconds, got 0.0",
    "sessions_shape": "sessions must have shape (17,), got (2,)",
}


def _same(a: float | str | bool | int, b: float | str | bool | int) -> bool:
    both_nan = isinstance(a, float) and isinstance(b, float) and math.isnan(a) and math.isnan(b)
    return both_nan or a == b


@pytest.mark.parametrize("name", sorted(CASES))
def test_assess_stillness_pinned(name: str) -> None:
    got = assess_stillness(**CASES[name])
    want = EXPECTED[name]
    differ = {
        f: (getattr(got, f), getattr(want, f))
        for f in StillnessResult.__dataclass_fields__
        if not _same(getattr(got, f), getattr(want, f))
    }
    assert not differ, differ


@pytest.mark.parametrize("name", sorted(BAD_INPUT))
def test_assess_stillness_bad_input_pinned(name: str) -> None:
    with pytest.raises(ValueError) as info:
        assess_stillness(**BAD_INPUT[name])
    assert str(info.value) == BAD_INPUT_MESSAGES[name]


def test_every_verdict_is_pinned() -> None:
    assert {r.verdict for r in EXPECTED.values()} == {"still", "moved", "incomplete"}
    assert sorted(EXPECTED) == sorted(CASES)
