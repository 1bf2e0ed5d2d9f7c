"""Was the robot still over a time window?  (Refuse a registration if it moved during the scan.)

The paper's method assumes the phantom did not move between the joint reading
and the O-arm scan (Bai et al. 2018, doi:10.1088/1742-6596/1016/1/012006):
the sphere positions in robot space come from one joint vector.  The service
therefore checks the recorded joint history over the scan window:

* **covered**: samples exist from the window start to its end, with no gap
  longer than ``max_gap_s`` (the link was alive the whole time), and
* **still**: every joint stayed within ``max_deviation_rad`` of its value at
  the window end (the pose used for the registration).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike

DEFAULT_MAX_DEVIATION_RAD = 0.0005
"""≈ 0.029°.  At the TX60's 670 mm reach an angular error of 0.0005 rad moves the flange by
≈ 0.34 mm, the order of the registration error budget (nominal-model error ≈ 0.3 mm,
research/staubli-link.md §3.1 item 4); encoder noise of a standing arm is far below it."""

DEFAULT_MAX_GAP_S = 0.25
"""12 frame periods at 50 Hz: a longer hole in the history means the link was not watching; 0.25 s
(not 5 periods) tolerates scheduling hiccups of a loaded service PC.  The value of
``stillness.max_gap_s`` in configs/oarmreg.toml; service/settings.py takes its default from here."""

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
    """

    still: bool
    max_deviation_rad: float
    covered_s: float
    n_samples: int
    reason: str


def assess_stillness(
    t_s: ArrayLike,
    joints_rad: ArrayLike,
    *,
    window_end_t_s: float,
    window_s: float,
    max_deviation_rad: float = DEFAULT_MAX_DEVIATION_RAD,
    max_gap_s: float = DEFAULT_MAX_GAP_S,
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
        Largest allowed time without a sample: between consecutive samples in the
        window, from the window start to the first sample, and from the last sample
        to the window end.

    Returns
    -------
    StillnessResult
        ``still`` is True iff the window is covered and the deviation is within the limit.

    Raises
    ------
    ValueError
        Shapes disagree, times decrease, or a parameter is not positive.
    """
    t = np.asarray(t_s, dtype=np.float64).reshape(-1)
    q = np.asarray(joints_rad, dtype=np.float64)
    if q.ndim != 2 or q.shape[0] != t.size:
        raise ValueError(f"joints_rad must have shape ({t.size}, n_joints), got {q.shape}")
    if not (window_s > 0 and max_gap_s > 0 and max_deviation_rad >= 0):
        raise ValueError("window_s and max_gap_s must be > 0 and max_deviation_rad >= 0")
    if t.size > 1 and np.any(np.diff(t) < 0):
        raise ValueError("t_s must be non-decreasing")
    start = window_end_t_s - window_s
    inside = (t >= start) & (t <= window_end_t_s)
    n = int(inside.sum())
    if n == 0:
        return StillnessResult(False, math.nan, 0.0, 0, f"no joint samples in the {window_s:g} s window")
    tw, qw = t[inside], q[inside]
    if not np.all(np.isfinite(qw)):
        return StillnessResult(False, math.nan, 0.0, n, "non-finite joint values in the window")
    q_end = qw[-1]
    deviation = float(np.max(np.abs(qw - q_end)))
    edges = np.concatenate(([start], tw, [window_end_t_s]))
    gaps = np.diff(edges)
    covered = float(np.sum(gaps[gaps <= max_gap_s]))
    worst_gap = float(gaps.max())
    if worst_gap > max_gap_s:
        i = int(np.argmax(gaps))
        return StillnessResult(
            False, deviation, covered, n,
            f"joint history has a {worst_gap:.3f} s gap (> {max_gap_s:g} s) at "
            f"{edges[i] - start:.3f} s into the {window_s:g} s window: "
            "the link did not watch the whole window",
        )  # fmt: skip
    if deviation > max_deviation_rad:
        j = int(np.argmax(np.max(np.abs(qw - q_end), axis=0)))
        return StillnessResult(
            False, deviation, covered, n,
            f"robot moved: joint {j + 1} deviated {math.degrees(deviation):.4f}° "
            f"({deviation:.6f} rad > {max_deviation_rad:g} rad) during the {window_s:g} s window",
        )  # fmt: skip
    return StillnessResult(True, deviation, covered, n, "")
