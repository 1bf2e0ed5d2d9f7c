"""Issue 40 item 3: the joint history is held by time, the whole ``history_s`` at any rate up to 1 kHz.

Before, the ring held a number of samples (``history_s / frame_period_s`` = 6000 at the 50 Hz default):
120 s at 50 Hz but 24 s at 250 Hz and 6 s at 1 kHz, shorter than the default 60 s stillness window,
so every scan of a fast controller was refused.
"""

from __future__ import annotations

import itertools
from datetime import UTC, datetime

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from drivers.base import HISTORY_S, MAX_RATE_HZ, JointRing, JointState
from drivers.simple_message import SimpleMessageLink

NOW = datetime(2026, 1, 1, tzinfo=UTC)


def _fill(ring: JointRing[JointState], rate_hz: float, span_s: float) -> None:
    for k in range(round(span_s * rate_hz)):
        ring.append(JointState((0.0,) * 6, k / rate_hz, NOW, "simple-message://x"))


@pytest.mark.parametrize("rate_hz", [50.0, 250.0, 1000.0])
def test_the_history_holds_its_whole_span_at_any_rate_up_to_1_khz(rate_hz: float) -> None:
    ring: JointRing[JointState] = JointRing(HISTORY_S)
    _fill(ring, rate_hz, HISTORY_S + 10.0)
    kept = ring.since(0.0)
    span = kept[-1].t_s - kept[0].t_s
    assert HISTORY_S - 1.0 / rate_hz <= span + 1e-9 and span <= HISTORY_S + 1e-9  # by time, no more
    assert len(kept) == len(ring)


def test_a_stream_faster_than_1_khz_keeps_the_newest_samples_and_no_more() -> None:
    ring: JointRing[JointState] = JointRing(10.0)
    _fill(ring, 2 * MAX_RATE_HZ, 12.0)
    assert len(ring) == round(10.0 * MAX_RATE_HZ)
    last = ring.latest()
    assert last is not None and last.t_s == pytest.approx(12.0 - 1.0 / (2 * MAX_RATE_HZ))


def test_appended_since_hands_on_exactly_the_new_samples() -> None:
    ring: JointRing[JointState] = JointRing(1.0)
    _fill(ring, 1000.0, 0.5)
    first, cursor = ring.appended_since(0)
    assert len(first) == 500 and cursor == 500
    ring.append(JointState((1.0,) * 6, 0.5, NOW, "x"))
    new, cursor = ring.appended_since(cursor)
    assert [s.t_s for s in new] == [0.5] and cursor == 501


def test_every_link_keeps_the_history_span_whatever_its_documented_rate() -> None:
    fast = SimpleMessageLink("simple-message://127.0.0.1:11002?frame_period_s=0.001")  # never connected
    assert fast.history_s == HISTORY_S
    with pytest.raises(ValueError, match="history_s"):
        JointRing(0.0)


@settings(max_examples=30, deadline=None)
@given(
    gaps_ms=st.lists(st.integers(0, 400), min_size=1, max_size=300),
    history_s=st.floats(0.5, 5.0),
    since_s=st.floats(0.0, 40.0),
)
def test_span_and_largest_gap_match_the_samples_without_copying(
    gaps_ms: list[int], history_s: float, since_s: float
) -> None:
    ring: JointRing[JointState] = JointRing(history_s)
    t = 0.0
    for g in gaps_ms:
        t += g / 1000.0
        ring.append(JointState((0.0,) * 6, t, NOW, "x"))
    kept = [s.t_s for s in ring.since(-1.0)]
    pairs = [(b, b - a) for a, b in itertools.pairwise(kept) if b >= since_s]
    assert ring.max_gap_s(since_s) == (max(g for _, g in pairs) if pairs else None)
    after = [x for x in kept if x >= since_s]
    assert ring.span_s(since_s) == pytest.approx(after[-1] - after[0] if len(after) > 1 else 0.0)
