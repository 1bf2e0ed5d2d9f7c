"""Where the imaged region ends: the circular field of view, the volume's edges, and the spheres they cut.

Scanners pad the voxels outside the reconstruction's FOV circle with one constant; the circle is
found from that padding (:func:`circular_fov_radius_mm`).  A sphere whose nominal ball crosses
the volume's edge or the FOV circle is refused (:func:`edge_reject_reason`,
:func:`fov_reject_reason`): it is not fully imaged, and the registration needs whole spheres.

Near an in-plane edge the voxels past it hold padding, and a sphere's clipped plateau may run
into it — the sphere's own, or only the bloom around a whole sphere close to the edge.  A window
symmetric about the centre then cannot say where the centre is along the edge normal (every
window position inside the plateau is a fixed point of its re-centring: a tungsten-carbide sphere
cut by 0.85 mm was reported 0.87 mm inside its true position), and the inner edge does not
either (the bloom is anisotropic).  So a sphere whose image is still near its peak where the data
end is refused (:func:`plateau_reaches_edge`): it is cut, or whole but too close to the edge to
be located.  Where the plateau ends inside the data, :mod:`.refine` locates it.

Everything here works in voxel indices (i, j, k) and mm along unit directions given in the
(i, j, k)-scaled mm space.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, Final

import numpy as np
from numpy.typing import NDArray

from registration.arrays import F64

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


AIR_HU: Final = -1000.0
"""Padding outside a circular FOV is stored at or below air (−1024 HU for RescaleIntercept −1024)."""


FOV_CORNER_PX: Final = 3
"""Side of the corner blocks tested for constant padding: 9 equal pixels do not happen by chance in
a noisy reconstruction, and a 3-pixel corner is inside the padding of any circular FOV."""


FOV_PADDED_FRACTION: Final = 0.99
"""An annulus (one pixel wide) around the matrix centre is outside the FOV when at least this
fraction of its voxels holds the padding value.  Air inside the FOV clipped to the same value is
scattered (noise about −1000 HU crosses −1024 in a fraction of the voxels, not in 99 %)."""


def circular_fov_radius_mm(vox: NDArray[Any], spacing: F64) -> float | None:
    """Radius of the reconstruction's circular field of view (centred on the matrix), or None.

    Scanners (and the simulator) fill the voxels outside the FOV circle with one constant (the
    lowest stored value).  If the four 3 × 3 corner blocks of the middle slice all hold that one
    value, the FOV is the circle inside which the padding stops: the inscribed circle if the
    image reaches it, else the radius of the farthest image voxel inside the smallest radius
    beyond which every one-pixel annulus is padded (:data:`FOV_PADDED_FRACTION`).  The
    simulator pads outside the inscribed circle; a scanner
    whose FOV is smaller than its matrix (say 200 mm on a 512 × 0.415 mm matrix; the O-arm's FOV
    diameter is unverified) pads inside the inscribed circle too, and a sphere cut there must not
    be taken for a whole one.
    """
    k = vox.shape[0] // 2
    sl = vox[k]
    n = FOV_CORNER_PX
    corners = [sl[:n, :n], sl[:n, -n:], sl[-n:, :n], sl[-n:, -n:]]
    v0 = corners[0].flat[0]
    if not all(bool(np.all(c == v0)) for c in corners):
        return None
    if float(v0) > AIR_HU:  # a constant but not air-or-below corner is an image, not padding
        return None
    inscribed_mm = float(min(vox.shape[1] * spacing[1], vox.shape[2] * spacing[0]) / 2.0)
    pixel_mm = float(min(spacing[0], spacing[1]))
    jj, ii = np.indices(sl.shape)
    r_mm = np.hypot((ii - (sl.shape[1] - 1) / 2.0) * spacing[0], (jj - (sl.shape[0] - 1) / 2.0) * spacing[1])
    ring = np.floor(r_mm / pixel_mm).astype(np.int64)
    n_rings = int(inscribed_mm / pixel_mm)
    inside = ring < n_rings
    total = np.bincount(ring[inside], minlength=n_rings)
    padded = np.bincount(ring[inside], weights=(sl[inside] == v0).astype(np.float64), minlength=n_rings)
    frac = np.divide(padded, total, out=np.zeros(n_rings), where=total > 0)
    open_rings = np.flatnonzero(frac < FOV_PADDED_FRACTION)
    if len(open_rings) == 0:
        return 0.0
    if open_rings[-1] == n_rings - 1:  # image up to the inscribed circle
        return inscribed_mm
    image = inside & (ring <= open_rings[-1]) & (sl != v0)
    return float(r_mm[image].max()) if image.any() else 0.0


def boundaries(
    centre_ijk: F64, shape: tuple[int, int, int], spacing: F64, fov_radius_mm: float | None
) -> list[tuple[str, F64, float, float]]:
    """(name, unit direction (i, j, k) in mm space, edge position along it mm, voxel step mm) of
    every boundary of the imaged region: both slab ends, the matrix edges and the circular FOV."""
    last = np.array([shape[2] - 1, shape[1] - 1, shape[0] - 1], dtype=np.float64)
    names = ("edge of the volume (matrix edge)",) * 2 + ("edge of the volume (first/last slice)",)
    out: list[tuple[str, F64, float, float]] = []
    for ax in range(3):
        e = np.zeros(3)
        e[ax] = 1.0
        out.append((names[ax], -e, 0.0, float(spacing[ax])))
        out.append((names[ax], e, float(last[ax] * spacing[ax]), float(spacing[ax])))
    if fov_radius_mm is not None:
        fov_c = np.array([last[0] / 2.0, last[1] / 2.0, 0.0]) * spacing
        off = centre_ijk * spacing - fov_c
        off[2] = 0.0
        rho = float(np.hypot(off[0], off[1]))
        if rho > 0.0:
            u = off / rho
            step = float(0.5 * (spacing[0] + spacing[1]))
            out.append(("circular field of view", u, fov_radius_mm + float(u @ fov_c), step))
    return out


def near_imaged_edge(
    centre_ijk: F64, shape: tuple[int, int, int], spacing: F64, fov_radius_mm: float | None, reach_mm: float
) -> bool:
    """Whether an edge of the imaged region (:func:`boundaries`) is within ``reach_mm`` of the centre."""
    return any(
        edge_mm - float(u @ (centre_ijk * spacing)) <= reach_mm
        for _, u, edge_mm, _ in boundaries(centre_ijk, shape, spacing, fov_radius_mm)
    )


def edge_reject_reason(
    centre_ijk: F64, shape: tuple[int, int, int], spacing: F64, radius_mm: float
) -> str | None:
    """Why a sphere is cut by the edge of the sampled volume (voxel centres 0 … n−1), or None.

    Blooming may touch the first/last slice, the nominal sphere itself may not.
    """
    last = np.array([shape[2] - 1, shape[1] - 1, shape[0] - 1])
    room_mm = np.minimum(centre_ijk, last - centre_ijk) * spacing
    if float(room_mm.min()) < radius_mm:
        return (
            f"cut by the edge of the volume (first/last slice or matrix edge): centre "
            f"{float(room_mm.min()):.2f} mm from the edge < sphere radius {radius_mm} mm"
        )
    return None


def fov_reject_reason(
    centre_ijk: F64, fov_radius_mm: float | None, shape: tuple[int, int, int], spacing: F64, radius_mm: float
) -> str | None:
    """Why a sphere is cut by the circular field of view (centred on the matrix), or None."""
    if fov_radius_mm is None:
        return None
    fov_centre = np.array([(shape[2] - 1) / 2.0, (shape[1] - 1) / 2.0])
    off_axis_mm = float(np.hypot(*((centre_ijk[:2] - fov_centre) * spacing[:2])))
    if off_axis_mm + radius_mm > fov_radius_mm:
        return (
            f"cut by the circular field of view: {off_axis_mm:.1f} mm off axis + radius {radius_mm} mm "
            f"> FOV radius {fov_radius_mm:.1f} mm"
        )
    return None
