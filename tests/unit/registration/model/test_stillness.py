"""assess_stillness: one test per rule (issue #5)."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from registration.model.stillness import DEFAULT_MAX_DEVIATION_RAD, assess_stillness

KW = {"window_s": 1.0, "max_deviation_rad": 0.0005, "max_gap_s": 0.1}


def _samples(t0: float = 0.0, t1: float = 2.0, dt: float = 0.02) -> tuple[np.ndarray, np.ndarray]:
    t = np.arange(t0, t1 + 1e-9, dt)
    return t, np.tile([0.1, 0.2, 1.5, 0.0, 0.7, 0.0], (t.size, 1))


def test_still_when_covered_and_within_deviation() -> None:
    t, q = _samples()
    q = q + 0.0002 * np.sin(t)[:, None]  # encoder-noise-sized wobble
    r = assess_stillness(t, q, window_end_t_s=2.0, **KW)
    assert r.still and r.reason == "" and r.n_samples == 51
    assert r.covered_s == pytest.approx(1.0) and r.max_deviation_rad <= 0.0005


def test_moved_beyond_threshold() -> None:
    t, q = _samples()
    q[t > 1.5, 2] += 0.001
    r = assess_stillness(t, q, window_end_t_s=1.6, **KW)
    assert not r.still and "joint 3" in r.reason and r.max_deviation_rad == pytest.approx(0.001)


def test_deviation_is_measured_against_the_window_end() -> None:
    t, q = _samples()
    q[t < 0.95, 0] += 0.01  # moved, then stopped before the window
    assert assess_stillness(t, q, window_end_t_s=2.0, **KW).still
    assert not assess_stillness(t, q, window_end_t_s=1.9, **KW).still


def test_gap_inside_window() -> None:
    t, q = _samples()
    keep = (t < 1.3) | (t > 1.5)
    r = assess_stillness(t[keep], q[keep], window_end_t_s=2.0, **KW)
    assert not r.still and "gap" in r.reason and r.covered_s < 1.0


def test_window_start_not_covered() -> None:
    t, q = _samples(t0=1.5)
    r = assess_stillness(t, q, window_end_t_s=2.0, **KW)
    assert not r.still and "gap" in r.reason


def test_window_end_not_covered() -> None:
    t, q = _samples(t1=1.5)
    r = assess_stillness(t, q, window_end_t_s=2.0, **KW)
    assert not r.still and "gap" in r.reason


def test_no_samples() -> None:
    t, q = _samples(t1=0.5)
    r = assess_stillness(t, q, window_end_t_s=2.0, **KW)
    assert not r.still and r.n_samples == 0 and math.isnan(r.max_deviation_rad)


def test_nan_samples_not_still() -> None:
    t, q = _samples()
    q[-3, 1] = math.nan
    assert not assess_stillness(t, q, window_end_t_s=2.0, **KW).still


def test_bad_inputs() -> None:
    t, q = _samples()
    with pytest.raises(ValueError, match="shape"):
        assess_stillness(t, q[:-1], window_end_t_s=2.0, **KW)
    with pytest.raises(ValueError, match="non-decreasing"):
        assess_stillness(t[::-1], q, window_end_t_s=2.0, **KW)
    with pytest.raises(ValueError, match="> 0"):
        assess_stillness(t, q, window_end_t_s=2.0, window_s=0.0, max_deviation_rad=0.001, max_gap_s=0.1)


def test_default_threshold_is_sub_millimetre_at_reach() -> None:
    assert DEFAULT_MAX_DEVIATION_RAD * 670.0 < 0.5  # mm at the TX60's 670 mm reach


@settings(max_examples=25, deadline=None)
@given(
    window_s=st.floats(0.2, 5.0),
    frac=st.floats(0.0, 1.0),
    outside_s=st.floats(1e-3, 10.0),
    q=st.lists(st.floats(-3.0, 3.0), min_size=6, max_size=6),
)
def test_controller_in_motion_inside_the_window_is_moved_outside_it_is_not(
    window_s: float, frac: float, outside_s: float, q: list[float]
) -> None:
    """Issue 31 item 8: a controller report of in_motion = TRUE inside the window refuses as moved,
    with the controller's reason, though the joints never change; a report outside the window does not."""
    end = 100.0
    t = np.linspace(end - window_s, end, 60)
    joints = np.tile(q, (t.size, 1))
    kw = {"window_end_t_s": end, "window_s": window_s, "max_gap_s": 0.25}
    inside = assess_stillness(t, joints, in_motion_t_s=[end - window_s + frac * window_s], **kw)
    assert inside.verdict == "moved" and not inside.still
    assert "controller reported in_motion at t=" in inside.reason and inside.max_deviation_rad == 0.0
    outside = assess_stillness(t, joints, in_motion_t_s=[end - window_s - outside_s, end + outside_s], **kw)
    assert outside.verdict == "still" and outside.still, outside.reason
