"""Cone-beam O-arm simulation (issue #11 item 1.5): 3-D rays, flat panel, FDK through RTK.

An optional extra: needs ``itk-rtk`` (``pip install 'oarmreg[cbct]'``), imported lazily by
:func:`_rtk` only; the service never imports this module.

Geometry (RTK's, :class:`itk.RTK.ThreeDCircularProjectionGeometry`): a circular orbit about RTK's
y axis; at gantry angle θ the fixed frame is rotated by R = R_y(−θ), the source sits at
(0, 0, SID) and the flat panel at z = SID − SDD in the rotated frame.  The scanner frame of
:mod:`mocks.oarm.simulator` (rotation axis z) maps to RTK by x_r = x, y_r = z, z_r = −y.

Forward model per view, same analytic objects and polychromatic spectrum as the slice-wise
simulator: the plastic cube's chord at every pixel centre; around each sphere and empty hole
(its projected disc plus a pixel) ``subrays`` × ``subrays`` rays per pixel through every object,
their transmitted intensities averaged before the log.  Then kernel scatter (SPR), Poisson
noise, scintillator light spread, detector lag (recursive, first-frame lag
``lag_fraction``: 2–10 % in a-Si panels, Siewerdsen & Jaffray, Med Phys 26:1624 (1999),
doi:10.1118/1.598657), electronic noise, the log, water linearisation and RTK's FDK
(Feldkamp, Davis, Kress, JOSA A 1:612 (1984), doi:10.1364/JOSAA.1.000612).

O-arm numbers (research note calibration.md §4, **unverified**): SID ≈ 650 mm, SDD ≈ 1150 mm,
40 × 30 cm panel (PaxScan 4030CB-like; here 4 × 4 binned to 0.776 mm), 391 views over 360°.
Not modelled: the rod, the vertebra and the body (slice-wise simulator only), gantry flex.
"""

from __future__ import annotations

import dataclasses
import math
import time
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from mocks.oarm import physics
from mocks.oarm.simulator import (
    HU_MAX,
    HU_MIN,
    ORIENTATIONS,
    SceneExtras,
    SimulatedScan,
    image_from_scanner,
    kernel_scatter,
)
from registration import frames
from registration.errors import ConfigError
from registration.phantom import Phantom

F64 = NDArray[np.float64]
F32 = NDArray[np.float32]

RTK_FROM_SCANNER = np.array([[1.0, 0, 0, 0], [0, 0, 1.0, 0], [0, -1.0, 0, 0], [0, 0, 0, 1.0]])
"""Scanner frame (rotation axis z) → RTK frame (rotation axis y); a proper rotation."""

INSTALL_HINT = "cone-beam simulation needs RTK: pip install 'oarmreg[cbct]' (PyPI package itk-rtk)"


def _rtk() -> Any:
    """Import ``itk.RTK`` lazily, with an install hint when it is missing."""
    try:
        import itk
        from itk import RTK
    except ImportError as e:  # pragma: no cover - depends on the environment
        raise ConfigError(f"{INSTALL_HINT} ({e})") from None
    return itk, RTK


@dataclass(frozen=True)
class ConeBeamSettings:
    """Cone-beam acquisition and reconstruction grid (grid fields as in ``AcquisitionSettings``)."""

    sid_mm: float = 650.0
    sdd_mm: float = 1150.0
    n_views: int = 391
    arc_deg: float = 360.0
    det_cols: int = 512
    det_rows: int = 384
    det_pitch_mm: float = 0.776
    subrays: int = 3
    rows: int = 512
    columns: int = 512
    n_slices: int = 192
    pixel_mm: float = 0.415
    slice_spacing_mm: float = 0.833
    photons_per_ray: float = 1.0e4
    electronic_noise_photons: float = 4.0
    min_count_photons: float = 1.0
    scatter_spr: float = 0.2
    scatter_kernel_fwhm_mm: float = 60.0
    light_spread_fwhm_mm: float = 0.6
    lag_fraction: float = 0.03
    kvp: float = physics.DEFAULT_KVP
    filter_al_mm: float = physics.DEFAULT_FILTER_AL_MM
    energy_bin_edges_kev: tuple[float, ...] = physics.K_EDGE_BIN_EDGES_KEV
    noise: bool = True
    seed: int = 0
    orientation: str = "axial"
    roi_centre_mm: tuple[float, float, float] = (0.0, 0.0, 0.0)
    preset_name: str = "custom-cbct"

    def __post_init__(self) -> None:
        problems = []
        if not 0 < self.sid_mm < self.sdd_mm:
            problems.append(f"need 0 < sid_mm < sdd_mm, got {self.sid_mm}, {self.sdd_mm}")
        if self.n_views < 8 or self.subrays < 1 or min(self.det_cols, self.det_rows) < 8:
            problems.append("need n_views >= 8, subrays >= 1 and a detector of >= 8 × 8 pixels")
        if not 0.0 <= self.lag_fraction < 1.0 or not 0.0 <= self.scatter_spr <= 2.0:
            problems.append("lag_fraction must be in [0, 1) and scatter_spr in [0, 2]")
        if self.orientation not in ORIENTATIONS:
            problems.append(f"orientation {self.orientation!r} not one of {sorted(ORIENTATIONS)}")
        if problems:
            raise ConfigError("invalid cone-beam settings: " + "; ".join(problems))

    @classmethod
    def preset(cls, name: str, **overrides: Any) -> ConeBeamSettings:
        """``oarm-cbct``: 512 × 512 × 192 at 0.415 × 0.833 mm, 391 views, 512 × 384 panel.
        ``cbct-ci``: 128 × 128 × 48 at 0.8 mm, 120 views, 256 × 192 panel at 1.552 mm."""
        presets: dict[str, dict[str, Any]] = {
            "oarm-cbct": {},
            "cbct-ci": {
                "n_views": 120,
                "det_cols": 256,
                "det_rows": 192,
                "det_pitch_mm": 1.552,
                "subrays": 2,
                "rows": 128,
                "columns": 128,
                "n_slices": 48,
                "pixel_mm": 0.8,
                "slice_spacing_mm": 1.6,
            },
        }
        if name not in presets:
            raise ConfigError(f"unknown cone-beam preset {name!r}; choose one of {sorted(presets)}")
        return cls(**{**presets[name], "preset_name": name, **overrides})

    @property
    def magnification(self) -> float:
        return self.sdd_mm / self.sid_mm

    @property
    def fov_radius_mm(self) -> float:
        return min(self.rows, self.columns) / 2.0 * self.pixel_mm

    def image_from_voxel(self) -> F64:
        m = np.diag([self.pixel_mm, self.pixel_mm, self.slice_spacing_mm, 1.0])
        centre = np.array([(self.columns - 1) / 2.0, (self.rows - 1) / 2.0, (self.n_slices - 1) / 2.0])
        m[:3, 3] = np.asarray(self.roi_centre_mm) - centre * m.diagonal()[:3]
        return image_from_scanner(self.orientation) @ m

    def to_dict(self) -> dict[str, Any]:
        return dataclasses.asdict(self)


CBCT_PRESET_NAMES = ("oarm-cbct", "cbct-ci")


def rotation_rtk(theta_rad: float) -> F64:
    """RTK's fixed → rotated frame for gantry angle θ: R_y(−θ) (3 × 3)."""
    c, s = math.cos(theta_rad), math.sin(theta_rad)
    return np.array([[c, 0.0, -s], [0.0, 1.0, 0.0], [s, 0.0, c]])


def projection_matrix(s: ConeBeamSettings, theta_rad: float) -> F64:
    """3 × 4 matrix mapping RTK-frame points to homogeneous detector (u, v) in mm (RTK's convention)."""
    r = np.eye(4)
    r[:3, :3] = rotation_rtk(theta_rad)
    k = np.array([[-s.sdd_mm, 0, 0, 0], [0, -s.sdd_mm, 0, 0], [0, 0, 1.0, -s.sid_mm]])
    return k @ r


@dataclass
class _Ball:
    centre_rtk_mm: F64
    radius_mm: float
    paths: tuple[tuple[int, float], ...]


def _sphere_chords(o: F64, d: F64, b: _Ball) -> F64:
    """Chord (mm) of rays o + t·d (d unit, shapes (3,), (..., 3)) through a ball."""
    oc = b.centre_rtk_mm - o
    t = d @ oc
    dist2 = float(oc @ oc) - t * t
    return np.asarray(2.0 * np.sqrt(np.clip(b.radius_mm**2 - dist2, 0.0, None)))


def _box_chords(o: F64, d: F64, centre: F64, axes: F64, half: F64) -> F64:
    """Chord (mm) of rays o + t·d (d unit) through a box (axes as columns), by the slab method."""
    ol = (o - centre) @ axes  # (3,)
    dl = d @ axes  # (..., 3)
    with np.errstate(divide="ignore", invalid="ignore"):
        inv = 1.0 / np.where(np.abs(dl) < 1e-12, 1e-12, dl)
        t1, t2 = (-half - ol) * inv, (half - ol) * inv
    tmin = np.max(np.minimum(t1, t2), axis=-1)
    tmax = np.min(np.maximum(t1, t2), axis=-1)
    return np.asarray(np.clip(tmax - tmin, 0.0, None))


@dataclass
class _Scene:
    box_centre: F64
    box_axes: F64
    box_half: F64
    box_paths: tuple[tuple[int, float], ...]
    balls: list[_Ball]


def _build(phantom: Phantom, rtk_from_phantom: F64, extras: SceneExtras) -> _Scene:
    slot = {m: i for i, m in enumerate(physics.SCENE_MATERIALS)}
    pl, sp = slot["plastic"], slot["sphere"]
    metal = extras.material_for(phantom) != "plastic"
    actual = extras.actual_centres_phantom_mm(phantom)
    balls: list[_Ball] = []
    n_filled = 0
    for i, c in enumerate(phantom.holes_phantom_mm):
        if phantom.filled[i]:
            if metal:
                centre = frames.apply(rtk_from_phantom, actual[n_filled])
                balls.append(_Ball(centre, phantom.sphere_radius_mm, ((sp, 1.0), (pl, -1.0))))
            n_filled += 1
        elif extras.empty_holes:
            balls.append(_Ball(frames.apply(rtk_from_phantom, c), phantom.sphere_radius_mm, ((pl, -1.0),)))
    return _Scene(
        rtk_from_phantom[:3, 3].copy(),
        rtk_from_phantom[:3, :3].copy(),
        phantom.size_mm / 2.0,
        ((pl, 1.0),),
        balls,
    )


def _rays(s: ConeBeamSettings, theta: float, u_mm: F64, v_mm: F64) -> tuple[F64, F64]:
    """Source (3,) and unit directions (..., 3) in the RTK frame for detector points (u, v) mm."""
    r_t = rotation_rtk(theta).T  # rotated → fixed
    src = r_t @ np.array([0.0, 0.0, s.sid_mm])
    det = np.stack([u_mm, v_mm, np.full_like(u_mm, s.sid_mm - s.sdd_mm)], axis=-1) @ r_t.T
    d = det - src
    return src, d / np.linalg.norm(d, axis=-1, keepdims=True)


def project_view(
    s: ConeBeamSettings, scene: _Scene, theta: float, mu: F32, weights: F64, n_slots: int
) -> F32:
    """Noise-free transmitted intensity (det_rows, det_cols) of one view (sub-ray averaged near balls)."""
    from mocks.oarm.simulator import polychromatic_transmission

    p = s.det_pitch_mm
    u = (np.arange(s.det_cols) - (s.det_cols - 1) / 2.0) * p
    v = (np.arange(s.det_rows) - (s.det_rows - 1) / 2.0) * p
    uu, vv = np.meshgrid(u, v)
    src, d = _rays(s, theta, uu, vv)
    paths = np.zeros((n_slots, s.det_rows, s.det_cols), np.float32)
    for slot, sign in scene.box_paths:
        paths[slot] += sign * _box_chords(src, d, scene.box_centre, scene.box_axes, scene.box_half)
    trans = polychromatic_transmission(paths, mu, weights)
    pm = projection_matrix(s, theta)
    ns = s.subrays
    offs = ((np.arange(ns) + 0.5) / ns - 0.5) * p
    for b in scene.balls:
        h = pm @ np.append(b.centre_rtk_mm, 1.0)
        uc, vc = h[0] / h[2], h[1] / h[2]
        rad = b.radius_mm * s.sdd_mm / max(abs(h[2]) - b.radius_mm, 1.0) + 1.5 * p
        c0, c1 = (
            max(0, math.floor((x - rad) / p + (n - 1) / 2)) for x, n in ((uc, s.det_cols), (vc, s.det_rows))
        )
        e0 = min(s.det_cols, math.ceil((uc + rad) / p + (s.det_cols - 1) / 2) + 1)
        e1 = min(s.det_rows, math.ceil((vc + rad) / p + (s.det_rows - 1) / 2) + 1)
        if e0 <= c0 or e1 <= c1:
            continue
        # Sub-rays across each pixel of the window, through every object near it.
        su = (u[c0:e0, None] + offs[None, :]).ravel()
        sv = (v[c1:e1, None] + offs[None, :]).ravel()
        suu, svv = np.meshgrid(su, sv)
        _, sd = _rays(s, theta, suu, svv)
        sp = np.zeros((n_slots, *suu.shape), np.float32)
        for slot, sign in scene.box_paths:
            sp[slot] += sign * _box_chords(src, sd, scene.box_centre, scene.box_axes, scene.box_half)
        for other in scene.balls:
            if (
                np.linalg.norm(other.centre_rtk_mm - b.centre_rtk_mm)
                < 2 * rad / s.magnification + 2 * other.radius_mm
            ):
                chord = _sphere_chords(src, sd, other)
                for slot, sign in other.paths:
                    sp[slot] += np.float32(sign) * chord.astype(np.float32)
        st = polychromatic_transmission(sp, mu, weights)
        trans[c1:e1, c0:e0] = st.reshape(e1 - c1, ns, e0 - c0, ns).mean(axis=(1, 3))
    return trans


def _detect_views(trans: F32, s: ConeBeamSettings, wcorr: physics.WaterCorrection) -> F32:
    """In place over views (V, rows, cols): scatter, Poisson, light spread, lag, electronics, log."""
    import cv2

    rng = np.random.default_rng(s.seed)
    n0 = np.float32(s.photons_per_ray)
    det_iso_mm = s.det_pitch_mm / s.magnification
    sigma_px = s.light_spread_fwhm_mm / 2.3548 / s.det_pitch_mm
    previous: F32 | None = None
    for i in range(trans.shape[0]):
        prim = trans[i]
        scatter = (
            kernel_scatter(prim[:, None, :], s.scatter_spr, s.scatter_kernel_fwhm_mm, det_iso_mm, det_iso_mm)[
                :, 0
            ]
            if s.scatter_spr > 0
            else 0.0
        )
        lam = n0 * (prim + scatter)
        counts = rng.poisson(lam).astype(np.float32) if s.noise else lam.astype(np.float32)
        if sigma_px > 0:
            counts = cv2.GaussianBlur(counts, (0, 0), sigma_px, borderType=cv2.BORDER_REPLICATE)
        if s.lag_fraction > 0 and previous is not None:
            counts = (1.0 - s.lag_fraction) * counts + s.lag_fraction * previous
        previous = counts
        if s.noise and s.electronic_noise_photons > 0:
            counts = counts + np.float32(s.electronic_noise_photons) * rng.standard_normal(
                counts.shape, np.float32
            )
        np.maximum(counts, np.float32(s.min_count_photons), out=counts)
        trans[i] = wcorr.apply((-np.log(counts / n0)).astype(np.float32))
    return trans


def fdk_rtk(
    line_integrals: F32,
    s: ConeBeamSettings,
    voxel_origin_rtk_mm: F64,
    shape_xyz: tuple[int, int, int],
    spacing_xyz_mm: tuple[float, float, float],
) -> F32:
    """RTK FDK of (V, rows, cols) line integrals onto an RTK-frame grid; returns array [z, y, x] (1/mm)."""
    itk, rtk = _rtk()
    img_t = itk.Image[itk.F, 3]
    g = rtk.ThreeDCircularProjectionGeometry.New()
    for i in range(s.n_views):
        g.AddProjection(s.sid_mm, s.sdd_mm, i * s.arc_deg / s.n_views)
    proj = itk.image_from_array(np.ascontiguousarray(line_integrals, dtype=np.float32))
    p = s.det_pitch_mm
    proj.SetOrigin([-(s.det_cols - 1) / 2.0 * p, -(s.det_rows - 1) / 2.0 * p, 0.0])
    proj.SetSpacing([p, p, 1.0])
    src = rtk.ConstantImageSource[img_t].New()
    src.SetOrigin([float(v) for v in voxel_origin_rtk_mm])
    src.SetSpacing([float(v) for v in spacing_xyz_mm])
    src.SetSize([int(v) for v in shape_xyz])
    src.SetConstant(0.0)
    fdk = rtk.FDKConeBeamReconstructionFilter[img_t].New()
    fdk.SetInput(0, src.GetOutput())
    fdk.SetInput(1, proj)
    fdk.SetGeometry(g)
    fdk.GetRampFilter().SetHannCutFrequency(0.0)
    fdk.Update()
    return np.asarray(itk.array_from_image(fdk.GetOutput()), dtype=np.float32)


def fully_imaged(
    centres_rtk_mm: F64, radius_mm: float, s: ConeBeamSettings, grid_half_rtk_mm: F64, grid_centre_rtk_mm: F64
) -> NDArray[np.bool_]:
    """Spheres inside the grid whose every ray in every view hits the panel (no truncation)."""
    inside = np.all(np.abs(centres_rtk_mm - grid_centre_rtk_mm) + radius_mm <= grid_half_rtk_mm, axis=1)
    half_u = (s.det_cols / 2.0) * s.det_pitch_mm
    half_v = (s.det_rows / 2.0) * s.det_pitch_mm
    for i in range(s.n_views):
        h = (
            np.c_[centres_rtk_mm, np.ones(len(centres_rtk_mm))]
            @ projection_matrix(s, math.radians(i * s.arc_deg / s.n_views)).T
        )
        rad = radius_mm * s.sdd_mm / (np.abs(h[:, 2]) - radius_mm)
        inside &= (np.abs(h[:, 0] / h[:, 2]) + rad <= half_u) & (np.abs(h[:, 1] / h[:, 2]) + rad <= half_v)
    return np.asarray(inside, dtype=bool)


def simulate_cbct(
    phantom: Phantom,
    image_from_phantom: NDArray[Any],
    settings: ConeBeamSettings,
    extras: SceneExtras | None = None,
) -> SimulatedScan:
    """Cone-beam scan of ``phantom`` at ``image_from_phantom``, reconstructed by RTK's FDK.

    Returns a :class:`~mocks.oarm.simulator.SimulatedScan` (``settings`` is the
    :class:`ConeBeamSettings`); its truth lists the spheres fully inside the grid and imaged by
    untruncated rays in every view.
    """
    t_start = time.perf_counter()
    s = settings
    extras = SceneExtras() if extras is None else extras
    image_from_phantom = frames.as_transform(image_from_phantom, "image_from_phantom")
    scanner_from_image = frames.invert(image_from_scanner(s.orientation))
    rtk_from_phantom = RTK_FROM_SCANNER @ scanner_from_image @ image_from_phantom
    material = extras.material_for(phantom)
    spectrum = physics.kramers_spectrum(s.kvp, s.filter_al_mm, s.energy_bin_edges_kev)
    mu = physics.attenuation_matrix_per_mm(
        spectrum, extras.plastic, "steel" if material == "plastic" else material
    )
    wcorr = physics.water_correction(spectrum)
    scene = _build(phantom, rtk_from_phantom, extras)
    timings: dict[str, float] = {}
    t0 = time.perf_counter()
    views = np.empty((s.n_views, s.det_rows, s.det_cols), np.float32)
    for i in range(s.n_views):
        theta = math.radians(i * s.arc_deg / s.n_views)
        views[i] = project_view(s, scene, theta, mu, spectrum.weights, len(physics.SCENE_MATERIALS))
    timings["project_s"] = time.perf_counter() - t0
    views = _detect_views(views, s, wcorr)
    t0 = time.perf_counter()
    roi = np.asarray(s.roi_centre_mm, dtype=np.float64)
    origin = np.array(
        [
            roi[0] - (s.columns - 1) / 2.0 * s.pixel_mm,
            roi[2] - (s.n_slices - 1) / 2.0 * s.slice_spacing_mm,
            -roi[1] - (s.rows - 1) / 2.0 * s.pixel_mm,
        ]
    )
    arr = fdk_rtk(
        views, s, origin, (s.columns, s.n_slices, s.rows), (s.pixel_mm, s.slice_spacing_mm, s.pixel_mm)
    )
    del views
    timings["fdk_s"] = time.perf_counter() - t0
    mu_vol = np.ascontiguousarray(arr.transpose(1, 0, 2)[:, ::-1, :])  # [z_r, y_r, x_r] → [k, j, i]
    hu = (mu_vol / np.float32(wcorr.mu_ref_per_mm) - 1.0) * 1000.0
    np.clip(hu, HU_MIN, HU_MAX, out=hu)
    centres_img = frames.apply(image_from_phantom, extras.actual_centres_phantom_mm(phantom))
    nominal_img = frames.apply(image_from_phantom, phantom.centres_phantom_mm)
    centres_rtk = frames.apply(RTK_FROM_SCANNER @ scanner_from_image, centres_img)
    half = np.array(
        [
            (s.columns - 1) / 2.0 * s.pixel_mm,
            (s.n_slices - 1) / 2.0 * s.slice_spacing_mm,
            (s.rows - 1) / 2.0 * s.pixel_mm,
        ]
    )
    grid_centre = np.array([roi[0], roi[2], -roi[1]])
    full = fully_imaged(centres_rtk, phantom.sphere_radius_mm, s, half, grid_centre)
    touches = np.all(np.abs(centres_rtk - grid_centre) - phantom.sphere_radius_mm < half, axis=1)
    idx = np.flatnonzero(full).astype(np.int64)
    timings["total_s"] = time.perf_counter() - t_start
    return SimulatedScan(
        hu=np.rint(hu).astype(np.int16),
        image_from_voxel=s.image_from_voxel(),
        image_from_phantom=image_from_phantom,
        spheres_image_mm=centres_img[idx],
        sphere_indices=idx,
        settings=s,  # type: ignore[arg-type]
        extras=extras,
        phantom_name=phantom.name,
        timings_s=timings,
        partial_indices=np.flatnonzero(touches & ~full).astype(np.int64),
        nominal_spheres_image_mm=nominal_img[idx],
        sphere_diameter_mm=phantom.sphere_diameter_mm,
        sphere_material=material,
        n_phantom_spheres=phantom.n_spheres,
    )
