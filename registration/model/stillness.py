"""Was the robot still over a time window?  (Refuse a registration if it moved during the scan.)

The paper's method assumes the phantom did not move between the joint reading
and the O-arm scan (Bai et al. 2018, doi:10.1088/1742-6596/1016/1/012006):
the sphere positions in robot space come from one joint vector.  The service
therefore checks the recorded joint history over the scan window and gives one of
three verdicts (docs/safety.md, "Stillness and health"):

* ``moved``: some joint deviated more than ``max_deviation_rad`` from its value at
  the window end (the pose used for the registration), or the controller itself reported
  ``in_motion`` = TRUE (its STATUS TriState; simple_message msg 13, the serial link's status
  line) inside the window, whatever the joints showed: the controller knows of a motion the
  joint stream may not show (a move below the deviation limit, a frame filtered out).  An
  ``in_motion`` of UNKNOWN (−1) or FALSE is no evidence either way and never refuses.  Proof of
  motion wins over everything else.
* ``incomplete``: the history does not cover the window, so nobody can say the robot
  was still: no samples; the window began before the link's session connected (the
  first scan after start-up); the link reconnected inside the window; or frames are
  missing.  How "missing" is judged depends on the link:

  - a **streamed** link (simple_message over TCP, serial) delivers late frames intact and in
    order, so a receive-clock gap inside one unbroken session is not a hole in the robot's
    history when the frames sent meanwhile follow it.  Only a receive gap longer than
    ``max_gap_s`` is examined: the frames received from its end until up to :data:`CATCH_UP_S`
    later are counted against the frames the controller sends over the gap and that horizon
    (the best horizon counts) at the session's long-run rate (:func:`stream_period_s`, frames
    over span); when more than ``max_gap_s`` worth are missing, the controller stopped
    sending.  The count runs over a second or so around each long receive gap, never over the
    whole window, so a rate error of a few per mille costs milliseconds, not the 0.25 s that a
    count over a 60 s window at the median receive interval lost under load.  The
    controller's own counters are not used: the VAL3 driver sends JOINT_POSITION with
    sequence number 0 and never JOINT_FEEDBACK (research/staubli-link.md §1.4, §1.7);
    JOINT_FEEDBACK's ``time`` is a float32 (1 ms resolution lost after ~2.3 h of controller
    uptime); the serial ``$J`` counter shows lines lost on the wire, not a controller that
    paused (docs/robot-link.md, "Joint history and the controller's cadence").
  - a **polled** link (Modbus) has a sample only when its poller ran: no gap between
    receive times (and the window edges) may exceed ``max_gap_s``.
* ``still``: covered and within the deviation limit.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

DEFAULT_MAX_DEVIATION_RAD = 0.0005
"""≈ 0.029°.  At the TX60's 670 mm reach an angular error of 0.0005 rad moves the flange by
≈ 0.34 mm, the order of the registration error budget (nominal-model error ≈ 0.3 mm,
research/staubli-link.md §3.1 item 4); encoder noise of a standing arm is far below it."""

DEFAULT_MAX_GAP_S = 0.25
"""12 frame periods at 50 Hz: a longer hole in the history means the link was not watching; 0.25 s
(not 5 periods) tolerates scheduling hiccups of a loaded service PC.  The value of
``stillness.max_gap_s`` in configs/oarmreg.toml; service/settings.py takes its default from here."""

STREAM_PERIOD_MIN_INTERVALS = 10
"""Fewest inter-frame intervals from which :func:`stream_period_s` measures a stream's period; with
fewer the coverage is judged by receive gaps, as for a polled link."""

CATCH_UP_S = 1.0
"""After a streamed link's receive gap longer than ``max_gap_s``, the frames the controller sent
meanwhile must have arrived within this long of the gap's end (s).  A receiver that could not read
finds the backlog in its socket and reads it in one go (the frames share one receive stamp); a
controller that paused sends nothing for the gap.  1 s leaves room for a second delay right after
the first (a descheduled reader, then a sender catching up); the rate's error over it is a few
milliseconds (a 0.5 s pause in the 60 s the rate is measured over: 0.8 % of 1.5 s)."""

VERDICT_STILL = "still"
VERDICT_MOVED = "moved"
VERDICT_INCOMPLETE = "incomplete"
VERDICTS = (VERDICT_STILL, VERDICT_MOVED, VERDICT_INCOMPLETE)
"""The stillness verdicts (docs/safety.md lists them with the refusal each one gives)."""

DEFAULT_WINDOW_S = 2.0
"""Default window for a manual capture; the service uses the scan's acquisition interval."""


@dataclass(frozen=True)
class StillnessResult:
    """Outcome of :func:`assess_stillness`.

    Attributes
    ----------
    still : bool
    max_deviation_rad : float
        Largest |q(t) − q(window_end)| over the window and all joints (NaN if no samples).
    covered_s : float
        Span of the window covered by samples without a gap > ``max_gap_s``.
    n_samples : int
        Samples inside the window.
    reason : str
        Why not still (empty if still).
    verdict : str
        ``still``, ``moved`` or ``incomplete`` (:data:`VERDICTS`).
    max_receive_gap_s : float
        Largest time between consecutive samples or a window edge and its nearest sample (s), by
        the receive clock (NaN if no samples).
    missing_frames : float
        Streamed links: frames missing after the receive gaps over ``max_gap_s`` (those sent over a
        gap that did not follow it within ``catch_up_s``), at the long-run period; 0 when no receive
        gap exceeds ``max_gap_s``.  NaN when coverage was judged by receive gaps (polled).
    """

    still: bool
    max_deviation_rad: float
    covered_s: float
    n_samples: int
    reason: str
    verdict: str = VERDICT_STILL
    max_receive_gap_s: float = math.nan
    missing_frames: float = math.nan


def stream_period_s(t_s: ArrayLike, *, min_intervals: int = STREAM_PERIOD_MIN_INTERVALS) -> float | None:
    """A stream's long-run frame period: the span of its receive times over the number of intervals (s).

    Frames over span does not depend on how the receive clock bunches them: a burst of late frames
    after a receive delay and the short intervals of a busy scheduler leave the count and the span
    unchanged (the median interval shrinks under both).  A controller pause inside the
    span lengthens the period by the pause's share of the span (0.5 s in 60 s: 0.8 %), which
    :func:`assess_stillness` applies only over a second around a receive gap.  None with fewer than
    ``min_intervals`` intervals or a zero span.
    """
    t = np.asarray(t_s, dtype=np.float64).reshape(-1)
    if t.size - 1 < min_intervals:
        return None
    period = float((t[-1] - t[0]) / (t.size - 1))
    return period if period > 0 and math.isfinite(period) else None


def assess_stillness(
    t_s: ArrayLike,
    joints_rad: ArrayLike,
    *,
    window_end_t_s: float,
    window_s: float,
    max_deviation_rad: float = DEFAULT_MAX_DEVIATION_RAD,
    max_gap_s: float = DEFAULT_MAX_GAP_S,
    watched_from_t_s: float | None = None,
    sessions: ArrayLike | None = None,
    period_s: float | None = None,
    in_motion_t_s: ArrayLike | None = None,
    catch_up_s: float = CATCH_UP_S,
) -> StillnessResult:
    """Decide whether the robot was still during ``[window_end_t_s − window_s, window_end_t_s]``.

    Parameters
    ----------
    t_s : array_like, shape (M,)
        Sample times (``time.monotonic()`` seconds), non-decreasing.
    joints_rad : array_like, shape (M, n_joints)
        Joint samples in radians.
    window_end_t_s, window_s : float
        The window; its start is ``window_end_t_s − window_s``.
    max_deviation_rad : float
        Largest allowed |q(t) − q_end| per joint, where q_end is the last sample at or
        before ``window_end_t_s``.
    max_gap_s : float
        Polled links (``period_s`` None): largest allowed time without a sample, between
        consecutive samples in the window, from the window start to the first sample,
        and from the last sample to the window end.  Streamed links: the frames of this
        much time may be missing from the count.
    watched_from_t_s : float, optional
        When the link session that delivered the window's samples connected; a window
        starting before it is ``incomplete`` (nobody watched the robot then).
    sessions : array_like of int, shape (M,), optional
        The transport session of each sample; more than one inside the window (a
        reconnect) is ``incomplete``.
    period_s : float, optional
        A streamed link's long-run frame period (:func:`stream_period_s`): a receive gap over
        ``max_gap_s`` is a hole only when the frames sent over it did not follow within
        ``catch_up_s`` (counted at this period).  None for a polled link.
    in_motion_t_s : array_like of float, optional
        Receive times (same clock as ``t_s``) of the controller statuses that reported
        ``in_motion`` = TRUE; one inside the window is ``moved``.
    catch_up_s : float
        Streamed links: how long after a long receive gap the frames sent over it are looked for
        (:data:`CATCH_UP_S`); samples after the window end up to this long count.

    Returns
    -------
    StillnessResult
        ``still`` is True iff the window is covered and the deviation is within the limit;
        ``verdict`` says which of ``still`` / ``moved`` / ``incomplete``.

    Raises
    ------
    ValueError
        Shapes disagree, times decrease, or a parameter is not positive.
    """
    t, q = _validated(t_s, joints_rad, window_s, max_gap_s, max_deviation_rad, period_s)
    start = window_end_t_s - window_s
    inside = (t >= start) & (t <= window_end_t_s)
    unusable = _unusable_window(q[inside], window_s)
    if unusable is not None:
        return unusable
    w = _window(t[inside], q[inside], start, window_end_t_s, window_s, max_gap_s)
    refusal = (
        _moved_by_deviation(w, max_deviation_rad)
        or _moved_by_report(w, in_motion_t_s)
        or _watched_late(w, watched_from_t_s)
        or _reconnected(w, sessions, inside)
    )
    if refusal is not None:
        return refusal
    if period_s is not None:
        return _streamed_coverage(w, t, period_s, max_gap_s, catch_up_s)
    return _polled_coverage(w, max_gap_s)


@dataclass(frozen=True)
class _Window:
    """The samples inside the window and what every step reads of them."""

    start_t_s: float
    end_t_s: float
    window_s: float
    n: int
    deviation_rad: float
    per_joint_rad: NDArray[np.float64]
    edges_t_s: NDArray[np.float64]
    """The window start, the sample times inside, the window end."""
    gaps_s: NDArray[np.float64]
    worst_gap_s: float
    covered_s: float
    """The span of the gaps no longer than ``max_gap_s``."""


def _validated(
    t_s: ArrayLike,
    joints_rad: ArrayLike,
    window_s: float,
    max_gap_s: float,
    max_deviation_rad: float,
    period_s: float | None,
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """The times and joints as arrays; ValueError for shapes, order or parameters out of range."""
    t = np.asarray(t_s, dtype=np.float64).reshape(-1)
    q = np.asarray(joints_rad, dtype=np.float64)
    if q.ndim != 2 or q.shape[0] != t.size:
        raise ValueError(f"joints_rad must have shape ({t.size}, n_joints), got {q.shape}")
    if not (window_s > 0 and max_gap_s > 0 and max_deviation_rad >= 0):
        raise ValueError("window_s and max_gap_s must be > 0 and max_deviation_rad >= 0")
    if t.size > 1 and np.any(np.diff(t) < 0):
        raise ValueError("t_s must be non-decreasing")
    if period_s is not None and not (period_s > 0 and math.isfinite(period_s)):
        raise ValueError(f"period_s must be a positive number of seconds, got {period_s}")
    return t, q


def _unusable_window(qw: NDArray[np.float64], window_s: float) -> StillnessResult | None:
    """``incomplete`` when the window holds no samples or non-finite ones; else None."""
    n = int(qw.shape[0])
    if n == 0:
        return StillnessResult(
            False, math.nan, 0.0, 0,
            f"joint history incomplete: no joint samples in the {window_s:g} s window", VERDICT_INCOMPLETE,
        )  # fmt: skip
    if not np.all(np.isfinite(qw)):
        return StillnessResult(
            False, math.nan, 0.0, n, "joint history incomplete: non-finite joint values in the window",
            VERDICT_INCOMPLETE,
        )  # fmt: skip
    return None


def _window(
    tw: NDArray[np.float64],
    qw: NDArray[np.float64],
    start: float,
    window_end_t_s: float,
    window_s: float,
    max_gap_s: float,
) -> _Window:
    """The deviation from the window-end pose and the receive gaps, window edges included."""
    per_joint = np.max(np.abs(qw - qw[-1]), axis=0)
    edges = np.concatenate(([start], tw, [window_end_t_s]))
    gaps = np.diff(edges)
    return _Window(
        start, window_end_t_s, window_s, int(tw.size), float(np.max(per_joint)), per_joint, edges, gaps,
        float(gaps.max()), float(np.sum(gaps[gaps <= max_gap_s])),
    )  # fmt: skip


def _moved_by_deviation(w: _Window, max_deviation_rad: float) -> StillnessResult | None:
    """``moved`` when a joint left the window-end pose by more than the limit."""
    if not w.deviation_rad > max_deviation_rad:
        return None
    j = int(np.argmax(w.per_joint_rad))
    return StillnessResult(
        False, w.deviation_rad, w.covered_s, w.n,
        f"robot moved: joint {j + 1} deviated {math.degrees(w.deviation_rad):.4f}° "
        f"({w.deviation_rad:.6f} rad > {max_deviation_rad:g} rad) during the {w.window_s:g} s window",
        VERDICT_MOVED, w.worst_gap_s,
    )  # fmt: skip


def _moved_by_report(w: _Window, in_motion_t_s: ArrayLike | None) -> StillnessResult | None:
    """``moved`` when the controller reported ``in_motion`` = TRUE inside the window."""
    reported = np.asarray([] if in_motion_t_s is None else in_motion_t_s, dtype=np.float64).reshape(-1)
    reported = reported[(reported >= w.start_t_s) & (reported <= w.end_t_s)]
    if not reported.size:
        return None
    return StillnessResult(
        False, w.deviation_rad, w.covered_s, w.n,
        f"robot moved: the controller reported in_motion at t={reported[0] - w.start_t_s:.3f} s into the "
        f"{w.window_s:g} s window ({reported.size} status report(s) in the window) while the joints "
        f"deviated {w.deviation_rad:.6f} rad at most",
        VERDICT_MOVED, w.worst_gap_s,
    )  # fmt: skip


def _watched_late(w: _Window, watched_from_t_s: float | None) -> StillnessResult | None:
    """``incomplete`` when the window began before the link session connected."""
    if watched_from_t_s is None or not watched_from_t_s > w.start_t_s:
        return None
    return StillnessResult(
        False, w.deviation_rad, max(0.0, w.end_t_s - watched_from_t_s), w.n,
        f"joint history incomplete: the {w.window_s:g} s window began "
        f"{watched_from_t_s - w.start_t_s:.3f} s before the robot link connected, so nobody watched the "
        "robot then",
        VERDICT_INCOMPLETE, w.worst_gap_s,
    )  # fmt: skip


def _reconnected(w: _Window, sessions: ArrayLike | None, inside: NDArray[np.bool_]) -> StillnessResult | None:
    """``incomplete`` when the window's samples came over more than one link session."""
    if sessions is None:
        return None
    sw = np.asarray(sessions).reshape(-1)
    if sw.size != inside.size:
        raise ValueError(f"sessions must have shape ({inside.size},), got {sw.shape}")
    n_sessions = len(set(sw[inside].tolist()))
    if n_sessions <= 1:
        return None
    return StillnessResult(
        False, w.deviation_rad, 0.0, w.n,
        f"joint history incomplete: the robot link reconnected {n_sessions - 1} time(s) inside the "
        f"{w.window_s:g} s window, so frames may be lost",
        VERDICT_INCOMPLETE, w.worst_gap_s,
    )  # fmt: skip


def _receive_gaps(t: NDArray[np.float64], w: _Window) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Starts and ends of the receive gaps that touch the window: between consecutive samples, from
    the last sample at or before the window start (else the start) and to the first sample at or
    after the window end (else the end: nothing arrived after it)."""
    before = t[t <= w.start_t_s]
    after = t[t >= w.end_t_s]
    seq = np.concatenate((
        before[-1:] if before.size else [w.start_t_s],
        t[(t > w.start_t_s) & (t < w.end_t_s)],
        after[:1] if after.size else [w.end_t_s],
    ))  # fmt: skip
    return seq[:-1], seq[1:]


def _streamed_coverage(
    w: _Window, t: NDArray[np.float64], period_s: float, max_gap_s: float, catch_up_s: float
) -> StillnessResult:
    """A streamed link: ``still`` unless a receive gap over ``max_gap_s`` was not followed by the
    frames the controller sent over it (more than ``max_gap_s`` worth missing at ``period_s``)."""
    starts, ends = _receive_gaps(t, w)
    long_gaps = np.flatnonzero(ends - starts > max_gap_s)
    missing_s = np.zeros(long_gaps.size)
    for k, i in enumerate(long_gaps):
        a, b = float(starts[i]), float(ends[i])
        # the frames received from b on, each horizon up to b + catch_up_s: did they make up for the gap?
        seg = t[(t >= b) & (t <= b + catch_up_s)]
        if seg.size:
            deficits = (seg - a) - np.arange(1, seg.size + 1) * period_s
            missing_s[k] = max(0.0, float(deficits.min()))
        else:
            missing_s[k] = b - a
    covered = w.window_s - float(np.sum(np.minimum(missing_s, w.window_s)))
    missing_frames = float(np.sum(missing_s) / period_s)
    worst = int(np.argmax(missing_s)) if missing_s.size else -1
    if worst >= 0 and missing_s[worst] > max_gap_s:
        i = long_gaps[worst]
        gap_s = float(ends[i] - starts[i])
        return StillnessResult(
            False, w.deviation_rad, max(0.0, covered), w.n,
            f"joint history incomplete: no joint frame for {gap_s:.3f} s from "
            f"{float(starts[i]) - w.start_t_s:.3f} s into the {w.window_s:g} s window, and the frames sent "
            f"meanwhile did not follow: {missing_s[worst]:.3f} s of frames missing (> {max_gap_s:g} s) at "
            f"the stream's long-run rate of {1.0 / period_s:.1f} Hz: the controller stopped sending",
            VERDICT_INCOMPLETE, w.worst_gap_s, missing_frames,
        )  # fmt: skip
    return StillnessResult(
        True, w.deviation_rad, max(0.0, covered), w.n, "", VERDICT_STILL, w.worst_gap_s, missing_frames
    )


def _polled_coverage(w: _Window, max_gap_s: float) -> StillnessResult:
    """A polled link: ``still`` unless a receive gap (window edges included) exceeds ``max_gap_s``."""
    covered = w.covered_s
    if w.worst_gap_s > max_gap_s:
        i = int(np.argmax(w.gaps_s))
        return StillnessResult(
            False, w.deviation_rad, covered, w.n,
            f"joint history incomplete: a {w.worst_gap_s:.3f} s gap (> {max_gap_s:g} s) at "
            f"{w.edges_t_s[i] - w.start_t_s:.3f} s into the {w.window_s:g} s window: "
            "the link did not watch the whole window",
            VERDICT_INCOMPLETE, w.worst_gap_s,
        )  # fmt: skip
    return StillnessResult(True, w.deviation_rad, covered, w.n, "", VERDICT_STILL, w.worst_gap_s)
