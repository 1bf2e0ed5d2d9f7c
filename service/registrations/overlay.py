"""Detection overlay: what ``detect_spheres`` found and refused, drawn on the scan.

A maximum-intensity projection along the slices (every sphere of the phantom shows, whatever its
slice) with a red ``+`` on each detected centre and one marker per rejection reason, the reasons
in a legend under the image, so a refused scan shows *where* the detector refused and why.
Matplotlib's Agg canvas directly (no pyplot, no global backend), as :mod:`service.registrations.histogram`.
"""

from __future__ import annotations

import re
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    from registration.detection import DetectionResult
    from registration.imaging.volume import Volume

WINDOW_HU = (-300.0, 2500.0)
"""Display window: plastic and bone grey, metal (steel spheres, the rod) white."""

REJECTION_MARKERS = ("x", "^", "s", "D", "v", "P", "*")
"""One marker per distinct rejection reason, in order of first appearance (then reused)."""


def short_reason(reason: str) -> str:
    """A rejection reason without its numbers, so blobs refused for the same cause share one
    legend entry: the text before the first " (" or ":", each number in it shown as "…"."""
    for sep in (" (", ":"):
        reason = reason.split(sep, 1)[0]
    return re.sub(r"\d+(?:\.\d+)?", "…", reason).strip()


def write_detection_overlay(
    volume: Volume, result: DetectionResult, path: str | Path, *, title: str | None = None
) -> Path:
    """Write the overlay PNG of ``result`` on ``volume``; returns the path."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure
    from matplotlib.layout_engine import ConstrainedLayoutEngine

    out = Path(path)
    out.parent.mkdir(parents=True, exist_ok=True)
    mip = np.asarray(volume.voxels).max(axis=0)
    # h_pad in inches: the default constrained layout cut the top of the title
    fig = Figure(figsize=(7.0, 7.6), dpi=100, layout=ConstrainedLayoutEngine(h_pad=0.1))
    FigureCanvasAgg(fig)
    ax = fig.add_subplot(1, 1, 1)
    ax.imshow(mip, cmap="gray", vmin=WINDOW_HU[0], vmax=WINDOW_HU[1], interpolation="nearest")
    n_found = len(result.spheres)
    if n_found:
        ijk = volume.image_to_voxel(result.centres_image_mm)
        ax.plot(ijk[:, 0], ijk[:, 1], "+", color="#e74c3c", markersize=9, markeredgewidth=1.6,
                label=f"detected ({n_found}, {result.method})")  # fmt: skip
    reasons: dict[str, list[tuple[float, float, float]]] = {}
    for r in result.rejections:
        reasons.setdefault(short_reason(r.reason), []).append(r.center_image_mm)
    for n, (reason, centres) in enumerate(reasons.items()):
        ijk = volume.image_to_voxel(np.asarray(centres, dtype=np.float64))
        ax.plot(ijk[:, 0], ijk[:, 1], REJECTION_MARKERS[n % len(REJECTION_MARKERS)], color="#f1c40f",
                markerfacecolor="none", markersize=10, markeredgewidth=1.4,
                label=f"rejected: {reason} ({len(centres)})")  # fmt: skip
    rows, cols = mip.shape
    ax.set_xlim(-0.5, cols - 0.5)
    ax.set_ylim(rows - 0.5, -0.5)
    ax.set_xlabel("column i (voxels)")
    ax.set_ylabel("row j (voxels)")
    uid = volume.series_uid
    ax.set_title(
        title
        or f"series …{uid[-16:]}: {n_found} sphere(s), {len(result.rejections)} rejected\n"
        f"maximum-intensity projection along the {volume.shape[0]} slices",
        fontsize=10,
    )
    if n_found or reasons:
        fig.legend(loc="outside lower center", ncols=1, fontsize=9, frameon=False)
    fig.savefig(out, format="png")
    return out
