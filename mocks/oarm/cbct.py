"""Cone-beam O-arm simulation: 3-D rays, flat panel, FDK with RTK's conventions.

Needs only numpy, scipy and OpenCV: the FDK (:func:`fdk_numpy`) re-implements RTK's
``FDKConeBeamReconstructionFilter`` (weights, ramp kernel, voxel-driven bilinear back-projection)
and is checked against it voxel for voxel in ``tests/unit/mocks/test_cbct.py`` (relative max difference
< 1e-4; 2e-6 measured).  RTK itself (``pip install 'oarmreg[cbct]'``, imported lazily by
:func:`_rtk`) serves ``reconstructor="rtk"`` and the tests; the service never imports this module.

Geometry (RTK's, :class:`itk.RTK.ThreeDCircularProjectionGeometry`): a circular orbit about RTK's
y axis; at gantry angle θ the fixed frame is rotated by R = R_y(−θ), the source sits at
(0, 0, SID) and the flat panel at z = SID − SDD in the rotated frame.  The scanner frame of
:mod:`mocks.oarm.simulator` (rotation axis z) maps to RTK by x_r = x, y_r = z, z_r = −y.  Pixel
and voxel coordinates are ITK's: an origin is the centre of the first pixel.

Forward model per view, same analytic objects and polychromatic spectrum as the slice-wise
simulator: the chords of the plastic cube, the optional steel rod (finite cylinder) and bone block
(cortical box, cancellous core) at every pixel centre inside their projected bounds; around each
sphere and empty hole (its projected disc plus 1.5 pixels) ``subrays`` × ``subrays`` rays per
pixel through every object whose shadow overlaps in that view, their transmitted intensities
averaged before the log.  Then kernel scatter (SPR), Poisson noise, scintillator light spread,
detector lag, electronic noise, the scanner's own lag correction, the log, water linearisation and
FDK (Feldkamp, Davis, Kress, JOSA A 1:612 (1984), doi:10.1364/JOSAA.1.000612), no apodisation
window, inside the cylinder every view sees (the rest is air, −1024 HU).

Detector lag (:func:`apply_lag`) is a linear, time-invariant multi-exponential impulse response,
the model a-Si flat panels are measured with: a fraction w_n of each frame's charge is trapped
and released over the following frames with per-frame retention r_n (first-frame lag Σ w_n;
2–10 % in a-Si panels, Siewerdsen & Jaffray, Med Phys 26:1624 (1999), doi:10.1118/1.598657;
four exponentials fit the Varian 4030CB, Starman et al., Med Phys 38:2398 (2011),
doi:10.1118/1.3574873).  :data:`DETECTOR_LAG` is representative of those ranges, not fitted to
a particular panel.  A CBCT scanner corrects lag before reconstruction, otherwise it shows as a
rotation of the image and "radar" arcs; the simulated scanner does so with the recursive
deconvolution of Hsieh et al. (Proc. SPIE 3977:298 (2000), doi:10.1117/12.384505;
:func:`correct_lag`) of its *calibrated* model, :data:`SCANNER_LAG_MODEL`: three exponentials
fitted to a step response, so the slowest two true terms are merged and the amplitudes are a few
per cent off — a residual lag remains, as Starman et al. report for every LTI correction.
Uncorrected, this lag rotates the image by its mean delay (0.34 frames); after the correction
the first-frame lag is 0.15 % instead of 3.6 % and the 50th-frame lag 0.025 % instead of 0.15 %.
Not modelled: the exposure dependence of lag (non-LTI, Starman et al. 2011's NLCSC), ghosting.

Slice thickness: the FDK point-samples the 0.833 mm slices (``slice_thickness_mm`` = 0), as
RTK does, with the panel's 0.44 mm axial PSF at the isocentre, which aliases: on noise-free,
lag-free steel scans the detection's centres are pulled towards the nearest slice centre (axial
RMS 0.034 mm; 0.060 mm with a 2 × 2-binned 0.388 mm panel; 0.019 mm on 0.4165 mm slices).
Averaging the rows over the slice thickness first (:func:`slab_filter_rows`, ``slice_thickness_mm``
= 0.833, the slice-wise simulator's convention) flips that bias (centres pushed towards the slice
boundaries, axial RMS 0.039 mm) rather than removing it: the bias is the centre estimator's on a
clipped sphere sampled every 0.833 mm.  What the O-arm's reconstructor does here is not known.

O-arm numbers (research note calibration.md §4, **unverified**): SID ≈ 650 mm, SDD ≈ 1150 mm,
40 × 30 cm panel (PaxScan 4030CB-like; here 4 × 4 binned to 0.776 mm), 391 views over 360°.
Not modelled: the water body (its axial extent needs the long-object problem's handling), gantry
flex, short scans (the numpy FDK has no Parker weights: 360° orbits only).
"""

from __future__ import annotations

import dataclasses
import math
import time
from dataclasses import dataclass, field
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
from registration.arrays import F64
from registration.errors import ConfigError
from registration.model import frames
from registration.model.phantom import Phantom

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


LagModel = tuple[tuple[float, float], ...]
"""Multi-exponential lag: (trapped fraction w_n, per-frame retention r_n) per term."""

DETECTOR_LAG: LagModel = ((0.020, 0.30), (0.010, 0.80), (0.004, 0.95), (0.002, 0.99))
"""The simulated panel's true lag: first-frame lag 3.6 %, 50th-frame lag 0.16 % (step response
falling edge; a-Si panels: 2–10 % and tenths of a per cent, Siewerdsen & Jaffray 1999, Starman et
al. 2011).  Representative, not a measured panel."""

SCANNER_LAG_MODEL: LagModel = ((0.0195, 0.33), (0.0095, 0.78), (0.0055, 0.97))
"""The simulated scanner's calibrated lag model (three exponentials, as if fitted to a measured
step response): fast amplitudes 5 % off, one rate 0.02 off, the two slow true terms merged into
one.  Its residual against :data:`DETECTOR_LAG` is what a real LTI correction leaves."""


def _valid_lag(model: LagModel) -> bool:
    return all(w >= 0.0 and 0.0 <= r < 1.0 for w, r in model) and sum(w for w, _ in model) < 1.0


def apply_lag(frames_in: F32, model: LagModel) -> F32:
    """Detector lag on a time series of frames (V, ...), in place; returns the array.

    Per term n, a store Q_n (charge per pixel): at each frame it releases (1 − r_n) Q_n and traps
    w_n of the new charge x_k, so the frame reads y_k = (1 − Σ w_n) x_k + Σ (1 − r_n) Q_n.  The
    store starts empty (the panel was dark before the scan); Σ of the impulse response is 1.
    """
    if not model:
        return frames_in
    stores = [np.zeros(frames_in.shape[1:], np.float32) for _ in model]
    prompt = np.float32(1.0 - sum(w for w, _ in model))
    for k in range(frames_in.shape[0]):
        x = frames_in[k].copy()
        frames_in[k] *= prompt
        for (w, r), q in zip(model, stores, strict=True):
            frames_in[k] += np.float32(1.0 - r) * q
            q *= np.float32(r)
            q += np.float32(w) * x
    return frames_in


def correct_lag(frames_in: F32, model: LagModel) -> F32:
    """The exact inverse of :func:`apply_lag` for ``model`` (Hsieh et al. 2000), in place.

    x̂_k = (y_k − Σ (1 − r_n) Q̂_n) / (1 − Σ w_n), then Q̂_n ← r_n Q̂_n + w_n x̂_k; with the true
    model this returns the lag-free frames to rounding, with a calibrated one a residual remains.
    """
    if not model:
        return frames_in
    stores = [np.zeros(frames_in.shape[1:], np.float32) for _ in model]
    inv_prompt = np.float32(1.0 / (1.0 - sum(w for w, _ in model)))
    for k in range(frames_in.shape[0]):
        y = frames_in[k]
        for (_, r), q in zip(model, stores, strict=True):
            y -= np.float32(1.0 - r) * q
        y *= inv_prompt
        for (w, r), q in zip(model, stores, strict=True):
            q *= np.float32(r)
            q += np.float32(w) * y
    return frames_in


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
    light_spread_fwhm_mm: float = 0.9
    """Blur of the detected quanta on the panel (mm FWHM at the detector, a Gaussian on the pixel
    grid): the scintillator's light spread and, lumped with it, the focal spot's penumbra (not
    traced).  0.9 mm puts the simulated O-arm's PSF at the published, geometrically calibrated
    O-arm's 0.65 mm FWHM (Uneri et al., Med Phys 45:4857 (2018); the uncalibrated O-arm: 0.80 mm,
    which the slice-wise ``*-realistic`` presets use): a 0.2 mm ball's in-plane FWHM, noise-free,
    at and 32–38 mm off the isocentre, 0.648 mm mean (``tests/unit/mocks/test_cbct.py``); the earlier
    0.6 mm gave 0.609 mm, sharper than any O-arm measurement found."""
    lag_components: LagModel = DETECTOR_LAG
    """The panel's true lag (:func:`apply_lag`); ``()`` for none."""
    lag_correction_model: LagModel = SCANNER_LAG_MODEL
    """The scanner's calibrated lag model, deconvolved before the log (:func:`correct_lag`);
    ``()`` for no correction (set it to ``()`` too when switching the lag off)."""
    kvp: float = physics.DEFAULT_KVP
    filter_al_mm: float = physics.DEFAULT_FILTER_AL_MM
    energy_bin_edges_kev: tuple[float, ...] = physics.K_EDGE_BIN_EDGES_KEV
    noise: bool = True
    seed: int = 0
    orientation: str = "axial"
    roi_centre_mm: tuple[float, float, float] = (0.0, 0.0, 0.0)
    preset_name: str = "custom-cbct"
    monochromatic_kev: float | None = None
    """Validation only: one photon energy (keV) instead of the spectrum, so no beam hardening."""
    slice_thickness_mm: float = 0.0
    """Reconstructed slice thickness (mm) by averaging the projections over the voxel's axial
    footprint (:func:`slab_filter_rows`); 0 (default) = point sampling, as RTK's voxel-driven FDK
    does.  See the module notes: the detection's axial bias changes sign with it."""
    hann_cut: float = 0.0
    """Ramp apodisation, RTK's ``HannCutFrequency``: 0 = plain ramp (default); c > 0 multiplies
    rfft bin i < round(c·n) by 0.5(1 + cos(π i / round(c·n))) and zeroes the rest (n bins)."""
    reconstructor: str = "numpy"
    """``numpy``: :func:`fdk_numpy` (RTK's FDK re-implemented, validated against it, no RTK needed);
    ``rtk``: RTK's own ``FDKConeBeamReconstructionFilter`` (needs itk-rtk, slow on CPU)."""

    def __post_init__(self) -> None:
        problems = []
        if not 0 < self.sid_mm < self.sdd_mm:
            problems.append(f"need 0 < sid_mm < sdd_mm, got {self.sid_mm}, {self.sdd_mm}")
        if self.n_views < 8 or self.subrays < 1 or min(self.det_cols, self.det_rows) < 8:
            problems.append("need n_views >= 8, subrays >= 1 and a detector of >= 8 × 8 pixels")
        if not 0.0 <= self.scatter_spr <= 2.0:
            problems.append(f"scatter_spr={self.scatter_spr} outside [0, 2]")
        if not (_valid_lag(self.lag_components) and _valid_lag(self.lag_correction_model)):
            problems.append("lag models need w_n >= 0, 0 <= r_n < 1 and sum(w_n) < 1")
        if self.orientation not in ORIENTATIONS:
            problems.append(f"orientation {self.orientation!r} not one of {sorted(ORIENTATIONS)}")
        if not 0.0 <= self.slice_thickness_mm <= 10.0:
            problems.append(f"slice_thickness_mm={self.slice_thickness_mm} outside [0, 10] mm")
        if not 0.0 <= self.hann_cut <= 1.0:
            problems.append(f"hann_cut={self.hann_cut} outside [0, 1]")
        if self.reconstructor not in ("numpy", "rtk"):
            problems.append(f"reconstructor must be 'numpy' or 'rtk', got {self.reconstructor!r}")
        if self.reconstructor == "numpy" and abs(self.arc_deg - 360.0) > 1e-9:
            problems.append("the numpy FDK needs a full 360° orbit (no Parker short-scan weights)")
        if self.monochromatic_kev is not None and not 30.0 <= self.monochromatic_kev <= 150.0:
            problems.append(f"monochromatic_kev={self.monochromatic_kev} outside the 30–150 keV tables")
        if problems:
            raise ConfigError("invalid cone-beam settings: " + "; ".join(problems))

    @classmethod
    def preset(cls, name: str, **overrides: Any) -> ConeBeamSettings:
        """``oarm-cbct``: 512 × 512 × 192 at 0.415 × 0.833 mm, 391 views, 512 × 384 panel.
        ``oarm-cbct-roi``: the same voxels, views and panel pitch on a 256 × 256 × 96 region
        (106 × 106 × 80 mm, the phantom and its surroundings) with a 384 × 256 panel and 2 × 2
        sub-rays: the hard-scan sweep's and CI's cone-beam scans.
        ``cbct-ci``: 128 × 128 × 48 at 0.8 mm, 120 views, 256 × 192 panel at 1.552 mm."""
        presets: dict[str, dict[str, Any]] = {
            "oarm-cbct": {},
            "oarm-cbct-roi": {
                "rows": 256,
                "columns": 256,
                "n_slices": 96,
                "det_cols": 384,
                "det_rows": 256,
                "subrays": 2,
            },
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


CBCT_PRESET_NAMES = ("oarm-cbct", "oarm-cbct-roi", "cbct-ci")


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


@dataclass
class _Box3:
    centre_rtk_mm: F64
    axes: F64  # box axes as columns (RTK frame)
    half_mm: F64
    paths: tuple[tuple[int, float], ...]


@dataclass
class _Cylinder3:
    start_rtk_mm: F64
    axis: F64  # unit
    length_mm: float
    radius_mm: float
    paths: tuple[tuple[int, float], ...]


def _sphere_chords(o: F64, d: F64, b: _Ball) -> F64:
    """Chord (mm) of rays o + t·d (d unit, shapes (3,), (..., 3)) through a ball."""
    oc = b.centre_rtk_mm - o
    t = d @ oc
    dist2 = float(oc @ oc) - t * t
    return np.asarray(2.0 * np.sqrt(np.clip(b.radius_mm**2 - dist2, 0.0, None)))


def _box_chords(o: F64, d: F64, box: _Box3) -> F64:
    """Chord (mm) of rays o + t·d (d unit) through a box, by the slab method."""
    ol = (o - box.centre_rtk_mm) @ box.axes  # (3,)
    dl = d @ box.axes  # (..., 3)
    tmin: F64 | None = None
    tmax: F64 | None = None
    for k in range(3):  # one slab per box axis (element-wise, not reductions over a length-3 axis)
        dk = dl[..., k]
        with np.errstate(divide="ignore", invalid="ignore"):
            inv = 1.0 / np.where(np.abs(dk) < 1e-12, 1e-12, dk)
        t1, t2 = (-box.half_mm[k] - ol[k]) * inv, (box.half_mm[k] - ol[k]) * inv
        near, far = np.minimum(t1, t2), np.maximum(t1, t2)
        tmin = near if tmin is None else np.maximum(tmin, near)
        tmax = far if tmax is None else np.minimum(tmax, far)
    assert tmin is not None and tmax is not None
    return np.asarray(np.clip(tmax - tmin, 0.0, None))


def _cylinder_chords(o: F64, d: F64, cyl: _Cylinder3) -> F64:
    """Chord (mm) of rays o + t·d (d unit) through a finite solid cylinder (side and end caps)."""
    w = o - cyl.start_rtk_mm
    wa = float(w @ cyl.axis)
    da = d @ cyl.axis
    w_perp = w - wa * cyl.axis
    d_perp = d - da[..., None] * cyl.axis
    a = np.maximum(np.einsum("...i,...i->...", d_perp, d_perp), 1e-18)
    b = d_perp @ w_perp
    c = float(w_perp @ w_perp) - cyl.radius_mm**2
    root = np.sqrt(np.clip(b * b - a * c, 0.0, None))
    t_in, t_out = (-b - root) / a, (-b + root) / a
    with np.errstate(divide="ignore", invalid="ignore"):
        inv = 1.0 / np.where(np.abs(da) < 1e-12, 1e-12, da)
        s1, s2 = -wa * inv, (cyl.length_mm - wa) * inv
    lo = np.maximum(t_in, np.minimum(s1, s2))
    hi = np.minimum(t_out, np.maximum(s1, s2))
    return np.asarray(np.where(b * b - a * c > 0, np.clip(hi - lo, 0.0, None), 0.0))


@dataclass
class _Scene:
    boxes: list[_Box3]
    cylinders: list[_Cylinder3]
    balls: list[_Ball]
    holes: list[_Cylinder3] = field(default_factory=list)
    """Small cylinders (drilled holes): traced only near their own projection."""

    def hole_centres_rtk_mm(self) -> tuple[F64, F64]:
        """(H, 3) centres and (H,) bounding radii of the drilled holes."""
        if not self.holes:
            return np.zeros((0, 3)), np.zeros(0)
        c = np.array([h.start_rtk_mm + h.axis * (h.length_mm / 2.0) for h in self.holes])
        return c, np.array([math.hypot(h.length_mm / 2.0, h.radius_mm) for h in self.holes])

    def corner_points_rtk_mm(self) -> F64:
        """Points whose projections bound the projections of the boxes and cylinders."""
        pts = []
        signs = np.array([[i, j, k] for i in (-1, 1) for j in (-1, 1) for k in (-1, 1)], dtype=np.float64)
        for bx in self.boxes:
            pts.append(bx.centre_rtk_mm + (signs * bx.half_mm) @ bx.axes.T)
        for cy in self.cylinders:
            end = cy.start_rtk_mm + cy.axis * cy.length_mm
            for e in (cy.start_rtk_mm, end):
                pts.append(e + signs * cy.radius_mm)  # the caps' bounding cubes
        return np.concatenate(pts) if pts else np.zeros((0, 3))


def _build(phantom: Phantom, rtk_from_phantom: F64, extras: SceneExtras, rtk_from_image: F64) -> _Scene:
    """The cube, its spheres and empty holes, and the optional rod and vertebra, in the RTK frame.

    As in :func:`mocks.oarm.simulator._build_scene`: the rod (steel) leaves the cube's +z face along
    the phantom's z axis; the vertebra is a cortical box with a cancellous core, offset in the image
    frame.  The water body is not modelled here (its 600 mm axial extent would need the long-object
    problem's extra rows).
    """
    if extras.body:
        raise ConfigError("the cone-beam simulator does not model the water body (SceneExtras.body)")
    slot = {m: i for i, m in enumerate(physics.SCENE_MATERIALS)}
    pl, sp, st = slot["plastic"], slot["sphere"], slot["steel"]
    r = rtk_from_phantom[:3, :3]
    balls, holes = _balls_and_holes(phantom, rtk_from_phantom, extras, pl, sp)
    boxes = [_Box3(rtk_from_phantom[:3, 3].copy(), r.copy(), phantom.size_mm / 2.0, ((pl, 1.0),))]
    if not extras.cube:  # the control: spheres in air, no plastic and no holes
        boxes, holes = [], []
        balls = [
            _Ball(frames.apply(rtk_from_phantom, c), phantom.sphere_radius_mm, ((sp, 1.0),))
            for c in extras.actual_centres_phantom_mm(phantom)
        ]
    cylinders = []
    if extras.rod:
        start = frames.apply(rtk_from_phantom, np.array([0.0, 0.0, phantom.size_mm[2] / 2.0]))
        cylinders.append(
            _Cylinder3(
                start, r[:, 2].copy(), extras.rod_length_mm, extras.rod_diameter_mm / 2.0, ((st, 1.0),)
            )
        )
    if extras.vertebra:
        image_from_phantom = frames.invert(rtk_from_image) @ rtk_from_phantom
        centre = frames.apply(
            rtk_from_image, image_from_phantom[:3, 3] + np.asarray(extras.vertebra_offset_image_mm)
        )
        rot = rtk_from_image[:3, :3].copy()
        half = np.asarray(extras.vertebra_size_mm, dtype=np.float64) / 2.0
        cb, cc = slot["bone_cortical"], slot["bone_cancellous"]
        boxes.append(_Box3(centre, rot, half, ((cb, 1.0),)))
        inner = half - extras.cortical_shell_mm
        if np.all(inner > 0):
            boxes.append(_Box3(centre, rot, inner, ((cc, 1.0), (cb, -1.0))))
    return _Scene(boxes, cylinders, balls, holes)


def _balls_and_holes(
    phantom: Phantom, rtk_from_phantom: F64, extras: SceneExtras, pl: int, sp: int
) -> tuple[list[_Ball], list[_Cylinder3]]:
    """The spheres and, for the drilled model, the air cylinders they sit in (RTK frame), as
    :func:`mocks.oarm.simulator._hole_objects` builds them."""
    drilled = extras.hole_model == "drilled"
    metal = extras.material_for(phantom) != "plastic"
    rot = rtk_from_phantom[:3, :3]
    balls: list[_Ball] = []
    holes: list[_Cylinder3] = []
    for h in extras.holes(phantom):
        if h.cylinder is not None:
            start, axis, length = h.cylinder
            at = frames.apply(rtk_from_phantom, start)
            holes.append(_Cylinder3(at, rot @ axis, length, h.cylinder_radius_mm, ((pl, -1.0),)))
        centre = frames.apply(rtk_from_phantom, h.centre_mm)
        if h.filled and metal:
            paths = ((sp, 1.0),) if drilled else ((sp, 1.0), (pl, -1.0))
            balls.append(_Ball(centre, phantom.sphere_radius_mm, paths))
        elif not h.filled and not drilled:
            balls.append(_Ball(centre, phantom.sphere_radius_mm, ((pl, -1.0),)))
    return balls, holes


def _rays(s: ConeBeamSettings, theta: float, u_mm: F64, v_mm: F64) -> tuple[F64, F64]:
    """Source (3,) and unit directions (..., 3) in the RTK frame for detector points (u, v) mm."""
    r_t = rotation_rtk(theta).T  # rotated → fixed
    src = r_t @ np.array([0.0, 0.0, s.sid_mm])
    det = np.stack([u_mm, v_mm, np.full_like(u_mm, s.sid_mm - s.sdd_mm)], axis=-1) @ r_t.T
    d = det - src
    length = np.sqrt(d[..., 0] ** 2 + d[..., 1] ** 2 + d[..., 2] ** 2)
    return src, d / length[..., None]


def _add_extended(paths: F32, scene: _Scene, src: F64, d: F64) -> None:
    """Add the boxes' and cylinders' signed chords to ``paths`` (n_slots, ...)."""
    for bx in scene.boxes:
        chord = _box_chords(src, d, bx).astype(np.float32)
        for slot, sign in bx.paths:
            paths[slot] += np.float32(sign) * chord
    for cy in scene.cylinders:
        chord = _cylinder_chords(src, d, cy).astype(np.float32)
        for slot, sign in cy.paths:
            paths[slot] += np.float32(sign) * chord


def _projected_discs(s: ConeBeamSettings, theta: float, centres: F64, radii: F64) -> tuple[F64, F64]:
    """Panel (u, v) mm of ball centres and a generous shadow radius (tangent cone + 1.5 pixels)."""
    if len(centres) == 0:
        return np.zeros((0, 2)), np.zeros(0)
    h = np.c_[centres, np.ones(len(centres))] @ projection_matrix(s, theta).T
    uv = h[:, :2] / h[:, 2:3]
    return uv, radii * s.sdd_mm / np.maximum(np.abs(h[:, 2]) - radii, 1.0) + 1.5 * s.det_pitch_mm


def _add_holes_in_window(
    paths: F32, scene: _Scene, s: ConeBeamSettings, theta: float, src: F64, d: F64, origin: tuple[int, int]
) -> None:
    """Add the drilled holes' chords to the extended pass's ``paths`` (rays ``d`` of the pixels from
    column, row ``origin``), each only over the pixels under its own shadow."""
    centres, radii = scene.hole_centres_rtk_mm()
    rows, cols = d.shape[0], d.shape[1]
    for hole, c, r in zip(scene.holes, centres, radii, strict=True):
        _, rad = _projected_discs(s, theta, c[None], np.array([r]))
        c0, e0, c1, e1 = _pixel_window(s, theta, c[None], float(rad[0]))
        c0, e0 = max(c0 - origin[0], 0), min(e0 - origin[0], cols)
        c1, e1 = max(c1 - origin[1], 0), min(e1 - origin[1], rows)
        if e0 <= c0 or e1 <= c1:
            continue
        chord = _cylinder_chords(src, d[c1:e1, c0:e0], hole).astype(np.float32)
        for slot, sign in hole.paths:
            paths[slot][c1:e1, c0:e0] += np.float32(sign) * chord


def _panel_windows(s: ConeBeamSettings, lo_uv_mm: F64, hi_uv_mm: F64) -> NDArray[np.int64]:
    """Detector columns [c0, e0) and rows [c1, e1) of panel rectangles (u, v mm, shapes (..., 2)),
    clipped to the panel: an int array (..., 4) of c0, e0, c1, e1 (empty where e <= c)."""
    p = s.det_pitch_mm
    mid = np.array([(s.det_cols - 1) / 2, (s.det_rows - 1) / 2])
    first = np.maximum(0, np.floor(lo_uv_mm / p + mid))
    end = np.minimum([s.det_cols, s.det_rows], np.ceil(hi_uv_mm / p + mid) + 1)
    return np.stack([first[..., 0], end[..., 0], first[..., 1], end[..., 1]], axis=-1).astype(np.int64)


def _pixel_window(s: ConeBeamSettings, theta: float, pts: F64, margin_mm: float) -> tuple[int, int, int, int]:
    """Detector columns [c0, e0) and rows [c1, e1) covering the projections of ``pts`` ± margin."""
    h = np.c_[pts, np.ones(len(pts))] @ projection_matrix(s, theta).T
    uv = h[:, :2] / h[:, 2:3]
    c0, e0, c1, e1 = (
        int(x) for x in _panel_windows(s, uv.min(axis=0) - margin_mm, uv.max(axis=0) + margin_mm)
    )
    return c0, e0, c1, e1


def _ball_windows(s: ConeBeamSettings, uv: F64, rad: F64) -> list[tuple[int, int, int, int, int]]:
    """Each ball's (index, c0, e0, c1, e1): the window of its projected centre ``uv`` ± ``rad``
    (mm), for all balls at once; balls whose window misses the panel are left out."""
    win = _panel_windows(s, uv - rad[:, None], uv + rad[:, None])
    out = []
    for i, (c0, e0, c1, e1) in enumerate(win.tolist()):
        if e0 > c0 and e1 > c1:
            out.append((i, c0, e0, c1, e1))
    return out


def project_view(
    s: ConeBeamSettings, scene: _Scene, theta: float, mu: F32, weights: F64, n_slots: int
) -> F32:
    """Noise-free transmitted intensity (det_rows, det_cols) of one view (sub-ray averaged near balls).

    Only the pixels inside the projected bounding box of the extended objects are traced (the rest
    see air and transmit 1); around each ball (its projected disc plus 1.5 pixels) ``subrays`` ×
    ``subrays`` rays per pixel go through every object.
    """
    from mocks.oarm.simulator import polychromatic_transmission

    p = s.det_pitch_mm
    u = (np.arange(s.det_cols) - (s.det_cols - 1) / 2.0) * p
    v = (np.arange(s.det_rows) - (s.det_rows - 1) / 2.0) * p
    trans = np.ones((s.det_rows, s.det_cols), np.float32)
    corners = scene.corner_points_rtk_mm()
    if len(corners):
        c0, e0, c1, e1 = _pixel_window(s, theta, corners, p)
        if e0 > c0 and e1 > c1:
            uu, vv = np.meshgrid(u[c0:e0], v[c1:e1])
            src, d = _rays(s, theta, uu, vv)
            paths = np.zeros((n_slots, *uu.shape), np.float32)
            _add_extended(paths, scene, src, d)
            _add_holes_in_window(paths, scene, s, theta, src, d, (c0, c1))
            trans[c1:e1, c0:e0] = polychromatic_transmission(paths, mu, weights)
    if not scene.balls:
        return trans
    hole_uv, hole_rad = _projected_discs(s, theta, *scene.hole_centres_rtk_mm())
    ns = s.subrays
    offs = ((np.arange(ns) + 0.5) / ns - 0.5) * p
    centres = np.array([bl.centre_rtk_mm for bl in scene.balls])
    radii = np.array([bl.radius_mm for bl in scene.balls])
    uv, rad = _projected_discs(s, theta, centres, radii)
    # Balls whose shadows overlap a window in this view (near in projection, however far apart).
    overlap = np.all(
        np.abs(uv[:, None, :] - uv[None, :, :]) < (rad[:, None] + rad[None, :])[..., None], axis=2
    )
    windows = _ball_windows(s, uv, rad)
    if not windows:
        return trans
    # Sub-rays across each pixel of every ball's window, traced together (one flat batch, each
    # window a contiguous segment in row-major order), through every object they may meet.
    coords = [
        np.meshgrid((u[c0:e0, None] + offs).ravel(), (v[c1:e1, None] + offs).ravel())
        for _, c0, e0, c1, e1 in windows
    ]
    bounds = np.cumsum([0] + [su.size for su, _ in coords])
    src, sd = _rays(
        s,
        theta,
        np.concatenate([su.ravel() for su, _ in coords]),
        np.concatenate([sv.ravel() for _, sv in coords]),
    )
    sp = np.zeros((n_slots, len(sd)), np.float32)
    _add_extended(sp, scene, src, sd)
    for (ib, *_), a, b in zip(windows, bounds[:-1], bounds[1:], strict=True):
        seg = sd[a:b]
        for io in np.flatnonzero(overlap[ib]):
            other = scene.balls[io]
            chord = _sphere_chords(src, seg, other).astype(np.float32)
            for slot, sign in other.paths:
                sp[slot, a:b] += np.float32(sign) * chord
        near = np.all(np.abs(hole_uv - uv[ib]) < (hole_rad + rad[ib])[:, None], axis=1)
        for ih in np.flatnonzero(near):
            hole = scene.holes[ih]
            chord = _cylinder_chords(src, seg, hole).astype(np.float32)
            for slot, sign in hole.paths:
                sp[slot, a:b] += np.float32(sign) * chord
    st = polychromatic_transmission(sp, mu, weights)
    for (_, c0, e0, c1, e1), a, b in zip(windows, bounds[:-1], bounds[1:], strict=True):
        trans[c1:e1, c0:e0] = st[a:b].reshape(e1 - c1, ns, e0 - c0, ns).mean(axis=(1, 3))
    return trans


def _detect_views(trans: F32, s: ConeBeamSettings, wcorr: physics.WaterCorrection) -> F32:
    """In place over views (V, rows, cols): scatter, Poisson, light spread, lag, electronics, the
    scanner's lag correction, the log and water linearisation."""
    import cv2

    rng = np.random.default_rng(s.seed)
    n0 = np.float32(s.photons_per_ray)
    det_iso_mm = s.det_pitch_mm / s.magnification
    sigma_px = s.light_spread_fwhm_mm / 2.3548 / s.det_pitch_mm
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
        trans[i] = counts
    apply_lag(trans, s.lag_components)
    if s.noise and s.electronic_noise_photons > 0:
        for i in range(trans.shape[0]):
            trans[i] += np.float32(s.electronic_noise_photons) * rng.standard_normal(
                trans.shape[1:], np.float32
            )
    correct_lag(trans, s.lag_correction_model)
    for i in range(trans.shape[0]):
        counts = np.maximum(trans[i], np.float32(s.min_count_photons))
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
    fdk.GetRampFilter().SetHannCutFrequency(float(s.hann_cut))
    fdk.Update()
    return np.asarray(itk.array_from_image(fdk.GetOutput()), dtype=np.float32)


# --- FDK (Feldkamp, Davis, Kress 1984) with RTK's conventions, in numpy + OpenCV -----------------

BP_SLICE_CHUNK = 16
"""Slices back-projected per OpenCV remap call (bounded by remap's 32767-row map limit)."""


def ramp_kernel_fft(
    n_cols: int, pitch_mm: float, hann_cut: float = 0.0
) -> tuple[NDArray[np.complex128], int]:
    """FFT of RTK's spatial ramp kernel (Kak & Slaney eq. 3.61; ``FFTRampImageFilter``).

    Optionally Hann-windowed as RTK's ``HannCutFrequency`` (:attr:`ConeBeamSettings.hann_cut`).
    h(0) = 1/(4Δ), h(n odd) = −1/(n²π²Δ), h(n even ≠ 0) = 0 (Δ = detector pitch, the spacing not
    squared as RTK does: the convolution is a plain sum), on a zero-padded length of the next power
    of two ≥ 2·n_cols so the circular convolution equals the linear one over the panel.
    """
    n_pad = 1 << (2 * n_cols - 1).bit_length()
    h = np.zeros(n_pad)
    h[0] = 1.0 / (4.0 * pitch_mm)
    odd = np.arange(1, n_pad // 2, 2)
    h[odd] = -1.0 / (odd * math.pi) ** 2 / pitch_mm
    h[n_pad - odd] = h[odd]
    resp = np.fft.rfft(h)
    if hann_cut > 0.0:
        n_cut = round(len(resp) * min(1.0, hann_cut))
        win = np.zeros(len(resp))
        win[:n_cut] = 0.5 * (1.0 + np.cos(np.pi * np.arange(n_cut) / n_cut))
        resp *= win
    return resp, n_pad


def filter_projections(line_integrals: F32, s: ConeBeamSettings) -> F32:
    """FDK pre-weighting and ramp filtering of (V, rows, cols) line integrals, in place.

    RTK's ``FDKWeightProjectionFilter``: p · cos γ · Δθ · SDD / (2 SID) with cos γ = SDD /
    √(SDD² + u² + v²) and Δθ the angular gap (2π/V on a full, uniform orbit; Rit & Clackdoyle,
    CT meeting 2014, for the SDD / SID factor); then the ramp of :func:`ramp_kernel_fft` along u.
    """
    from scipy import fft as sfft

    p = s.det_pitch_mm
    u = (np.arange(s.det_cols) - (s.det_cols - 1) / 2.0) * p
    v = (np.arange(s.det_rows) - (s.det_rows - 1) / 2.0) * p
    cos_g = s.sdd_mm / np.sqrt(s.sdd_mm**2 + u[None, :] ** 2 + v[:, None] ** 2)
    gap = 2.0 * math.pi / s.n_views
    weight = (cos_g * gap * s.sdd_mm / (2.0 * s.sid_mm)).astype(np.float32)
    kernel, n_pad = ramp_kernel_fft(s.det_cols, p, s.hann_cut)
    for i in range(line_integrals.shape[0]):
        spec = sfft.rfft(line_integrals[i] * weight, n=n_pad, axis=-1, workers=-1)
        spec *= kernel[None, :]
        line_integrals[i] = sfft.irfft(spec, n=n_pad, axis=-1, workers=-1)[:, : s.det_cols]
    return line_integrals


def slab_filter_rows(line_integrals: F32, s: ConeBeamSettings) -> F32:
    """Average each view's rows over the reconstructed slice thickness projected at the isocentre.

    A box of ``slice_thickness_mm`` × SDD / SID on the panel (fractional pixel overlaps), along v:
    the reconstructor's slice-thickness filter, so the 0.833 mm slices of the O-arm grid integrate
    the axial profile instead of point-sampling it (magnification varies by ±8 % over ±50 mm of
    depth, so the effective thickness does too).  Returns ``line_integrals`` filtered in place.
    """
    from scipy import ndimage

    width_px = s.slice_thickness_mm * s.magnification / s.det_pitch_mm
    if width_px <= 1.0:
        return line_integrals
    half = width_px / 2.0
    n = math.ceil(half - 0.5)
    taps = np.arange(-n, n + 1, dtype=np.float64)
    kernel = np.clip(np.minimum(taps + 0.5, half) - np.maximum(taps - 0.5, -half), 0.0, None)
    kernel /= kernel.sum()
    ndimage.convolve1d(
        line_integrals, kernel.astype(np.float32), axis=1, output=line_integrals, mode="nearest"
    )
    return line_integrals


def fov_radius_rtk_mm(s: ConeBeamSettings) -> float:
    """Radius (mm) of the cylinder about the orbit axis that every view's panel sees in u."""
    half_u = (s.det_cols - 1) / 2.0 * s.det_pitch_mm
    return s.sid_mm * math.sin(math.atan2(half_u, s.sdd_mm))


def backproject(
    filtered: F32,
    s: ConeBeamSettings,
    xz_rtk_mm: F64,
    y_rtk_mm: F64,
) -> F32:
    """Voxel-driven FDK back-projection (RTK's ``FDKBackProjectionImageFilter``): (n_y, n_xz).

    Each voxel (x, y, z) takes, from each filtered view, the bilinear value at its projection under
    :func:`projection_matrix`, weighted by (SID / (SID − z_rot))² (RTK normalises the matrix so the
    weight is 1 at the isocentre).  On a circular orbit about y the column u and the weight depend
    on (x, z) only and the row is v = y · SDD / (SID − z_rot), so u and the weight are computed once
    per view and column; OpenCV's ``remap`` (exact float bilinear) does the gathers in chunks of
    :data:`BP_SLICE_CHUNK` slices.  Samples outside the panel contribute 0.
    """
    import cv2

    p = s.det_pitch_mm
    u0 = -(s.det_cols - 1) / 2.0 * p
    v0 = -(s.det_rows - 1) / 2.0 * p
    n, n_y = xz_rtk_mm.shape[0], len(y_rtk_mm)
    width = 512
    m_rows = -(-n // width)
    x = np.pad(xz_rtk_mm[:, 0], (0, m_rows * width - n))
    z = np.pad(xz_rtk_mm[:, 1], (0, m_rows * width - n))
    out = np.zeros((n_y * m_rows, width), np.float32)  # slice-major: rows [k·m_rows, (k+1)·m_rows)
    y32 = np.asarray(y_rtk_mm, np.float32)
    chunk = min(BP_SLICE_CHUNK, n_y)
    map_v = np.empty((chunk, m_rows * width), np.float32)
    for i in range(s.n_views):
        theta = math.radians(i * s.arc_deg / s.n_views)
        c, sn = math.cos(theta), math.sin(theta)
        depth = s.sid_mm - (sn * x + c * z)
        mag = s.sdd_mm / depth
        map_u = (((c * x - sn * z) * mag - u0) / p).astype(np.float32).reshape(m_rows, width)
        map_u = np.tile(map_u, (chunk, 1))
        weight = np.tile(((s.sid_mm / depth) ** 2).astype(np.float32).reshape(m_rows, width), (chunk, 1))
        vscale = (mag / p).astype(np.float32)
        view = np.ascontiguousarray(filtered[i])
        for k0 in range(0, n_y, chunk):
            nk = min(chunk, n_y - k0)
            rows = nk * m_rows
            np.multiply.outer(y32[k0 : k0 + nk], vscale, out=map_v[:nk])
            map_v[:nk] -= np.float32(v0 / p)
            samples = cv2.remap(
                view,
                map_u[:rows],
                map_v[:nk].reshape(rows, width),
                cv2.INTER_LINEAR,
                borderMode=cv2.BORDER_CONSTANT,
                borderValue=0.0,
            )
            cv2.accumulateProduct(samples, weight[:rows], out[k0 * m_rows : k0 * m_rows + rows])
    return out.reshape(n_y, m_rows * width)[:, :n]


def _fov_mask(
    s: ConeBeamSettings,
    voxel_origin_rtk_mm: F64,
    shape_xyz: tuple[int, int, int] | None = None,
    spacing_xyz_mm: tuple[float, float, float] | None = None,
) -> tuple[F64, F64, F64, NDArray[np.bool_]]:
    """Grid x, z ([z, x]) and y coordinates (RTK frame, mm) and the [z, x] mask outside the FOV."""
    nx, ny, nz = shape_xyz or (s.columns, s.n_slices, s.rows)
    sx, sy, sz = spacing_xyz_mm or (s.pixel_mm, s.slice_spacing_mm, s.pixel_mm)
    xs = voxel_origin_rtk_mm[0] + np.arange(nx) * sx
    ys = voxel_origin_rtk_mm[1] + np.arange(ny) * sy
    zs = voxel_origin_rtk_mm[2] + np.arange(nz) * sz
    zz, xx = np.meshgrid(zs, xs, indexing="ij")
    return xx, zz, ys, np.hypot(xx, zz) > fov_radius_rtk_mm(s)


def fdk_numpy(
    line_integrals: F32,
    s: ConeBeamSettings,
    voxel_origin_rtk_mm: F64,
    shape_xyz: tuple[int, int, int],
    spacing_xyz_mm: tuple[float, float, float],
) -> F32:
    """FDK as :func:`fdk_rtk` (same grid arguments, array [z, y, x] in 1/mm) without RTK.

    ``line_integrals`` is filtered in place (:func:`filter_projections`), then
    :func:`backproject_grid`.
    """
    if abs(s.arc_deg - 360.0) > 1e-9:
        raise ConfigError("fdk_numpy handles full 360° orbits only (no Parker short-scan weights)")
    return backproject_grid(
        filter_projections(line_integrals, s), s, voxel_origin_rtk_mm, shape_xyz, spacing_xyz_mm
    )


def backproject_grid(
    filtered: F32,
    s: ConeBeamSettings,
    voxel_origin_rtk_mm: F64,
    shape_xyz: tuple[int, int, int],
    spacing_xyz_mm: tuple[float, float, float],
) -> F32:
    """Back-project filtered views onto an RTK-frame grid ([z, y, x], 1/mm).

    Only voxels inside the cylinder every view sees (:func:`fov_radius_rtk_mm`) are reconstructed;
    the others are returned as 0 (air).  One set of filtered views serves any number of grids.
    """
    xx, zz, ys, outside = _fov_mask(s, voxel_origin_rtk_mm, shape_xyz, spacing_xyz_mm)
    keep = ~outside
    vol = np.zeros((zz.shape[0], len(ys), zz.shape[1]), np.float32)
    if np.any(keep):
        vals = backproject(filtered, s, np.stack([xx[keep], zz[keep]], axis=1), ys)
        vol.transpose(0, 2, 1)[keep] = vals.T
    return vol


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


def _spectrum(s: ConeBeamSettings) -> physics.Spectrum:
    """The polychromatic spectrum, or one line at ``monochromatic_kev`` (validation: no hardening)."""
    if s.monochromatic_kev is not None:
        return physics.Spectrum(np.array([float(s.monochromatic_kev)]), np.array([1.0]))
    return physics.kramers_spectrum(s.kvp, s.filter_al_mm, s.energy_bin_edges_kev)


def _grid_rtk(s: ConeBeamSettings) -> tuple[F64, F64, F64]:
    """RTK-frame voxel origin, half extent (centre to outer voxel centres) and centre of the grid."""
    roi = np.asarray(s.roi_centre_mm, dtype=np.float64)
    centre = np.array([roi[0], roi[2], -roi[1]])
    half = np.array(
        [
            (s.columns - 1) / 2.0 * s.pixel_mm,
            (s.n_slices - 1) / 2.0 * s.slice_spacing_mm,
            (s.rows - 1) / 2.0 * s.pixel_mm,
        ]
    )
    return centre - half, half, centre


def project_scan(
    phantom: Phantom,
    rtk_from_phantom: F64,
    s: ConeBeamSettings,
    extras: SceneExtras,
    rtk_from_image: F64,
) -> tuple[F32, physics.WaterCorrection, dict[str, float]]:
    """All views, detected and water-linearised: line integrals (V, rows, cols), the correction
    (its ``mu_ref_per_mm`` converts μ to HU) and the timings."""
    material = extras.material_for(phantom)
    spectrum = _spectrum(s)
    mu = physics.attenuation_matrix_per_mm(
        spectrum, extras.plastic, "steel" if material == "plastic" else material
    )
    wcorr = physics.water_correction(spectrum)
    scene = _build(phantom, rtk_from_phantom, extras, rtk_from_image)
    timings: dict[str, float] = {}
    t0 = time.perf_counter()
    views = np.empty((s.n_views, s.det_rows, s.det_cols), np.float32)
    for i in range(s.n_views):
        theta = math.radians(i * s.arc_deg / s.n_views)
        views[i] = project_view(s, scene, theta, mu, spectrum.weights, len(physics.SCENE_MATERIALS))
    timings["project_s"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    views = _detect_views(views, s, wcorr)
    timings["detect_s"] = time.perf_counter() - t0
    return views, wcorr, timings


def simulate_cbct_mu(
    phantom: Phantom,
    image_from_phantom: NDArray[Any],
    settings: ConeBeamSettings,
    extras: SceneExtras | None = None,
) -> tuple[F32, SimulatedScan]:
    """Cone-beam scan, FDK-reconstructed: the unclipped float HU volume [k, j, i] and the scan.

    The scan's ``hu`` is the same volume rounded and clipped to [−1024, 3071] as a scanner stores
    it; the float volume serves validation (no saturation of the metal).  Voxels outside the
    cylinder every view sees are air (−1024 HU), as the slice-wise simulator fills its FOV.
    """
    t_start = time.perf_counter()
    s = settings
    extras = SceneExtras() if extras is None else extras
    image_from_phantom = frames.as_transform(image_from_phantom, "image_from_phantom")
    rtk_from_image = RTK_FROM_SCANNER @ frames.invert(image_from_scanner(s.orientation))
    rtk_from_phantom = rtk_from_image @ image_from_phantom
    material = extras.material_for(phantom)
    views, wcorr, timings = project_scan(phantom, rtk_from_phantom, s, extras, rtk_from_image)
    t0 = time.perf_counter()
    origin, half, grid_centre = _grid_rtk(s)
    grid = ((s.columns, s.n_slices, s.rows), (s.pixel_mm, s.slice_spacing_mm, s.pixel_mm))
    fdk = fdk_rtk if s.reconstructor == "rtk" else fdk_numpy
    arr = fdk(slab_filter_rows(views, s), s, origin, *grid)
    del views
    timings["fdk_s"] = time.perf_counter() - t0
    mu_vol = np.ascontiguousarray(arr.transpose(1, 0, 2)[:, ::-1, :])  # [z_r, y_r, x_r] → [k, j, i]
    hu = (mu_vol / np.float32(wcorr.mu_ref_per_mm) - 1.0) * 1000.0
    hu[:, _fov_mask(s, origin)[3][::-1, :]] = HU_MIN
    centres_img = frames.apply(image_from_phantom, extras.actual_centres_phantom_mm(phantom))
    nominal_img = frames.apply(image_from_phantom, phantom.centres_phantom_mm)
    centres_rtk = frames.apply(rtk_from_image, centres_img)
    full = fully_imaged(centres_rtk, phantom.sphere_radius_mm, s, half, grid_centre)
    touches = np.all(np.abs(centres_rtk - grid_centre) - phantom.sphere_radius_mm < half, axis=1)
    idx = np.flatnonzero(full).astype(np.int64)
    timings["total_s"] = time.perf_counter() - t_start
    scan = SimulatedScan(
        hu=np.rint(np.clip(hu, HU_MIN, HU_MAX)).astype(np.int16),
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
    return hu, scan


def simulate_cbct(
    phantom: Phantom,
    image_from_phantom: NDArray[Any],
    settings: ConeBeamSettings,
    extras: SceneExtras | None = None,
) -> SimulatedScan:
    """Cone-beam scan of ``phantom`` at ``image_from_phantom``, FDK-reconstructed.

    Returns a :class:`~mocks.oarm.simulator.SimulatedScan` (``settings`` is the
    :class:`ConeBeamSettings`); its truth lists the spheres fully inside the grid and imaged by
    untruncated rays in every view.  See :func:`simulate_cbct_mu` for the unclipped volume.
    """
    return simulate_cbct_mu(phantom, image_from_phantom, settings, extras)[1]
