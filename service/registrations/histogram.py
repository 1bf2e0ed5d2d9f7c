"""Histogram of verification position errors (Bai et al. 2018, Figure 7).

x = position error (mm), y = number of spheres.  Uses matplotlib's Agg canvas
directly (no pyplot, no global backend switch), so it is safe in threads and
without a display.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from numpy.typing import ArrayLike

TARGET_BINS = 10
"""About this many bins between 0 and the largest error (the bin width is rounded to 1, 2 or 5 × 10^k mm)."""


def nice_bin_width_mm(max_error_mm: float, target_bins: int = TARGET_BINS) -> float:
    """A 1/2/5 × 10^k bin width giving about ``target_bins`` bins up to ``max_error_mm``."""
    raw = max(max_error_mm, 1e-3) / target_bins
    exp = np.floor(np.log10(raw))
    for m in (1.0, 2.0, 5.0, 10.0):
        if m * 10**exp >= raw:
            return float(m * 10**exp)
    return float(10 ** (exp + 1))


def write_error_histogram(
    errors_mm: ArrayLike,
    path: str | Path,
    *,
    title: str = "Position error of the calibration spheres",
    bin_width_mm: float | None = None,
    gate_mm: float | None = None,
) -> Path:
    """Write a PNG histogram of per-sphere position errors; returns the path.

    Parameters
    ----------
    errors_mm : array_like, shape (K,)
        Per-sphere errors |T·p_r − p_i| in mm (paper eq. 10).
    path : str or Path
        Output PNG.
    bin_width_mm : float, optional
        Default: :func:`nice_bin_width_mm` of the largest error.
    gate_mm : float, optional
        The verification gate (``quality.max_verification_error_mm``): drawn as a vertical line, and
        the verdict (PASS when the largest error is at most the gate, else FAIL) in the title, so a
        failed verification never looks like a passed one.
    """
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure
    from matplotlib.ticker import MaxNLocator

    e = np.asarray(errors_mm, dtype=np.float64).reshape(-1)
    out = Path(path)
    out.parent.mkdir(parents=True, exist_ok=True)
    fig = Figure(figsize=(6.4, 4.0), dpi=100)
    FigureCanvasAgg(fig)
    ax = fig.add_subplot(1, 1, 1)
    max_mm = float(e.max()) if len(e) else 0.0
    if bin_width_mm is None:
        bin_width_mm = nice_bin_width_mm(max_mm)
    top = max(max_mm, bin_width_mm)
    if gate_mm is not None:
        passed = max_mm <= gate_mm
        ax.axvline(gate_mm, color="#1e8449" if passed else "#c0392b", linewidth=2.0,
                   label=f"gate {gate_mm:.3f} mm")  # fmt: skip
        # the verdict on its own line: on one line a long title ran off the figure's right edge
        title = f"{title}\n{'PASS' if passed else 'FAIL'} (max {max_mm:.3f} mm, gate {gate_mm:.3f} mm)"
    bins = [float(b) for b in np.arange(0.0, top + bin_width_mm, bin_width_mm)]
    ax.hist(e, bins=bins, color="#4a7ab5", edgecolor="black", linewidth=0.6)
    if len(e):
        mean = float(e.mean())
        rms = float(np.sqrt(np.mean(e**2)))
        ax.axvline(mean, color="#c0392b", linestyle="--", linewidth=1.0, label=f"mean {mean:.3f} mm")
        ax.legend(title=f"n = {len(e)}, RMS {rms:.3f} mm, max {float(e.max()):.3f} mm", fontsize=8)
    ax.set_xlabel("Position error (mm)")
    ax.set_ylabel("Number of spheres")
    ax.yaxis.set_major_locator(MaxNLocator(integer=True))  # counts: no 7.5-sphere ticks
    ax.set_title(title)
    ax.set_xlim(left=0.0)
    fig.tight_layout()
    fig.savefig(out, format="png")
    return out
