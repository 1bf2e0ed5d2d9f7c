"""Metal artefact reduction in polar coordinates, on a patch around one metal object.

The method of Bai et al. 2018 (doi:10.1088/1742-6596/1016/1/012006, §2.2, after
Naranjo et al. 2011, doi:10.1016/j.cmpb.2010.11.009):

1. find the streak source (the metal centre) by line detection and a Hough
   transform, cross-checked against the centroid of the thresholded metal;
2. resample the patch to polar coordinates about that centre
   (``cv2.warpPolar`` puts the angle on rows and the radius on columns, so a
   radial streak becomes a horizontal line);
3. apply the closing–opening average filter (eq. 1,
   ``COA = (closing + opening) / 2``) with a structuring element that runs
   across the streaks (vertical, spanning rows) and whose length λ adapts to
   the distance from the centre (λ = 2 … 20 rows);
4. transform back to Cartesian coordinates (``WARP_INVERSE_MAP``);
5. composite with the threshold mask (eq. 3) so the metal itself is kept:
   ``out = original · mask + filtered · (1 − mask)``.

The paper writes eq. 3 as a product, ``I_original × I_filtered × (1 − I_msk)``;
read literally it would zero the metal, which contradicts its stated purpose
("preserve the original structure"), so the masked composite above is used.

Everything here works on one small 2-D patch (a few mm around one sphere,
one slice); :mod:`registration.detection` decides where the patches are.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass
from typing import Final

import cv2
import numpy as np
from numpy.typing import NDArray

from registration.arrays import F64

log = logging.getLogger(__name__)

F32 = NDArray[np.float32]
LAMBDA_MIN_ROWS: Final = 2
"""Smallest structuring-element length (polar rows): the paper's λ = 2 … 20 (§2.2)."""
LAMBDA_MAX_ROWS: Final = 20
"""Largest structuring-element length (polar rows): the paper's λ = 2 … 20 (§2.2)."""
LAMBDA_LEVELS_ROWS: Final = (2, 3, 5, 8, 13, 20)
"""λ is snapped to these (roughly geometric) levels so a patch needs six filter pairs, not one per radius."""


@dataclass(frozen=True)
class MarParams:
    """Tuning of the polar MAR filter.

    Attributes
    ----------
    metal_threshold_hu : float
        I_msk of eq. 3: pixels at or above this are metal and kept unfiltered.
        Steel spheres saturate at 3071 HU in a 12-bit export; cortical bone
        stays below ~2000 HU (image-side.md §3.3).
    n_angles : int
        Polar rows (angle samples over 360°).  2° per row keeps the λ range of
        the paper meaningful on a ~20 px patch.
    streak_width_mm : float
        Physical width of a streak; the SE spans ``(w / r) / (2π / n_angles)``
        rows at radius r, clipped to λ = 2 … 20 (image-side.md §2.3).  An SE
        shorter than the streak leaves it untouched; 1.5 mm removed ~50 % of
        the annulus SD on simulated ~1 mm streaks (tests/unit/registration/imaging/test_mar.py),
        wider values gained little more (COA can at most halve a line).
    hough_votes : int
        Accumulator threshold of ``cv2.HoughLines`` (edge pixels on a line);
        a streak must cross at least this many pixels of the patch.
    max_lines : int
        Strongest Hough lines used for the intersection.
    max_source_offset_mm : float
        The Hough intersection is used as the streak source only if it lies
        within this distance of the thresholded-metal centroid (half a 2.5 mm
        sphere: a farther intersection belongs to another object's streaks).
    canny_low, canny_high : float
        Canny hysteresis thresholds on the 8-bit windowed patch.
    window_hu : tuple of float
        HU window mapped to 0 … 255 before Canny / Hough.
    """

    metal_threshold_hu: float = 2000.0
    n_angles: int = 180
    streak_width_mm: float = 1.5
    hough_votes: int = 8
    max_source_offset_mm: float = 0.6
    max_lines: int = 40
    canny_low: float = 20.0
    canny_high: float = 60.0
    window_hu: tuple[float, float] = (-500.0, 1500.0)


@dataclass(frozen=True, eq=False)
class StreakSource:
    """Where the streaks come from, in patch pixel coordinates (x = column, y = row)."""

    center_px: F64  # (2,) x, y
    method: str  # "hough" | "metal-centroid"
    n_lines: int
    metal_centroid_px: F64  # (2,) x, y; NaN if no metal pixel


@dataclass(frozen=True, eq=False)
class MarResult:
    """A filtered patch and how it was made."""

    patch: F32  # (rows, cols) HU, metal kept
    filtered: F32  # (rows, cols) the COA-filtered image before compositing
    metal_mask: NDArray[np.bool_]
    source: StreakSource


def to_u8(
    patch_hu: NDArray[np.floating] | NDArray[np.integer], window_hu: tuple[float, float]
) -> NDArray[np.uint8]:
    """Map HU in ``window_hu`` linearly to 0 … 255 (clipped) for OpenCV's 8-bit operators."""
    lo, hi = window_hu
    scaled = (np.asarray(patch_hu, dtype=np.float32) - np.float32(lo)) * np.float32(255.0 / (hi - lo))
    out: NDArray[np.uint8] = np.clip(scaled, 0.0, 255.0).astype(np.uint8)
    return out


def metal_centroid(mask: NDArray[np.bool_]) -> F64:
    """Centroid (x, y) in pixels of the largest 8-connected blob of ``mask``; NaN if empty."""
    if not mask.any():
        return np.array([math.nan, math.nan])
    _, _, stats, cents = cv2.connectedComponentsWithStats(mask.astype(np.uint8), connectivity=8)
    best = 1 + int(np.argmax(stats[1:, cv2.CC_STAT_AREA]))
    return np.asarray(cents[best], dtype=np.float64)


def _nearest_point_to_lines(lines: F64, start: F64, n_iter: int = 3, trim_px: float = 2.0) -> F64 | None:
    """Least-squares point nearest to Hesse-normal lines (rho, theta), trimming far lines.

    Minimises Σ (n_k · p − rho_k)² with n_k = (cos θ_k, sin θ_k); after each
    solve, lines farther than ``trim_px`` from the point are dropped.  Returns
    None when the remaining lines do not span two directions.
    """
    normals = np.stack([np.cos(lines[:, 1]), np.sin(lines[:, 1])], axis=1)
    rho = lines[:, 0]
    p = start.astype(np.float64)
    keep = np.abs(normals @ p - rho) <= 3.0 * trim_px
    for _ in range(n_iter):
        if keep.sum() < 2:
            return None
        a = normals[keep].T @ normals[keep]
        if np.linalg.cond(a) > 1e3:  # all lines (nearly) parallel
            return None
        p = np.linalg.solve(a, normals[keep].T @ rho[keep])
        keep = np.abs(normals @ p - rho) <= trim_px
    return p


def find_streak_source(
    patch_hu: F32, pixel_mm: float, params: MarParams = MarParams(), *, exclude_radius_px: float | None = None
) -> StreakSource:
    """Locate the streak source in a patch: Hough lines of the streak edges, intersected.

    Edges are found with Canny on the windowed patch; edges within
    ``exclude_radius_px`` of the metal centroid (the metal's own outline, whose
    tangents would vote for spurious lines) are removed.  The lines found by
    ``cv2.HoughLines`` are intersected in the least-squares sense (the point
    nearest to all of them, lines farther than 2 px trimmed) and that point is
    the source.  If fewer than two lines are
    found, or the intersection lies more than ``max_source_offset_mm`` from
    the thresholded-metal centroid, the centroid is used (the paper's step 1
    with the threshold as cross-check).

    Parameters
    ----------
    patch_hu : ndarray, shape (rows, cols), float32
        One slice patch in HU.
    pixel_mm : float
        In-plane pixel size.

    Returns
    -------
    StreakSource
    """
    mask = patch_hu >= params.metal_threshold_hu
    centroid = metal_centroid(mask)
    if not np.all(np.isfinite(centroid)):
        h, w = patch_hu.shape
        centroid = np.array([(w - 1) / 2.0, (h - 1) / 2.0])
    edges = cv2.Canny(to_u8(patch_hu, params.window_hu), params.canny_low, params.canny_high)
    if exclude_radius_px is None:
        area = float(mask.sum())
        exclude_radius_px = math.sqrt(area / math.pi) + 2.0
    yy, xx = np.mgrid[0 : patch_hu.shape[0], 0 : patch_hu.shape[1]]
    edges[(xx - centroid[0]) ** 2 + (yy - centroid[1]) ** 2 <= exclude_radius_px**2] = 0
    lines = cv2.HoughLines(edges, 1.0, math.pi / 180.0, params.hough_votes)
    n_lines = 0 if lines is None else len(lines)
    if lines is not None and n_lines >= 2:
        # OpenCV returns lines by decreasing votes: keep the strongest
        cand = _nearest_point_to_lines(lines[: params.max_lines, 0, :2].astype(np.float64), centroid)
        if (
            cand is not None
            and float(np.linalg.norm(cand - centroid)) * pixel_mm <= params.max_source_offset_mm
        ):
            return StreakSource(cand, "hough", n_lines, centroid)
    return StreakSource(centroid, "metal-centroid", n_lines, centroid)


def adaptive_lambda_rows(
    radius_px: F64, pixel_mm: float, params: MarParams = MarParams()
) -> NDArray[np.int64]:
    """Structuring-element length (rows) per radius: λ = (w / r) / (2π / n), clipped to 2 … 20, snapped."""
    r_mm = np.maximum(np.asarray(radius_px, dtype=np.float64) * pixel_mm, 1e-6)
    lam = (params.streak_width_mm / r_mm) / (2.0 * math.pi / params.n_angles)
    lam = np.clip(lam, LAMBDA_MIN_ROWS, LAMBDA_MAX_ROWS)
    # snap to a few geometric levels (one pair of morphology calls per level, not per radius)
    levels = np.asarray(LAMBDA_LEVELS_ROWS, dtype=np.float64)
    idx = np.argmin(np.abs(np.log(lam)[:, None] - np.log(levels)[None, :]), axis=1)
    return np.asarray(levels[idx], dtype=np.int64)


def closing_opening_average(polar: F32, lam_per_column: NDArray[np.int64]) -> F32:
    """Eq. 1 of the paper: ``(closing + opening) / 2`` with a vertical SE of λ rows per column.

    The angle axis (rows) is periodic, so the image is wrapped by ``LAMBDA_MAX_ROWS``
    rows on both sides before filtering.
    """
    pad = LAMBDA_MAX_ROWS
    wrapped = np.concatenate([polar[-pad:], polar, polar[:pad]], axis=0)
    out = np.empty_like(polar)
    for lam in np.unique(lam_per_column):
        cols = np.flatnonzero(lam_per_column == lam)
        c0, c1 = int(cols[0]), int(cols[-1]) + 1  # λ is monotone in r, so columns are contiguous
        block = np.ascontiguousarray(wrapped[:, c0:c1])
        se = np.ones((int(lam), 1), dtype=np.uint8)
        closed = cv2.morphologyEx(block, cv2.MORPH_CLOSE, se, borderType=cv2.BORDER_REPLICATE)
        opened = cv2.morphologyEx(block, cv2.MORPH_OPEN, se, borderType=cv2.BORDER_REPLICATE)
        out[:, c0:c1] = (0.5 * (closed + opened))[pad:-pad]
    return out


def reduce_metal_artifacts(
    patch_hu: NDArray[np.floating] | NDArray[np.integer], pixel_mm: float, params: MarParams = MarParams()
) -> MarResult:
    """Polar closing–opening-average MAR of one patch around one metal object.

    Parameters
    ----------
    patch_hu : ndarray, shape (rows, cols)
        One slice patch in HU (any real dtype), centred roughly on the metal.
    pixel_mm : float
        In-plane pixel size in mm.
    params : MarParams

    Returns
    -------
    MarResult
        ``patch`` is float32 HU with the metal pixels (≥ ``metal_threshold_hu``)
        unchanged and the rest replaced by the filtered image.
    """
    img = np.ascontiguousarray(patch_hu, dtype=np.float32)
    source = find_streak_source(img, pixel_mm, params)
    h, w = img.shape
    cx, cy = float(source.center_px[0]), float(source.center_px[1])
    # radius reaching the farthest corner, so the inverse warp covers the whole patch
    max_r = math.hypot(max(cx, w - 1 - cx), max(cy, h - 1 - cy)) + 1.0
    n_r = math.ceil(max_r)
    # warpPolar leaves samples outside the source undefined: pad (replicate) so every
    # sample up to max_r lies inside, then crop after the inverse warp
    pad = n_r + 1
    padded = cv2.copyMakeBorder(img, pad, pad, pad, pad, cv2.BORDER_REPLICATE)
    centre = (cx + pad, cy + pad)
    polar = np.asarray(
        cv2.warpPolar(
            padded, (n_r, params.n_angles), centre, max_r, cv2.WARP_POLAR_LINEAR + cv2.INTER_LINEAR
        ),
        dtype=np.float32,
    )
    radius_px = np.asarray((np.arange(n_r) + 0.5) * (max_r / n_r), dtype=np.float64)
    lam = adaptive_lambda_rows(radius_px, pixel_mm, params)
    coa = closing_opening_average(polar, lam)
    back = cv2.warpPolar(
        coa,
        (w + 2 * pad, h + 2 * pad),
        centre,
        max_r,
        cv2.WARP_POLAR_LINEAR + cv2.INTER_LINEAR + cv2.WARP_INVERSE_MAP,
    )
    filtered = back[pad : pad + h, pad : pad + w]
    mask = img >= params.metal_threshold_hu
    out = np.where(mask, img, filtered).astype(np.float32)
    return MarResult(patch=out, filtered=filtered.astype(np.float32), metal_mask=mask, source=source)


def streak_energy_hu(
    patch_hu: NDArray[np.floating] | NDArray[np.integer],
    center_px: tuple[float, float],
    inner_px: float,
    outer_px: float,
) -> float:
    """Standard deviation (HU) of the pixels in an annulus around ``center_px`` (x, y).

    The measure of streak strength used to compare MAR on and off: in a
    uniform background the annulus SD is the noise; streaks add to it.
    """
    p = np.asarray(patch_hu, dtype=np.float64)
    yy, xx = np.mgrid[0 : p.shape[0], 0 : p.shape[1]]
    r2 = (xx - center_px[0]) ** 2 + (yy - center_px[1]) ** 2
    ring = (r2 >= inner_px**2) & (r2 <= outer_px**2)
    return float(np.std(p[ring])) if ring.any() else math.nan
