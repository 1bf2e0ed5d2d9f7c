"""Step 3 of the detection: the sub-voxel centroid of a sphere on the raw volume, and its axial profile.

Every sphere is first located by an intensity-weighted 3-D centroid of the raw voxels above the
local background + a margin inside a ball (:func:`subvoxel_centre`, iterated); the background
is a plane fitted through a shell outside the ball, so a sphere on the phantom face is weighted
over its own signal.  The centroid is the ``subvoxel`` estimator's answer and every other
estimator's start.  Its slice coordinate is refined by a quadratic through the per-slice sums of
the weights (:func:`axial_profile_position`): the slices are coarse, and the plain centroid is
pulled towards the nearest slice centre.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from typing import Any, Final

import numpy as np
from numpy.typing import NDArray

from registration.arrays import F64
from registration.detection.candidates import Support
from registration.detection.params import DetectionParams

SATURATION_MIN_VOXELS: Final = 3
"""A crop whose maximum is held by at least this many voxels is clipped there (a 12-bit export
stores 3071 HU for every metal voxel; noise makes a tie of 3 unclipped voxels improbable)."""


LINEAR_BACKGROUND_MIN_VOXELS: Final = 20
"""Shell voxels needed to fit the 4-parameter linear background (5 per parameter); a smaller
shell (a sphere in a corner of the volume) gets the constant median."""


def support_mask(
    lo_ijk: NDArray[np.int_],
    hi_ijk: NDArray[np.int_],
    support: Support,
) -> NDArray[np.bool_]:
    """The (k, j, i) crop [lo, hi) of a split core's support mask (False outside its box)."""
    box, mask = support
    out = np.zeros((hi_ijk[2] - lo_ijk[2], hi_ijk[1] - lo_ijk[1], hi_ijk[0] - lo_ijk[0]), dtype=bool)
    src, dst = [], []
    for ax, b in zip((2, 1, 0), box, strict=True):
        a0, a1 = max(int(lo_ijk[ax]), b.start), min(int(hi_ijk[ax]), b.stop)
        if a1 <= a0:
            return out
        src.append(slice(a0 - b.start, a1 - b.start))
        dst.append(slice(a0 - int(lo_ijk[ax]), a1 - int(lo_ijk[ax])))
    out[dst[0], dst[1], dst[2]] = mask[src[0], src[1], src[2]]
    return out


@dataclass(frozen=True, eq=False)
class BallWeights:
    """Centroid weights of the voxels in the ball around a centre (internal).

    ``w`` (k, j, i) crop of weights (0 outside the ball / support), ``ijk`` the crop's index
    grids (i, j, k) broadcastable to it, ``bg_hu`` and ``peak_hu`` of the crop, ``saturated``
    whether the ball is clipped at ``peak_hu`` (:data:`SATURATION_MIN_VOXELS`).
    """

    w: NDArray[np.float64]
    ijk: tuple[F64, F64, F64]
    bg_hu: float
    peak_hu: float
    saturated: bool = False


def ball_weights(
    vox: NDArray[Any], centre_ijk: F64, spacing: F64, params: DetectionParams, support: Support | None
) -> BallWeights:
    """Weights of the voxels within ``radius + bloom`` mm of ``centre_ijk`` for the centroid.

    The weight is ``min(HU − background, cap) − margin`` (≥ 0).  The background is, per
    ``params.background_model``, the median of the ``background_shell_mm`` shell outside the ball
    (``constant``) or a least-squares plane a + g·x through the shell voxels (``linear``).
    ``cap`` (saturated crops only) is the lowest sphere signal that saturates anywhere (saturation
    − the highest background), so a clipped plateau weighs the same over air and over plastic; the
    margin is ``centroid_margin_fraction`` of the sphere signal.
    """
    r_ball = params.radius_mm + params.bloom_mm
    r_shell = r_ball + params.background_shell_mm
    half = np.ceil(r_shell / spacing).astype(int) + 1  # (i, j, k) voxels
    shape = vox.shape  # (k, j, i)
    c = np.rint(centre_ijk).astype(int)
    lo = np.maximum(c - half, 0)
    hi = np.minimum(c + half + 1, (shape[2], shape[1], shape[0]))
    crop = np.asarray(vox[lo[2] : hi[2], lo[1] : hi[1], lo[0] : hi[0]], dtype=np.float64)
    ii = np.arange(lo[0], hi[0], dtype=np.float64)[None, None, :]
    jj = np.arange(lo[1], hi[1], dtype=np.float64)[None, :, None]
    kk = np.arange(lo[2], hi[2], dtype=np.float64)[:, None, None]
    off = [np.broadcast_to((g - centre_ijk[a]) * spacing[a], crop.shape) for a, g in enumerate((ii, jj, kk))]
    d2 = off[0] ** 2 + off[1] ** 2 + off[2] ** 2
    ball = d2 <= r_ball**2
    shell = (d2 > r_ball**2) & (d2 <= r_shell**2)
    bg = float(np.median(crop[shell])) if shell.any() else float(np.median(crop))
    peak = float(crop[ball].max()) if ball.any() else float(crop.max())
    if params.background_model == "linear" and int(shell.sum()) > LINEAR_BACKGROUND_MIN_VOXELS:
        a = np.stack([np.ones(int(shell.sum()))] + [o[shell] for o in off], axis=1)
        coef = np.linalg.lstsq(a, crop[shell], rcond=None)[0]
        bg_field = coef[0] + coef[1] * off[0] + coef[2] * off[1] + coef[3] * off[2]
    else:
        bg_field = np.full(crop.shape, bg)
    signal = crop - bg_field
    saturated = ball.any() and int(np.count_nonzero(crop[ball] == peak)) >= SATURATION_MIN_VOXELS
    cap = peak - float(bg_field[ball].max()) if saturated else math.inf
    s_peak = cap if saturated else (float(signal[ball].max()) if ball.any() else peak - bg)
    margin = max(params.centroid_margin_hu, params.centroid_margin_fraction * s_peak)
    if support is not None:
        ball = ball & support_mask(lo, hi, support)
    w = np.where(ball, np.clip(np.minimum(signal, cap) - margin, 0.0, None), 0.0)
    return BallWeights(w, (ii, jj, kk), bg, peak, bool(saturated))


def subvoxel_centre(
    vox: NDArray[Any],
    start_ijk: F64,
    spacing: F64,
    params: DetectionParams,
    support: Support | None = None,
) -> tuple[F64, float, float]:
    """Intensity-weighted 3-D centroid of the raw voxels above background + margin.

    With a split core's ``support``, only voxels inside it are weighted (the streak tails the
    split cut off would pull the centroid towards the neighbours they lead to).

    Returns (centre (i, j, k), background HU, peak HU).  The ball has radius
    ``radius + bloom`` mm; the background is the median of the shell between
    that radius and ``background_shell_mm`` farther out.
    """
    centre = start_ijk.astype(np.float64).copy()
    bg = peak = math.nan
    for _ in range(max(1, params.centroid_iterations)):
        bw = ball_weights(vox, centre, spacing, params, support)
        bg, peak = bw.bg_hu, bw.peak_hu
        total = float(bw.w.sum())
        if total <= 0.0:
            break
        centre = np.array([float((bw.w * g).sum()) / total for g in bw.ijk])
    return centre, bg, peak


AXIAL_PROFILE_MIN_SLICES: Final = 3
"""A quadratic in z has 3 coefficients: fewer profile slices cannot place its vertex."""


def axial_profile_position(bw: BallWeights, min_fraction: float) -> float | None:
    """The slice index (continuous k) of the vertex of a quadratic fitted to the per-slice weight sums.

    A sphere thresholded at a level is the level's iso-surface, a ball of some radius R_t: its
    cross-section in slice z is a disc of area π(R_t² − (z − z0)²), a parabola in z whatever the
    sampling phase (under a wider slice profile an ellipsoid, still a parabola: the factor
    R_t² / c_t² on (z − z0)²), and an in-plane edge ramp of the same shape in every slice adds a constant
    (the ramp's second moment).  So the per-slice sums of the centroid weights m_k = a + b·k + c·k²
    put z0 at −b / 2c exactly where the centroid Σ m_k k / Σ m_k of 3–4 coarse slices is pulled
    towards the nearest slice centre (±0.06 mm on 0.833 mm slices).  Only slices with
    at least ``min_fraction`` of the largest sum are fitted: the tips, where the slice grazes the
    cap and the blur rounds the profile, are not a parabola.  None (keep the centroid) if fewer
    than :data:`AXIAL_PROFILE_MIN_SLICES` slices qualify, the fitted profile is not concave, its
    vertex lies outside the fitted slices, or the profile touches the crop's first or last slice
    (cut by the ball or the volume: a one-sided profile).
    """
    m = bw.w.sum(axis=(1, 2))
    k = bw.ijk[2].ravel()
    if len(m) == 0 or float(m.max()) <= 0.0:
        return None
    keep = np.flatnonzero(m >= min_fraction * float(m.max()))
    if len(keep) < AXIAL_PROFILE_MIN_SLICES or keep[0] == 0 or keep[-1] == len(m) - 1:
        return None
    k0 = float(k[keep].mean())
    u = k[keep] - k0
    a = np.stack([np.ones_like(u), u, u * u], axis=1)
    _, b, c = np.linalg.lstsq(a, m[keep], rcond=None)[0]
    if c >= 0.0:
        return None
    vertex = k0 - float(b) / (2.0 * float(c))
    return vertex if k[keep[0]] <= vertex <= k[keep[-1]] else None


def axial_profile_centre(
    vox: NDArray[Any], centre_ijk: F64, spacing: F64, params: DetectionParams, support: Support | None = None
) -> F64:
    """``centre_ijk`` with its slice coordinate from the per-slice profile (:func:`axial_profile_position`)
    of the centroid weights around it (unchanged where the profile does not give one)."""
    cp = replace(params, centroid_margin_fraction=params.axial_profile_margin_fraction)
    k = axial_profile_position(
        ball_weights(vox, centre_ijk, spacing, cp, support), params.axial_profile_min_fraction
    )
    return centre_ijk if k is None else np.array([centre_ijk[0], centre_ijk[1], k])
