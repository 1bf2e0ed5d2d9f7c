"""Whether a sphere's clipped plateau runs into an in-plane edge of the imaged region (FOV, matrix).

Where the circular field of view (or the matrix edge) cuts a sphere's image — the sphere itself,
or only the bloom around a whole sphere close to the edge — the voxels past the edge hold
padding.  A window symmetric about the centre then sees a plateau that runs into the edge and
cannot tell where the centre is along the edge normal: a clipped tungsten-carbide bloom is about
1.9 mm in radius around a 1.25 mm sphere, and every window position inside that plateau is a
fixed point of the re-centring (a sphere cut by 0.85 mm was reported 0.87 mm inside its true
position, far enough to pass "centre a radius inside the edge"; issue #11 held-out seeds).  Nor
does the inner edge say where the centre is: the bloom is anisotropic (a tungsten-carbide sphere
near the FOV edge reached its half level 2.6 mm inwards along the normal and 1.4 mm across it).
Where the plateau ends inside the data, the symmetric window holds both of its ends and locates
the sphere (:func:`registration.detection.edge_refined_centre`).  So a sphere whose image is still
near its peak where the data end is refused: it is cut, or whole but too close to the edge to be
located.

Everything here works in voxel indices (i, j, k) and mm along unit directions given in the
(i, j, k)-scaled mm space, as :mod:`registration.detection` does.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, Final

import numpy as np
from numpy.typing import NDArray

F64 = NDArray[np.float64]

PROFILE_STEP_MM: Final = 0.05
"""Sampling step along a profile (mm): far below the 0.4 mm pixel, so the linear interpolation
between samples adds nothing to the trilinear interpolation of the voxels."""

BUNDLE_OFFSET_FRACTION: Final = 0.25
"""The profile is the mean of a 3 × 3 bundle of parallel lines offset by ± this fraction of the
nominal radius across it (in-plane and axially): 9 lines average the noise that could end a
single line's profile below the level early."""


@dataclass(frozen=True)
class DataRegion:
    """Where a volume holds image data: inside the array and, if given, the circular FOV
    (centred on the matrix, radius in mm, in-plane)."""

    shape_kji: tuple[int, int, int]
    spacing_ijk_mm: F64
    fov_radius_mm: float | None

    def contains(self, ijk: F64) -> NDArray[np.bool_]:
        """(N,) whether each (N, 3) voxel position is image data (not padding, not off the array)."""
        last = np.array([self.shape_kji[2] - 1, self.shape_kji[1] - 1, self.shape_kji[0] - 1], np.float64)
        ok: NDArray[np.bool_] = np.all((ijk >= 0.0) & (ijk <= last), axis=1)
        if self.fov_radius_mm is not None:
            off = (ijk[:, :2] - last[:2] / 2.0) * self.spacing_ijk_mm[:2]
            ok &= np.hypot(off[:, 0], off[:, 1]) <= self.fov_radius_mm
        return ok


def sample_trilinear(vox: NDArray[Any], ijk: F64, region: DataRegion) -> F64:
    """(N,) samples of ``vox`` [k, j, i] at (N, 3) positions, trilinear over the corners inside
    ``region`` (weights renormalised, so padding never leaks into a profile); NaN where the
    nearest voxel is outside it.  The samples thus reach the last image voxel."""
    base = np.floor(ijk).astype(np.int64)
    frac = ijk - base
    acc = np.zeros(len(ijk), np.float64)
    wsum = np.zeros(len(ijk), np.float64)
    last = np.array([region.shape_kji[2] - 1, region.shape_kji[1] - 1, region.shape_kji[0] - 1])
    for corner in np.ndindex(2, 2, 2):
        idx = base + np.array(corner)
        w = np.prod(np.where(np.array(corner) == 1, frac, 1.0 - frac), axis=1)
        w = np.where(region.contains(idx.astype(np.float64)), w, 0.0)
        idx = np.clip(idx, 0, last)
        acc += w * np.asarray(vox[idx[:, 2], idx[:, 1], idx[:, 0]], dtype=np.float64)
        wsum += w
    near_ok = region.contains(np.rint(ijk))
    out = np.full(len(ijk), np.nan)
    good = near_ok & (wsum > 0.0)
    out[good] = acc[good] / wsum[good]
    return out


def line_profile(
    vox: NDArray[Any],
    centre_ijk: F64,
    spacing: F64,
    direction: F64,
    across: tuple[F64, F64],
    offset_mm: float,
    half_length_mm: float,
    region: DataRegion,
) -> tuple[F64, F64]:
    """(t mm, mean value) along ``direction`` (unit, mm space) through ``centre_ijk``, averaged
    over the 3 × 3 bundle offset by 0, ±``offset_mm`` along the two ``across`` unit directions.
    NaN where any line of the bundle leaves the data."""
    t = np.arange(-half_length_mm, half_length_mm + 0.5 * PROFILE_STEP_MM, PROFILE_STEP_MM)
    acc = np.zeros_like(t)
    for a in (-offset_mm, 0.0, offset_mm):
        for b in (-offset_mm, 0.0, offset_mm):
            pts_mm = centre_ijk * spacing + t[:, None] * direction + a * across[0] + b * across[1]
            acc += sample_trilinear(vox, pts_mm / spacing, region)
    return t, acc / 9.0


def first_crossing(t: F64, profile: F64, level: float, sign: int) -> float | None:
    """First position from t = 0 in the direction ``sign`` (±1) where ``profile`` falls below
    ``level`` (linear between samples), or None if the data end (NaN) or the profile ends first,
    or the profile is not above ``level`` at t = 0."""
    i0 = int(np.argmin(np.abs(t)))
    if not profile[i0] >= level:
        return None
    i = i0
    while 0 <= i + sign < len(t):
        nxt = i + sign
        if math.isnan(profile[nxt]):
            return None
        if profile[nxt] < level:
            f = (profile[i] - level) / (profile[i] - profile[nxt])
            return float(t[i] + f * (t[nxt] - t[i]))
        i = nxt
    return None


def plateau_level(
    vox: NDArray[Any],
    centre_ijk: F64,
    spacing: F64,
    r_ball_mm: float,
    shell_mm: float,
    region: DataRegion,
    fraction: float,
) -> float:
    """``fraction`` of the way from the background (median of the shell between ``r_ball_mm``
    and ``r_ball_mm + shell_mm``, image data only) to the brightest voxel of the ball."""
    r_shell = r_ball_mm + shell_mm
    half = np.ceil(r_shell / spacing).astype(int) + 1
    c = np.rint(centre_ijk).astype(int)
    lo = np.maximum(c - half, 0)
    hi = np.minimum(c + half + 1, np.array([region.shape_kji[2], region.shape_kji[1], region.shape_kji[0]]))
    grid = np.stack(
        np.meshgrid(*(np.arange(lo[a], hi[a]) for a in range(3)), indexing="ij"), axis=-1
    ).reshape(-1, 3)
    ijk = grid.astype(np.float64)
    d = np.linalg.norm((ijk - centre_ijk) * spacing, axis=1)
    ok = region.contains(ijk)
    vals = np.asarray(vox[grid[:, 2], grid[:, 1], grid[:, 0]], dtype=np.float64)
    shell = ok & (d > r_ball_mm) & (d <= r_shell)
    ball = ok & (d <= r_ball_mm)
    if not shell.any() or not ball.any():
        return math.nan
    bg = float(np.median(vals[shell]))
    return bg + fraction * (float(vals[ball].max()) - bg)


def plateau_reaches_edge(
    vox: NDArray[Any],
    centre_ijk: F64,
    spacing: F64,
    u: F64,
    radius_mm: float,
    r_ball_mm: float,
    shell_mm: float,
    region: DataRegion,
    fraction: float,
) -> bool:
    """Whether the sphere's image, followed from ``centre_ijk`` along the in-plane edge normal
    ``u``, is still above :func:`plateau_level` where the image data end: the edge cuts the
    sphere, or the clipped plateau of a whole sphere close to it.  Also True (refused) when the
    image at ``centre_ijk`` is itself below the level, or no background is left: an estimate that
    is not on the sphere's plateau cannot be checked against the edge, and refusing is the safe
    side (not seen on the simulator's scans, where the estimate is always on the plateau)."""
    level = plateau_level(vox, centre_ijk, spacing, r_ball_mm, shell_mm, region, fraction)
    if math.isnan(level):
        return True
    off = BUNDLE_OFFSET_FRACTION * radius_mm
    t, prof = line_profile(vox, centre_ijk, spacing, u, _across(u), off, r_ball_mm + shell_mm, region)
    return first_crossing(t, prof, level, +1) is None


def _across(u: F64) -> tuple[F64, F64]:
    """Two unit directions perpendicular to the unit ``u`` and to each other (for an in-plane
    ``u``: the in-plane one and the slice axis)."""
    ref = np.array([0.0, 0.0, 1.0]) if abs(float(u[2])) < 0.9 else np.array([1.0, 0.0, 0.0])
    v = np.cross(ref, u)
    v /= np.linalg.norm(v)
    return v, np.cross(u, v)
