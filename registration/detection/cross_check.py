"""Step 5 of the detection: the circles in a sphere's slices, the cross-check of its 3-D centre.

In each slice a sphere spans, a square patch around the centre is searched for circles by moment
invariants (:mod:`registration.imaging.circles`, Bai 2018 §2.2), after the polar MAR
(:mod:`registration.imaging.mar`) on every patch when the circles are the measurement (``paper``), else
only on a patch whose raw cross-section fails the circle test.  The accepted circle nearest the
3-D centre per slice gives the sphere's slice count, its fitted (apparent) radius and its score;
a blob with none is refused unless it is a split core (its 3-D shape was already tested).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from registration.arrays import F64
from registration.detection.candidates import Support
from registration.detection.centroid import support_mask
from registration.detection.params import DetectionParams
from registration.detection.timing import StageTimer
from registration.imaging.circles import CircleParams, find_circles
from registration.imaging.mar import reduce_metal_artifacts


@dataclass(frozen=True)
class SliceCircle:
    i: float  # column, full-volume index
    j: float  # row
    k: int  # slice
    r_mm: float


def slice_circles(
    vox: NDArray[Any],
    k_range: range,
    centre_ijk: F64,
    params: DetectionParams,
    pixel_mm: float,
    timer: StageTimer,
    support: Support | None = None,
    *,
    mar_every_patch: bool = False,
) -> list[SliceCircle]:
    """The accepted circle nearest the 3-D centre in each slice of ``k_range`` (MAR as configured).

    With ``mar_every_patch`` (the estimator measures from the circles, ``paper``: Bai 2018) and
    ``params.use_mar`` every patch is MAR-filtered first; otherwise MAR runs only on a patch whose
    raw cross-section fails the circle test.
    """
    shape = vox.shape
    half_px = max(math.ceil(params.patch_half_mm / pixel_mm), params.min_patch_half_px)
    ci, cj = float(centre_ijk[0]), float(centre_ijk[1])
    j0, j1 = max(round(cj) - half_px, 0), min(round(cj) + half_px + 1, shape[1])
    i0, i1 = max(round(ci) - half_px, 0), min(round(ci) + half_px + 1, shape[2])
    r_app_px = (params.radius_mm + params.bloom_mm) / pixel_mm
    mar_first = params.use_mar and mar_every_patch

    def circle(patch: NDArray[np.float32], k: int) -> SliceCircle | None:
        with timer.stage("circles_s"):
            return _circle_near(patch, k, (i0, j0), (ci, cj), r_app_px, pixel_mm, params.circles)

    circles: list[SliceCircle] = []
    for k in k_range:
        patch = np.asarray(vox[k, j0:j1, i0:i1], dtype=np.float32)
        if support is not None:
            patch = _flatten_outside(patch, k, (j0, i0), support, params.circles.window_hu[0])
        best = None if mar_first else circle(patch, k)
        if best is None and params.use_mar:
            with timer.stage("mar_s"):
                patch = reduce_metal_artifacts(patch, pixel_mm, params.mar).patch
            best = circle(patch, k)
        if best is not None:
            circles.append(best)
    return circles


def _flatten_outside(
    patch: NDArray[np.float32], k: int, origin_ji: tuple[int, int], support: Support, floor_hu: float
) -> NDArray[np.float32]:
    """``patch`` (slice k, rows/columns from ``origin_ji``) with voxels outside ``support`` capped at
    ``floor_hu`` (the circle window's floor, so they map to 0 before Canny)."""
    lo = np.array([origin_ji[1], origin_ji[0], k])
    hi = lo + np.array([patch.shape[1], patch.shape[0], 1])
    inside = support_mask(lo, hi, support)[0]
    return np.where(inside, patch, np.minimum(patch, np.float32(floor_hu)))


def _circle_near(
    patch: NDArray[np.float32],
    k: int,
    origin_ij: tuple[int, int],
    centre_ij: tuple[float, float],
    max_offset_px: float,
    pixel_mm: float,
    circle_params: CircleParams,
) -> SliceCircle | None:
    """The accepted circle of slice ``k``'s patch nearest the 3-D centre, within ``max_offset_px``."""
    best: SliceCircle | None = None
    best_d = math.inf
    for c in find_circles(patch, pixel_mm, circle_params):
        if not c.accepted:
            continue
        i = c.center_px[0] + origin_ij[0]
        j = c.center_px[1] + origin_ij[1]
        d = math.hypot(i - centre_ij[0], j - centre_ij[1])
        if d <= max_offset_px and d < best_d:
            best_d = d
            best = SliceCircle(i, j, k, c.radius_px * pixel_mm)
    return best


def fit_radius(circles: list[SliceCircle], dz_mm: float) -> tuple[float, float]:
    """Least-squares sphere from per-slice radii: r_i² + z_i² = c + 2·z0·z_i (image-side.md §3.2).

    Returns (R mm, z0 mm) with z measured as ``k · dz_mm``; NaN if < 2 distinct slices.
    """
    z = np.array([c.k * dz_mm for c in circles])
    r = np.array([c.r_mm for c in circles])
    if len(np.unique(z)) < 2:
        return math.nan, math.nan
    a = np.stack([np.ones_like(z), 2.0 * z], axis=1)
    (cc, z0), *_ = np.linalg.lstsq(a, r * r + z * z, rcond=None)
    r2 = cc + z0 * z0
    return (math.sqrt(r2) if r2 > 0 else math.nan), float(z0)


def sphere_score(
    circles: list[SliceCircle], centre_sv: F64, spacing: F64, n_slices: int, radius_mm: float
) -> float:
    """Fraction of the blob's slices with a circle × (1 − in-plane circle/centre disagreement / radius)."""
    if not circles:
        return 0.0
    inplane_mm = math.hypot(
        (np.mean([c.i for c in circles]) - centre_sv[0]) * spacing[0],
        (np.mean([c.j for c in circles]) - centre_sv[1]) * spacing[1],
    )
    frac = len(circles) / n_slices
    return float(np.clip(frac, 0.0, 1.0) * max(0.0, 1.0 - inplane_mm / radius_mm))
