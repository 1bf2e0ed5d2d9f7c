"""Centre of a sphere from the level crossings of rays cast from an estimate (``rays``).

A weighted centroid integrates everything above its margin in its window: a bright streak that
lengthens a clipped plateau on one side of a sphere pulls it along the streak (the
worst cone-beam steel sphere: a 7 × 4 voxel plateau, 0.17 mm error).  Here the sphere is located
by its outline instead.  From the current estimate, N unit directions d (a Fibonacci set closed
under d → −d, in mm space) are cast; along each, the distance r(d) at which the background-
subtracted image first falls below a fraction (0.7, :class:`RayParams`) of the sphere's (clipped)
contrast is found with trilinear sampling.  The crossings are those of an axis-aligned ellipsoid
offset by δ (in-plane semi-axis a shared by i and j, axial c: the slices are thicker than the
pixels); to first order in δ

    r(d) ≈ a · (dx² + dy²) + c · dz² + δ · d,

fitted by iteratively reweighted least squares with Tukey's biweight, so rays along a streak (too
long) or a dark band (too short) lose their weight instead of pulling the centre.  The estimate
moves by δ and the rays are cast again.  On a direction set closed under d → −d the odd term δ · d
is orthogonal to the even shape terms, so the first-order shape model biases δ only through the
robust weights.  Pure numpy: the detect CLI path must not import scipy.ndimage / scipy.optimize.

What the sweep showed (:class:`RayParams`): the Tukey weights were seldom zero on the
simulator's steel and titanium spheres (a zero-weight fraction of 0 for the median sphere, ≤ 0.03
for the 90th percentile), so the gain over the centroid comes mostly from locating the outline at
70 % of the clipped contrast, against a background plane fitted 3–4.5 mm beyond the sphere, rather
than integrating the window, not from rejecting rays.  The rays' axial offset measured worse than
the centroid's per-slice profile (the slices are coarse), so the ``rays`` method keeps only the
in-plane centre (:mod:`registration.detection.estimators.rays`).  On tungsten carbide the
``core`` centroid stays better (cone-beam SPR 0.3, 3.0 mm reach: 0.072 / 0.271 mm against
0.062 / 0.159).

Coordinates: voxel indices (i, j, k) and mm along unit directions in the (i, j, k)-scaled mm space,
as :mod:`registration.detection` uses.
"""

from __future__ import annotations

import functools
import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, Final

import numpy as np
from numpy.typing import NDArray

from registration.arrays import F64

TUKEY_C: Final = 4.685
"""Tukey biweight cut-off in robust standard deviations (95 % efficiency for Gaussian residuals)."""

MAD_TO_SIGMA: Final = 1.4826
"""Median absolute deviation → standard deviation for Gaussian residuals."""

IRLS_WEIGHT_TOLERANCE: Final = 1.0e-3
"""The robust fit stops once no weight changes by more than this between passes."""

CROP_MARGIN_VOXELS: Final = 2
"""The voxels copied reach this many voxels past the background shell around the start, so the
rays (which end at the reach, a shell's thickness inside it) stay in the copy for any shift up to
``max_shift_mm`` (a ray that left it would have no crossing and drop out)."""

SHELL_STEP_MM: Final = 0.25
"""Sampling step of the background shell along the rays (mm): ~0.6 pixel, 96 × 6 samples."""

N_MODEL: Final = 5
"""Parameters of the crossing model: a, c, δ (3)."""


@dataclass(frozen=True)
class RayParams:
    """Settings of :func:`ray_centre` (mm, fractions of the sphere's contrast).

    Rays are cast from a centroid of the sphere to where the image crosses ``level_fraction`` of
    its clipped contrast above a local background plane, and a sphere is fitted robustly to the
    crossings.  Each default was chosen on the simulator's 40-scan hard sweep
    (``python -m benchmarks.bench_detection --hard 40``), one setting at a time; the figures of
    every alternative measured are in ``docs/detection-settings.md`` ("rays").

    Attributes
    ----------
    n_directions : int
        Rays cast per iteration (half of them the negatives of the other half).
    step_mm : float
        Coarse step along a ray, half the 0.4 mm pixel (the trilinear image cannot dip below the
        level and back within it); the first crossing interval is resampled at ``refine`` sub-steps.
    refine : int
        Sub-steps of the crossing interval (0.2 / 4 = 0.05 mm).
    reach_mm : float
        Rays are followed to the nominal radius + this, where the background shell starts (a
        nearer shell holds the sphere's bloom and raises the background).
    level_fraction : float
        The crossing level: background + this fraction of the sphere's (clipped) contrast.
    iterations : int
        Casts at most (each from the moved estimate).
    tolerance_mm : float
        No further cast once an estimate moves less than this (first-order error ~δ² / radius).
    irls_iterations : int
        Reweighting passes of the robust fit at most.
    min_scale_mm : float
        Floor of the robust residual scale (a noise-free symmetric sphere has residuals ≈ 0).
    min_rays_fraction : float
        Refuse when fewer than this fraction of the rays cross the level inside the reach and the
        data, or keep a weight in the robust fit.
    max_shift_mm : float
        Refuse when the estimate would move farther than this from the start (the start is a
        centroid of the same sphere: a larger move means the fit locked onto something else).
    shell_mm : float
        The background is a least-squares plane through the voxels between the reach and the
        reach + this.
    """

    n_directions: int = 96
    step_mm: float = 0.2
    refine: int = 4
    reach_mm: float = 3.0
    level_fraction: float = 0.7
    iterations: int = 2
    tolerance_mm: float = 0.02
    irls_iterations: int = 4
    min_scale_mm: float = 0.02
    min_rays_fraction: float = 0.5
    max_shift_mm: float = 1.0
    shell_mm: float = 1.5


@functools.lru_cache(maxsize=8)
def symmetric_directions(n: int) -> F64:
    """(2·⌈n/2⌉, 3) unit vectors (read-only): a Fibonacci set on the upper half-sphere and their
    negatives."""
    m = max(1, (n + 1) // 2)
    k = np.arange(m, dtype=np.float64) + 0.5
    z = k / m  # uniform in (0, 1]: equal-area bands of the upper half-sphere
    phi = k * math.pi * (3.0 - math.sqrt(5.0))
    rho = np.sqrt(1.0 - z * z)
    half = np.stack([rho * np.cos(phi), rho * np.sin(phi), z], axis=1)
    dirs = np.concatenate([half, -half], axis=0)
    dirs.flags.writeable = False
    return dirs


@dataclass(frozen=True)
class _Crop:
    """A float copy of the voxels around the sphere, NaN outside the circular FOV (internal)."""

    values: F64  # (k, j, i), C-contiguous
    lo_ijk: NDArray[np.int64]


def _crop(
    vox: NDArray[Any], centre_ijk: F64, half_ijk: NDArray[np.int64], spacing: F64, fov_radius_mm: float | None
) -> _Crop:
    """The voxels within ``half_ijk`` of ``centre_ijk`` (clamped to the array); NaN where less
    than a pixel inside the circular field of view (centred on the matrix, as
    ``registration.detection`` finds it), so no sample interpolates padding."""
    c = np.rint(centre_ijk).astype(np.int64)
    lo = np.maximum(c - half_ijk, 0)
    hi = np.minimum(c + half_ijk + 1, (vox.shape[2], vox.shape[1], vox.shape[0]))
    vals = np.array(vox[lo[2] : hi[2], lo[1] : hi[1], lo[0] : hi[0]], dtype=np.float64)
    if fov_radius_mm is not None:
        di = (np.arange(lo[0], hi[0]) - (vox.shape[2] - 1) / 2.0) * spacing[0]
        dj = (np.arange(lo[1], hi[1]) - (vox.shape[1] - 1) / 2.0) * spacing[1]
        outside = np.hypot(di[None, :], dj[:, None]) > fov_radius_mm - float(np.hypot(spacing[0], spacing[1]))
        vals[:, outside] = np.nan
    return _Crop(vals, lo)


def _sample(crop: _Crop, ijk: F64) -> F64:
    """Trilinear samples at (..., 3) voxel positions (i, j, k); NaN outside the crop or next to a
    NaN voxel."""
    nk, nj, ni = crop.values.shape
    p = ijk - crop.lo_ijk
    base = np.floor(p).astype(np.int64)
    f = p - base
    bi, bj, bk = base[..., 0], base[..., 1], base[..., 2]
    ok = (bi >= 0) & (bi < ni - 1) & (bj >= 0) & (bj < nj - 1) & (bk >= 0) & (bk < nk - 1)
    i0 = np.where(ok, (bk * nj + bj) * ni + bi, 0)
    flat = crop.values.ravel()
    fi, fj, fk = f[..., 0], f[..., 1], f[..., 2]
    out = np.zeros(p.shape[:-1], np.float64)
    for step_k, wk in ((0, 1.0 - fk), (nj * ni, fk)):
        for step_j, wj in ((0, 1.0 - fj), (ni, fj)):
            row = i0 + step_k + step_j
            out += wk * wj * ((1.0 - fi) * flat[row] + fi * flat[row + 1])
    return np.where(ok, out, np.nan)


def _background(values_hu: F64, offsets_mm: F64) -> F64 | None:
    """(4,) least-squares plane a + g · x (HU, x the (V, 3) ``offsets_mm``) through the finite
    samples ``values_hu`` (V,); None if too few."""
    ok = np.isfinite(values_hu)
    n = int(ok.sum())
    if n < 4 * N_MODEL:
        return None
    a = np.c_[np.ones(n), offsets_mm[ok]]
    return np.asarray(np.linalg.lstsq(a, values_hu[ok], rcond=None)[0], dtype=np.float64)


def _first_below(signal: F64, level: float) -> tuple[NDArray[np.intp], NDArray[np.bool_]]:
    """(N,) index of the first sample of each row of ``signal`` (N, T) below ``level``, and
    whether it is a crossing: the row starts above the level and the sample is data, not NaN."""
    below = ~(signal >= level)  # NaN counts as "below": the finite test then rejects it
    first = np.argmax(below, axis=1)
    rows = np.arange(len(signal))
    ok = below[rows, first] & (first > 0)
    ok &= np.isfinite(signal[rows, np.where(ok, first, 0)])
    return first, ok


def _crossings(signal: F64, t_mm: F64, level: float) -> F64:
    """(N,) first t where each row of ``signal`` (N, T) falls below ``level`` (linear between
    samples; ``t_mm`` (T,) or per row (N, T)); NaN if a row starts below it, hits NaN data first
    or never falls below it."""
    first, ok = _first_below(signal, level)
    t = np.broadcast_to(t_mm, signal.shape)
    rows = np.arange(len(signal))
    i1 = np.where(ok, first, 1)
    v0, v1 = signal[rows, i1 - 1], signal[rows, i1]
    f = np.where(ok, (v0 - level) / np.where(v0 != v1, v0 - v1, 1.0), 0.0)
    r = t[rows, i1 - 1] + f * (t[rows, i1] - t[rows, i1 - 1])
    return np.where(ok, r, np.nan)


def _refined_crossings(
    crop: _Crop,
    c_ijk: F64,
    dirs: F64,
    spacing: F64,
    bg_at: Callable[[F64], F64],
    t_mm: F64,
    signal: F64,
    level: float,
    refine: int,
) -> F64:
    """(N,) crossings of ``level``: the bracket of the first coarse sample below it (``signal``
    (N, T) at ``t_mm``) resampled at ``refine`` sub-steps, then interpolated linearly."""
    first, ok = _first_below(signal, level)
    i1 = np.where(ok, first, 1)
    rows = np.arange(len(signal))
    frac = np.arange(1, refine) / refine
    t_in = t_mm[i1 - 1][:, None] + frac[None, :] * (t_mm[i1] - t_mm[i1 - 1])[:, None]  # (N, refine-1)
    pts_mm = t_in[..., None] * dirs[:, None, :]
    inner = _sample(crop, c_ijk + pts_mm / spacing) - bg_at(pts_mm)
    sig = np.concatenate([signal[rows, i1 - 1][:, None], inner, signal[rows, i1][:, None]], axis=1)
    t_rows = np.concatenate([t_mm[i1 - 1][:, None], t_in, t_mm[i1][:, None]], axis=1)
    # The bracket's first sample is above the level, so its first crossing is the ray's.
    return np.where(ok, _crossings(sig, t_rows, level), np.nan)


def robust_ellipsoid_fit(dirs: F64, r_mm: F64, params: RayParams) -> tuple[F64, F64] | None:
    """(a, c, δx, δy, δz) of ``r ≈ a·(dx²+dy²) + c·dz² + δ·d`` by Tukey IRLS, and the final weights;
    None if fewer than ``min_rays_fraction`` of the rays keep a weight."""
    a_mat = np.c_[dirs[:, 0] ** 2 + dirs[:, 1] ** 2, dirs[:, 2] ** 2, dirs]
    w = np.ones(len(r_mm))
    coef = np.zeros(N_MODEL)
    for _ in range(max(1, params.irls_iterations)):
        aw = a_mat * w[:, None]
        try:
            coef = np.linalg.solve(aw.T @ a_mat, aw.T @ r_mm)
        except np.linalg.LinAlgError:
            return None
        res = r_mm - a_mat @ coef
        dev = np.abs(res)
        mad = float(np.partition(dev, len(dev) // 2)[len(dev) // 2])
        scale = max(params.min_scale_mm, MAD_TO_SIGMA * mad)
        u = res / (TUKEY_C * scale)
        w_new = np.where(np.abs(u) < 1.0, (1.0 - u * u) ** 2, 0.0)
        if int(np.count_nonzero(w_new)) < max(N_MODEL + 1, params.min_rays_fraction * len(r_mm)):
            return None
        converged = float(np.abs(w_new - w).max()) < IRLS_WEIGHT_TOLERANCE
        w = w_new
        if converged:
            break
    return np.asarray(coef, dtype=np.float64), w


@dataclass(frozen=True)
class RayFit:
    """The outcome of :func:`ray_centre`: the centre (voxel indices) or None and why not."""

    centre_ijk: F64 | None
    reason: str = ""
    n_rays: int = 0
    semi_axes_mm: tuple[float, float] = (math.nan, math.nan)
    outlier_fraction: float = math.nan


def ray_centre(
    vox: NDArray[Any],
    start_ijk: F64,
    spacing: F64,
    radius_mm: float,
    saturation_hu: float,
    params: RayParams,
    fov_radius_mm: float | None = None,
) -> RayFit:
    """The centre of the sphere near ``start_ijk`` (voxel indices (i, j, k)) from its outline.

    ``vox`` [k, j, i] HU, ``spacing`` (i, j, k) mm, ``radius_mm`` the nominal radius,
    ``saturation_hu`` the export's clip value (inf if the sphere is not clipped),
    ``fov_radius_mm`` the radius of the reconstruction's circular field of view (None: none).
    A ray ends without a crossing where it leaves the array or the field of view before falling
    below the level; a sphere cut by an edge is the caller's to refuse.
    """
    dirs = symmetric_directions(params.n_directions)
    reach = radius_mm + params.reach_mm
    t = np.arange(0.0, reach + 0.5 * params.step_mm, params.step_mm)
    pts_mm = t[None, :, None] * dirs[:, None, :]  # (N, T, 3) from the estimate
    start = np.asarray(start_ijk, dtype=np.float64)
    # The background: a plane through samples of the shell along the same directions.
    t_shell = np.arange(reach + SHELL_STEP_MM, reach + params.shell_mm + 0.5 * SHELL_STEP_MM, SHELL_STEP_MM)
    shell_mm = (t_shell[None, :, None] * dirs[:, None, :]).reshape(-1, 3)
    half = np.ceil((reach + params.shell_mm) / spacing).astype(np.int64) + CROP_MARGIN_VOXELS
    crop = _crop(vox, start, half, spacing, fov_radius_mm)
    bg = _background(_sample(crop, start + shell_mm / spacing), shell_mm)
    if bg is None:
        return RayFit(None, "rays: too few background samples around the sphere")
    c = start.copy()
    fit: tuple[F64, F64] | None = None
    n_ok = 0
    for _ in range(max(1, params.iterations)):
        shift_mm = (c - start) * spacing

        def bg_at(p_mm: F64, shift_mm: F64 = shift_mm) -> F64:
            return np.asarray(bg[0] + (p_mm + shift_mm) @ bg[1:], dtype=np.float64)

        bg_hu = bg_at(pts_mm)
        values = _sample(crop, c + pts_mm / spacing)
        signal = values - bg_hu
        finite = np.isfinite(values)
        if not finite.any():
            return RayFit(None, "rays: no image data around the sphere")
        clipped = math.isfinite(saturation_hu) and float(values[finite].max()) >= saturation_hu - 0.5
        top = saturation_hu - float(bg_hu.max()) if clipped else float(signal[finite].max())
        if top <= 0.0:
            return RayFit(None, "rays: no signal above the background")
        r = _refined_crossings(
            crop, c, dirs, spacing, bg_at, t, signal, params.level_fraction * top, params.refine
        )
        ok = np.isfinite(r)
        n_ok = int(ok.sum())
        if n_ok < max(N_MODEL + 1, params.min_rays_fraction * len(dirs)):
            return RayFit(None, f"rays: {n_ok} of {len(dirs)} rays cross the level", n_ok)
        fit = robust_ellipsoid_fit(dirs[ok], r[ok], params)
        if fit is None:
            return RayFit(None, "rays: too few rays fit an ellipsoid", n_ok)
        delta = fit[0][2:] / spacing
        c = c + delta
        if float(np.linalg.norm((c - start) * spacing)) > params.max_shift_mm:
            return RayFit(
                None, f"rays: the outline's centre is > {params.max_shift_mm} mm from the start", n_ok
            )
        if float(np.linalg.norm(delta * spacing)) < params.tolerance_mm:
            break
    assert fit is not None
    return RayFit(c, "", n_ok, (float(fit[0][0]), float(fit[0][1])), float(np.mean(fit[1] == 0.0)))
