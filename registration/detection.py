"""Metal-sphere detection in a CT volume: candidates, MAR, circles, centres, rejections.

The chain of Bai et al. 2018 (doi:10.1088/1742-6596/1016/1/012006, §2.2):
metal artefact reduction in polar coordinates (:mod:`registration.mar`),
circle recognition by moment invariants (:mod:`registration.circles`) and the
sphere centre by Pythagorean depth, plus a 3-D sub-voxel estimate on the raw
volume that research (image-side.md §0.4, §3) and our own measurements
(benchmarks/bench_detection.py) show to be more accurate.

Pipeline (only small crops are ever copied or converted to float):

1. **candidates**: one vectorised threshold of the whole volume
   (``voxels >= candidate_threshold_hu``), ``np.flatnonzero``, grouping of the
   hits through a coarse cell grid;
2. **components**: each group's crop is thresholded and labelled
   (26-connectivity); every component is measured (extent, volume, peak)
   and rejected with a reason if it is not a sphere-sized bright blob
   (connecting rod, bone edge, streak crossing, blob cut by the volume edge);
3. **per slice**: a patch around the component, MAR (optional), circles;
4. **centre**: ``subvoxel`` = intensity-weighted 3-D centroid of the raw
   voxels above ``background + margin`` inside a ball, iterated, its slice coordinate then from
   a quadratic fit to the weights' per-slice sums (:func:`axial_profile_position`); ``paper`` =
   per-slice Pythagorean depth with a per-sphere fitted radius.

Coordinates: the work is done in voxel indices (i, j, k) = (column, row,
slice) and mapped to the image frame (LPS, mm) by ``volume.image_from_voxel``,
so flipped orientations and reversed slice order need no special case.
"""

from __future__ import annotations

import logging
import math
import time
from collections.abc import Iterator, Mapping
from contextlib import contextmanager
from dataclasses import dataclass, field, replace
from typing import Any, Final, Protocol

import cc3d
import numpy as np
from numpy.typing import NDArray

from registration.circles import CircleParams, find_circles
from registration.core_centroid import CoreParams, CoreWeights, core_centroid
from registration.edge_profile import DataRegion, plateau_reaches_edge
from registration.errors import DetectionError
from registration.mar import MarParams, reduce_metal_artifacts
from registration.ray_fit import RayFit, RayParams, ray_centre
from registration.sphere_fit import FitParams, fit_sphere_model
from registration.volume import Volume

log = logging.getLogger(__name__)

F64 = NDArray[np.float64]
Support = tuple[tuple[slice, slice, slice], NDArray[np.bool_]]
"""A region of the volume: a (k, j, i) box and a boolean mask of the box's shape."""

METHODS: Final = ("subvoxel", "model", "paper", "core", "rays")
"""Centre estimators.  ``subvoxel`` and ``model`` measured more accurate than ``paper``
(benchmarks/bench_detection.py); ``model`` fits a blurred saturated ball (:mod:`registration.sphere_fit`);
``core`` is the centroid of the saturated core of an opaque sphere (:mod:`registration.core_centroid`);
``rays`` the centre of the sphere's outline at 70 % of its contrast, robust to streaks
(:mod:`registration.ray_fit`)."""

METHOD_FOR_MATERIAL: Final[Mapping[str, str]] = {
    "tungsten_carbide": "core",
    "steel": "rays",
    "titanium": "rays",
}
"""Centre estimator per sphere material (``registration.phantom``'s names) where it is not the
default ``subvoxel``: on the simulator's tungsten-carbide scans ``core`` measures better (README
hard-scan table, ``python -m benchmarks.bench_detection --hard 40``; ``--method subvoxel`` for the
comparison), on steel and titanium worse (:mod:`registration.core_centroid`).  On steel and
titanium ``rays`` (:mod:`registration.ray_fit`) measured better than ``subvoxel`` on the mean of
every steel and titanium condition of that sweep (cone-beam steel SPR 0.3 with rod and vertebra:
mean / max 0.049 / 0.171 → 0.034 / 0.075 mm; parallel steel SPR 0.1 0.020 / 0.039 → 0.018 /
0.037; titanium SPR 0.2 0.021 / 0.042 → 0.016 / 0.034) and on 24 held-out scans of the same
conditions (seeds 1000+, ``--seed-offset 1000 --only steel`` / ``--only Ti``; cone-beam steel
SPR 0.3 0.048 / 0.134 → 0.035 / 0.128 mm); on tungsten carbide worse than ``core``."""


def method_for_material(material: str) -> str:
    """The centre estimator for spheres of ``material`` (:data:`METHOD_FOR_MATERIAL`, else ``subvoxel``)."""
    return METHOD_FOR_MATERIAL.get(material, DetectionParams.method)


def params_for_spheres(material: str, sphere_diameter_mm: float, **overrides: Any) -> DetectionParams:
    """Detection settings for spheres of ``material`` and ``sphere_diameter_mm`` (a phantom file's
    or a scan's): the estimator :func:`method_for_material` chooses, as the service does, with
    ``overrides`` (any other :class:`DetectionParams` field)."""
    return DetectionParams(
        **{"method": method_for_material(material), "sphere_diameter_mm": sphere_diameter_mm, **overrides}
    )


BACKGROUND_MODELS: Final = ("linear", "constant")
"""Background under a sphere for the centroid weights (:class:`DetectionParams`)."""

SATURATION_MIN_VOXELS: Final = 3
"""A crop whose maximum is held by at least this many voxels is clipped there (a 12-bit export
stores 3071 HU for every metal voxel; noise makes a tie of 3 unclipped voxels improbable)."""

AIR_HU: Final = -1000.0
"""Padding outside a circular FOV is stored at or below air (−1024 HU for RescaleIntercept −1024)."""

FOV_CORNER_PX: Final = 3
"""Side of the corner blocks tested for constant padding: 9 equal pixels do not happen by chance in
a noisy reconstruction, and a 3-pixel corner is inside the padding of any circular FOV."""

_GROUP_CELL_VOXELS: Final = (4, 8, 8)
"""(k, j, i) size of the coarse cells used to group threshold hits: ~3.3 mm, far below the 15 mm pitch."""


@dataclass(frozen=True)
class DetectionParams:
    """Sphere-detection settings.  Every threshold has its unit in its name.

    Attributes
    ----------
    method : str
        ``"subvoxel"`` (default: intensity-weighted 3-D centroid, measured
        mean error ~0.01 mm) or ``"paper"`` (per-slice Pythagoras, Bai 2018).
    sphere_diameter_mm : float
        Nominal sphere diameter (phantom definition, 2.5 mm in Bai 2018 §2.1).
    use_mar : bool
        Apply the polar MAR before circle recognition.  With ``paper`` it
        runs on every slice patch, as in Bai 2018 (the circles *are* the
        measurement).  With ``subvoxel`` the circles are only the
        cross-check of a centre measured on the raw volume, so MAR runs on a
        patch only when its raw cross-section fails the circle test (a
        streak-distorted outline): the 20-scan sweep showed identical
        centres, misses and false positives for MAR on every patch vs off
        (README, detection table), at ~3× the detection time.
    candidate_threshold_hu : float
        Metal threshold of the candidate pass.  Steel spheres saturate at
        3071 HU (12-bit export); cortical bone and streaks stay below ~1800 HU
        in the simulator and in the literature (image-side.md §3.3).
    min_peak_hu : float
        A sphere's brightest voxel must reach this: a 2.5 mm steel sphere
        blurred by a 0.8 mm FWHM PSF still clips at 3071 HU; bone edges and
        streak crossings that cross the candidate threshold peak lower.
    bloom_mm : float
        Allowance for the apparent growth of the sphere by PSF and clipping:
        the apparent radius reached 1.9 mm for a 1.25 mm sphere
        (image-side.md §3.3), so 1.5 mm on the radius leaves margin.
    min_extent_fraction : float
        Smallest thresholded extent (per axis) as a fraction of the diameter;
        smaller blobs are streak crossings or noise.
    min_volume_fraction : float
        Smallest thresholded volume as a fraction of the nominal sphere volume.
    min_fill_fraction : float
        Smallest fraction of its bounding box a blob fills.  A thresholded ball fills about
        π/6 ≈ 0.52; bloom and streak tails took true spheres down to 0.16 (tungsten carbide,
        SPR 0.3, issue #11 hard sweep); a cone-beam streak fragment between tungsten-carbide
        spheres, reported as a sphere before this test, filled 0.079.  A sparser blob is split
        into sphere cores like an oversized one (a streak fragment has none).
    centroid_margin_hu : float
        ``subvoxel``: voxels are weighted by ``HU − (background + margin)``
        (clipped at 0).  The margin keeps noise and streaks (±200 HU in the
        simulator) out of the weights (image-side.md §3.3).
    centroid_margin_fraction : float
        The margin is at least this fraction of (peak − background): 0.5
        weights only the half-maximum core, which keeps the plastic/air face
        the spheres sit on out of the weights (on the O-arm preset: mean error
        0.077 mm at 0.1, 0.055 at 0.3, 0.051 at 0.5, 0.052 at 0.7).
    centroid_iterations : int
        Re-centre the weighting ball this many times.
    min_circle_slices : int
        Slices with an accepted circle needed to accept a sphere (the
        circles are the cross-check of the 3-D estimate; ``paper`` always
        needs ≥ 2 for its radius fit).
    patch_half_mm : float
        Half-size of the square slice patch used for MAR and circles.
    min_patch_half_px : int
        The patch is at least this many pixels each side of the centre (a coarse grid still gives
        the circle finder a 9 × 9 patch: a 2.5 mm sphere with blooming spans ≥ 3 pixels).
    crop_margin_mm : float
        Margin around a group of threshold hits when its components are labelled: more than a
        voxel of blooming on each side, far below the 15 mm pitch (neighbours stay out).
    split_core_fraction : float
        A blob too large for one sphere (a sphere with streak tails joining it to its neighbours,
        several spheres joined by blooms) is split by a morphological opening of its metal mask
        with an ellipsoid of this fraction of the nominal radius: streaks (1–2 voxels wide) vanish,
        sphere cores (apparent radius ≈ 1.9 mm for 1.25 mm) and the rod (Ø10 mm) stay.  0.75
        keeps a 3-slice core of a 2.5 mm sphere at 0.833 mm slices; on a 40-sphere tungsten
        carbide scan (SPR 0.3, 256² × 120 at 0.415 × 0.833 mm) 0.75 recovered every sphere where
        the unsplit detection lost 21 to "elongated" (streak tails) and failed circle tests.
    background_shell_mm : float
        ``subvoxel``: thickness of the shell outside the weighting ball whose median is the local
        background (1.5 mm holds enough voxels at 0.4–0.8 mm spacing and stays on the phantom).
    background_model : str
        ``subvoxel``: ``"linear"`` fits a plane a + g·x (HU) through the background shell, so a
        sphere on the phantom face (plastic behind, air in front) is weighted over its own signal;
        ``"constant"`` takes the shell's median.  Measured on steel, SPR 0.1–0.2 (2 × 28 spheres):
        error along the face normal −0.023 mm (constant) → 0.001 mm (linear), mean FLE
        0.041 → 0.031 mm; a per-direction median over-corrected (+0.028 mm): the shell reaches past
        the face plane at angles where the ball does not.
    axial_profile_margin_fraction : float
        ``subvoxel``: the margin (fraction of the sphere signal, at least ``centroid_margin_hu``) of
        the weights whose per-slice sums give the slice coordinate (:func:`axial_profile_centre`).
        Below the centroid's 0.5 the profile spans 1–2 more slices and its fit is steadier: on the
        40-scan hard sweep (``benchmarks/bench_detection.py --hard 40``) cone-beam steel SPR 0.1
        mean / max FLE 0.032 / 0.112 mm at 0.5, 0.031 / 0.090 at 0.3, 0.031 / 0.076 at 0.15;
        lower hits the 300 HU floor (same figures at 0.08 and 0).
    axial_profile_min_fraction : float
        ``subvoxel``: profile slices with less than this fraction of the largest per-slice sum are
        left out of its quadratic fit (the tips, rounded by the blur).  0.05 / 0.1 / 0.2 on the same
        sweep: cone-beam steel SPR 0.1 mean 0.031 / 0.031 / 0.032 mm, parallel steel SPR 0.2
        0.028 / 0.027 / 0.025 mm, cone-beam titanium 0.026 / 0.026 / 0.027 mm.
    edge_plateau_fraction : float
        Near the FOV circle or the matrix edge, a sphere whose image, followed along the edge
        normal, is still above this fraction of its contrast where the image data end is refused
        (:func:`registration.edge_profile.plateau_reaches_edge`): its clipped plateau runs into
        the edge, so no window says where its centre is along the normal.  On the issue #11
        held-out seeds a tungsten-carbide sphere cut by 0.85 mm was reported 0.87 mm inside its
        true position before this test.  The level sits near the top of the clipped plateau
        (noise on a 3071 HU plateau is a few HU); where only the falloff below it is cut, the
        symmetric window holds both ends of the plateau (measured in the partial-FOV sweep rows).
        On ``benchmarks/bench_fov_edge.py --seeds 4`` (96 scans, 65 cut spheres, 23 whole ones
        with their surface within 0.2 mm of the circle) 0.5 / 0.9 / 0.95 / 0.98 reported 0 / 0 /
        0 / 0 cut spheres and 0 / 0 / 3 / 8 of those whole ones (steel 0 / 0 / 2 / 4 of 11,
        tungsten carbide 0 / 0 / 1 / 4 of 12; at 0.2–0.4 mm 3 / 8 / 8 / 9 of 10 tungsten-carbide
        spheres).  0.95 keeps a margin below the highest level that leaked none, against a dip in
        a cut sphere's plateau (a dark band across it) that a level nearer 1 would mistake for its
        end.
    min_separation_mm : float
        Two reported centres are at least this far apart; of a closer pair only the one with more
        circle slices (then the higher score) is kept.  Half the 15 mm pitch of the Bai 2018 hole
        grid (its closest spheres are 15 mm apart, 15.9 mm across a cube edge).  On a cone-beam
        tungsten-carbide scan (SPR 0.3) split cores of one sphere gave 4 duplicates and bright
        streak fragments 4.4–6.8 mm from a sphere gave 4 false positives.
    core : CoreParams
        ``core`` method: its ball and margin (:mod:`registration.core_centroid`).
    rays : RayParams
        ``rays`` method: its rays, level and robust fit (:mod:`registration.ray_fit`).
    mar, circles : MarParams, CircleParams
    """

    method: str = "subvoxel"
    sphere_diameter_mm: float = 2.5
    use_mar: bool = True
    candidate_threshold_hu: float = 2000.0
    min_peak_hu: float = 2500.0
    bloom_mm: float = 1.5
    min_extent_fraction: float = 0.5
    min_volume_fraction: float = 0.25
    min_fill_fraction: float = 0.12
    centroid_margin_hu: float = 300.0
    centroid_margin_fraction: float = 0.5
    centroid_iterations: int = 3
    min_circle_slices: int = 1
    patch_half_mm: float = 6.0
    min_patch_half_px: int = 4
    crop_margin_mm: float = 2.0
    background_shell_mm: float = 1.5
    split_core_fraction: float = 0.75
    background_model: str = "linear"
    axial_profile_margin_fraction: float = 0.15
    axial_profile_min_fraction: float = 0.1
    edge_plateau_fraction: float = 0.95
    min_separation_mm: float = 7.5
    mar: MarParams = field(default_factory=MarParams)
    circles: CircleParams = field(default_factory=CircleParams)
    core: CoreParams = field(default_factory=CoreParams)
    rays: RayParams = field(default_factory=RayParams)

    def __post_init__(self) -> None:
        if self.background_model not in BACKGROUND_MODELS:
            raise DetectionError(
                f"unknown background model {self.background_model!r}: expected one of "
                + ", ".join(BACKGROUND_MODELS)
            )
        if not 0.0 <= self.min_separation_mm <= 1000.0:
            raise DetectionError(
                f"min_separation_mm {self.min_separation_mm} is implausible: expected 0 … 1000 mm "
                "(half the phantom's hole pitch, 7.5 mm for Bai 2018; 0 turns the rule off)"
            )
        if not 0.0 < self.edge_plateau_fraction < 1.0:
            raise DetectionError(
                f"edge_plateau_fraction {self.edge_plateau_fraction} must be in (0, 1): the fraction of "
                "a sphere's contrast above which its image running into the FOV edge counts as cut (0.95)"
            )
        if self.method not in METHODS:
            raise DetectionError(
                f"unknown detection method {self.method!r}: expected one of {', '.join(METHODS)}"
            )
        if not 0.5 <= self.sphere_diameter_mm <= 50.0:
            raise DetectionError(
                f"sphere diameter {self.sphere_diameter_mm} mm is implausible: expected 0.5 … 50 mm "
                "(the Bai 2018 phantom uses 2.5 mm)"
            )

    @property
    def radius_mm(self) -> float:
        return self.sphere_diameter_mm / 2.0


@dataclass(frozen=True, eq=False)
class DetectedSphere:
    """One detected sphere.

    Attributes
    ----------
    center_image_mm : ndarray, shape (3,), float64
        Centre in the image frame (DICOM LPS, mm).
    radius_mm : float
        Per-sphere fitted radius from the circle radii (r_i² + z_i² = c + 2·z0·z_i);
        this is the *apparent* (bloomed) radius, typically 1.5–2 mm for a
        1.25 mm steel sphere.  NaN if fewer than two circle slices.
    n_slices : int
        Slices with an accepted circle.
    score : float
        0 … 1: fraction of the blob's slices with an accepted circle × (1 −
        in-plane disagreement between the circles and the centre / radius).
    center_voxel : ndarray, shape (3,), float64
        Centre in continuous voxel indices (i, j, k).
    """

    center_image_mm: F64
    radius_mm: float
    n_slices: int
    score: float
    center_voxel: F64 = field(default_factory=lambda: np.full(3, math.nan))


@dataclass(frozen=True)
class Rejection:
    """A bright blob that is not reported as a sphere, and why."""

    center_image_mm: tuple[float, float, float]
    reason: str


@dataclass(frozen=True, eq=False)
class DetectionResult:
    """Spheres found in one volume, the rejected candidates and the time spent per stage."""

    spheres: tuple[DetectedSphere, ...]
    rejections: tuple[Rejection, ...]
    method: str
    timings_s: dict[str, float]

    @property
    def centres_image_mm(self) -> F64:
        """(M, 3) float64 sphere centres, image frame (LPS, mm), in detection order."""
        if not self.spheres:
            return np.zeros((0, 3))
        return np.stack([s.center_image_mm for s in self.spheres]).astype(np.float64)

    def to_dict(self, series_uid: str = "") -> dict[str, Any]:
        """The ``oarmreg detect --json`` document."""
        return {
            "series_uid": series_uid,
            "frame": "image",
            "method": self.method,
            "spheres": [
                {
                    "center_mm": [float(v) for v in s.center_image_mm],
                    "radius_mm": None if math.isnan(s.radius_mm) else float(s.radius_mm),
                    "n_slices": int(s.n_slices),
                    "score": float(s.score),
                }
                for s in self.spheres
            ],
            "rejected": [{"center_mm": list(r.center_image_mm), "reason": r.reason} for r in self.rejections],
            "timings_s": dict(self.timings_s),
        }


# ----------------------------------------------------------------------------- candidates


def _group_hits(flat: NDArray[np.intp], shape: tuple[int, int, int]) -> list[tuple[slice, slice, slice]]:
    """Bounding boxes (k, j, i slices) of clusters of threshold hits, via a coarse cell grid."""
    k, j, i = np.unravel_index(flat, shape)
    ck, cj, ci = _GROUP_CELL_VOXELS
    grid_shape = (shape[0] // ck + 1, shape[1] // cj + 1, shape[2] // ci + 1)
    cell = (k // ck, j // cj, i // ci)
    occ = np.zeros(grid_shape, dtype=bool)
    occ[cell] = True
    labels, n = cc3d.connected_components(occ, connectivity=26, return_N=True)
    hit_label = labels[cell]
    boxes: list[tuple[slice, slice, slice]] = []
    order = np.argsort(hit_label, kind="stable")
    bounds = np.searchsorted(hit_label[order], np.arange(1, n + 2))
    for g in range(n):
        idx = order[bounds[g] : bounds[g + 1]]
        if len(idx) == 0:
            continue
        boxes.append(
            (
                slice(int(k[idx].min()), int(k[idx].max()) + 1),
                slice(int(j[idx].min()), int(j[idx].max()) + 1),
                slice(int(i[idx].min()), int(i[idx].max()) + 1),
            )
        )
    return boxes


def _expand(
    box: tuple[slice, slice, slice], margin: tuple[int, int, int], shape: tuple[int, int, int]
) -> tuple[slice, slice, slice]:
    return (
        slice(max(box[0].start - margin[0], 0), min(box[0].stop + margin[0], shape[0])),
        slice(max(box[1].start - margin[1], 0), min(box[1].stop + margin[1], shape[1])),
        slice(max(box[2].start - margin[2], 0), min(box[2].stop + margin[2], shape[2])),
    )


@dataclass
class _Blob:
    """A connected above-threshold component (internal)."""

    box: tuple[slice, slice, slice]  # in the full volume, (k, j, i)
    n_voxels: int
    peak_hu: float
    centroid_voxel: F64  # (i, j, k)
    extent_mm: F64  # (3,) along i, j, k
    support: Support | None = None
    """A split core's region (box in the volume, mask in it): outside it, slice patches are
    flattened to the circle window's floor so the streak tails cut off by the split do not
    distort the cross-sections.  None for an unsplit blob."""


FOV_PADDED_FRACTION: Final = 0.99
"""An annulus (one pixel wide) around the matrix centre is outside the FOV when at least this
fraction of its voxels holds the padding value.  Air inside the FOV clipped to the same value is
scattered (noise about −1000 HU crosses −1024 in a fraction of the voxels, not in 99 %)."""


def _circular_fov_radius_mm(vox: NDArray[Any], spacing: F64) -> float | None:
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


# ----------------------------------------------------------------------------- centres


def _support_mask(
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
class _BallWeights:
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


LINEAR_BACKGROUND_MIN_VOXELS: Final = 20
"""Shell voxels needed to fit the 4-parameter linear background (5 per parameter); a smaller
shell (a sphere in a corner of the volume) gets the constant median."""


def _ball_weights(
    vox: NDArray[Any], centre_ijk: F64, spacing: F64, params: DetectionParams, support: Support | None
) -> _BallWeights:
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
        ball = ball & _support_mask(lo, hi, support)
    w = np.where(ball, np.clip(np.minimum(signal, cap) - margin, 0.0, None), 0.0)
    return _BallWeights(w, (ii, jj, kk), bg, peak, bool(saturated))


def _subvoxel_centre(
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
        bw = _ball_weights(vox, centre, spacing, params, support)
        bg, peak = bw.bg_hu, bw.peak_hu
        total = float(bw.w.sum())
        if total <= 0.0:
            break
        centre = np.array([float((bw.w * g).sum()) / total for g in bw.ijk])
    return centre, bg, peak


AXIAL_PROFILE_MIN_SLICES: Final = 3
"""A quadratic in z has 3 coefficients: fewer profile slices cannot place its vertex."""


def axial_profile_position(bw: _BallWeights, min_fraction: float) -> float | None:
    """The slice index (continuous k) of the vertex of a quadratic fitted to the per-slice weight sums.

    A sphere thresholded at a level is the level's iso-surface, a ball of some radius R_t: its
    cross-section in slice z is a disc of area π(R_t² − (z − z0)²), a parabola in z whatever the
    sampling phase (under a wider slice profile an ellipsoid, still a parabola: the factor
    R_t² / c_t² on (z − z0)²), and an in-plane edge ramp of the same shape in every slice adds a constant
    (the ramp's second moment).  So the per-slice sums of the centroid weights m_k = a + b·k + c·k²
    put z0 at −b / 2c exactly where the centroid Σ m_k k / Σ m_k of 3–4 coarse slices is pulled
    towards the nearest slice centre (issue #11: ±0.06 mm on 0.833 mm slices).  Only slices with
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
        _ball_weights(vox, centre_ijk, spacing, cp, support), params.axial_profile_min_fraction
    )
    return centre_ijk if k is None else np.array([centre_ijk[0], centre_ijk[1], k])


EDGE_WINDOW_ITERATIONS: Final = 8
"""Re-centrings of the symmetric window near an edge; each halves the remaining offset or better
(measured on spheres 0–2 mm inside the slab end: converged to < 0.01 mm after 5)."""


def _symmetric_position(
    w: F64, t_mm: F64, c_mm: float, edge_mm: float, step_mm: float, r_ball_mm: float
) -> float:
    """Centroid along a direction of the weights inside a window symmetric about the estimate.

    The window ``|t − c| ≤ h`` has ``h = min(r_ball, edge + step/2 − c)``: it never reaches past
    the last sample (which covers up to ``edge + step/2``), so what the edge cut off on one side is
    trimmed from the other and a symmetric blurred ball is located without bias.  Voxels are
    intervals of ``step_mm`` along the direction, counted by the fraction inside the window.
    ``w`` (V,) weights and ``t_mm`` (V,) positions along the direction (mm, edge at ``edge_mm``,
    data at t < edge).  Returns the centre along the direction (mm); beyond the edge if the ball is.
    """
    c = c_mm
    for _ in range(EDGE_WINDOW_ITERATIONS):
        h = min(r_ball_mm, edge_mm + 0.5 * step_mm - c)
        if h <= 0.0:
            return c
        m = w * np.clip((h - np.abs(t_mm - c)) / step_mm + 0.5, 0.0, 1.0)
        total = float(m.sum())
        if total <= 0.0:
            return c
        c = float((m * t_mm).sum()) / total
    return c


def _boundaries(
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


MAX_CORE_AXIS_RATIO: Final = 4.0
"""Largest axis ratio (√ of the largest / smallest eigenvalue of the weighted covariance) of a
sphere's centroid weights.  Measured over 480 detected spheres (cone-beam and parallel steel,
tungsten carbide with streaks, titanium): ≤ 2.5; a bright cone-beam streak line that passed the
size and peak tests: 8.2."""


def core_axis_ratio(bw: _BallWeights, spacing: F64) -> float:
    """Axis ratio of the weights ``bw`` in mm (inf if they are all zero or degenerate)."""
    total = float(bw.w.sum())
    if total <= 0.0:
        return math.inf
    g = [np.broadcast_to(x * float(spacing[a]), bw.w.shape) for a, x in enumerate(bw.ijk)]
    m = [float((bw.w * gi).sum()) / total for gi in g]
    cov = np.array(
        [[float((bw.w * (g[a] - m[a]) * (g[b] - m[b])).sum()) / total for b in range(3)] for a in range(3)]
    )
    ev = np.linalg.eigvalsh(cov)
    return math.inf if ev[0] <= 0.0 else float(np.sqrt(ev[-1] / ev[0]))


def edge_refined_centre(
    vox: NDArray[Any],
    centre_ijk: F64,
    spacing: F64,
    params: DetectionParams,
    fov_radius_mm: float | None,
    support: Support | None = None,
) -> tuple[F64, str | None]:
    """The centre of a sphere near an edge of the imaged region, and why it is cut (or None).

    Near a slab end, matrix edge or the FOV circle the centroid is pulled inwards: a sphere cut by
    the edge (its centre outside, or less than a radius inside) shows only its inner part, and the
    bloom halo of a whole sphere close to it is cut too.  Along each such boundary the centre is
    re-measured with :func:`_symmetric_position`, and the sphere is cut if that centre is less than
    the nominal radius from the edge (the simulator's and the registration's "fully imaged").
    """
    r_ball = params.radius_mm + params.bloom_mm
    centre = centre_ijk.astype(np.float64).copy()
    shape = (vox.shape[0], vox.shape[1], vox.shape[2])
    region = DataRegion(shape, spacing, fov_radius_mm)
    for name, u, edge_mm, step_mm in _boundaries(centre, shape, spacing, fov_radius_mm):
        t_c = float(u @ (centre * spacing))
        if edge_mm - t_c > r_ball + step_mm:
            continue
        # In-plane edges only: at the slab ends the same test refused 4 more whole spheres on
        # the 12 partial-FOV sweep scans and no false one (the symmetric window below holds there).
        if u[2] == 0.0 and plateau_reaches_edge(
            vox,
            centre,
            spacing,
            u,
            params.radius_mm,
            r_ball,
            params.background_shell_mm,
            region,
            params.edge_plateau_fraction,
        ):
            return centre, (
                f"cut by the {name}: the sphere's image is still above {params.edge_plateau_fraction:.0%} "
                "of its peak where the image ends (the sphere is cut, or whole but too close to the "
                "edge to be located)"
            )
        bw = _ball_weights(vox, centre, spacing, params, support)
        t = sum(float(u[a] * spacing[a]) * bw.ijk[a] for a in range(3))
        w, t_all = np.broadcast_arrays(bw.w, t)
        c = _symmetric_position(w.ravel(), t_all.ravel(), t_c, edge_mm, step_mm, r_ball)
        if edge_mm - c < params.radius_mm:
            return centre, (
                f"cut by the {name}: centre re-measured symmetrically {edge_mm - c:.2f} mm inside "
                f"it < sphere radius {params.radius_mm} mm"
            )
        centre = centre + (c - t_c) * u / spacing
    return centre, None


@dataclass(frozen=True)
class _SliceCircle:
    i: float  # column, full-volume index
    j: float  # row
    k: int  # slice
    r_mm: float


def _fit_radius(circles: list[_SliceCircle], dz_mm: float) -> tuple[float, float]:
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


def _paper_depth(circles: list[_SliceCircle], radius_mm: float, dz_mm: float) -> float:
    """Pythagorean depth (Bai 2018 §2.2): per slice two depths z_i ± √(R² − r_i²); the radius trend picks one.

    Slices before the largest circle (in k) have the centre above them, slices
    after it below; at the largest circle the larger neighbour says which way.
    Returns the centre's k (continuous slice index), the average over slices.
    """
    cs = sorted(circles, key=lambda c: c.k)
    radii = np.array([c.r_mm for c in cs])
    m = int(np.argmax(radii))
    zs = []
    for n, c in enumerate(cs):
        d = math.sqrt(max(radius_mm * radius_mm - c.r_mm * c.r_mm, 0.0)) / dz_mm
        if n < m:
            sign = 1.0
        elif n > m:
            sign = -1.0
        else:
            below = radii[n - 1] if n > 0 else -math.inf
            above = radii[n + 1] if n + 1 < len(cs) else -math.inf
            sign = 1.0 if above > below else -1.0
        zs.append(c.k + sign * d)
    return float(np.mean(zs))


# ----------------------------------------------------------------------------- steps


class StageTimer:
    """Seconds per named stage: ``with timer.stage("mar_s"): ...`` adds that block's time.

    ``stages`` are created at 0.0 up front (so a stage that never ran still reports 0 s) and keep
    their order in :attr:`seconds`.
    """

    def __init__(self, stages: tuple[str, ...] = ()) -> None:
        self.seconds: dict[str, float] = dict.fromkeys(stages, 0.0)

    @contextmanager
    def stage(self, name: str) -> Iterator[None]:
        t0 = time.perf_counter()
        try:
            yield
        finally:
            self.seconds[name] = self.seconds.get(name, 0.0) + time.perf_counter() - t0


TIMED_STAGES: Final = ("threshold_s", "group_s", "components_s", "mar_s", "circles_s", "centres_s")
"""The stages :func:`detect_spheres` reports (plus ``total_s``)."""


def _checked_spacing(volume: Volume) -> F64:
    """The voxel spacing (i, j, k) mm of a 3-D volume; DetectionError otherwise."""
    vox = volume.voxels
    if vox.ndim != 3 or min(vox.shape) < 1:
        raise DetectionError(
            f"series {volume.series_uid or '(no UID)'}: expected a 3-D volume, got shape {vox.shape}"
        )
    spacing = volume.spacing_mm
    if not np.all(np.isfinite(spacing)) or np.any(spacing <= 0):
        raise DetectionError(
            f"series {volume.series_uid or '(no UID)'}: voxel spacing {spacing.tolist()} mm is not positive"
        )
    return spacing


def threshold_hits(vox: NDArray[Any], threshold_hu: float) -> tuple[NDArray[np.intp], float]:
    """Flat indices of voxels ≥ the threshold (one pass, no float copy) and the threshold as compared.

    For an integer volume the threshold is rounded up to the stored type; one above its maximum
    gives no hits.
    """
    integer = np.issubdtype(vox.dtype, np.integer)
    thr_cast = float(np.ceil(threshold_hu)) if integer else float(threshold_hu)
    if integer and thr_cast > np.iinfo(vox.dtype).max:
        return np.zeros(0, dtype=np.intp), thr_cast
    thr = np.asarray(thr_cast).astype(vox.dtype)
    # Slab by slab into one small reused mask: a whole-volume mask (50 MB for 512² × 192) costs
    # more in first-touch page faults than the comparison itself (benchmarks/bench_detect_process.py).
    per_slice = int(np.prod(vox.shape[1:]))
    n_slab = max(1, THRESHOLD_SLAB_VOXELS // max(per_slice, 1))
    mask = np.empty((min(n_slab, vox.shape[0]), *vox.shape[1:]), dtype=bool)
    hits: list[NDArray[np.intp]] = []
    for k0 in range(0, vox.shape[0], n_slab):
        slab = vox[k0 : k0 + n_slab]
        m = mask[: slab.shape[0]]
        np.greater_equal(slab, thr, out=m)
        hits.append(np.flatnonzero(m) + k0 * per_slice)
    return (np.concatenate(hits) if hits else np.zeros(0, dtype=np.intp)), thr_cast


THRESHOLD_SLAB_VOXELS: Final = 1 << 21
"""Voxels per slab of :func:`threshold_hits` (8 slices of 512²: a 2 MB mask, cache-sized)."""


def find_blobs(
    vox: NDArray[Any],
    boxes: list[tuple[slice, slice, slice]],
    threshold_hu: float,
    spacing: F64,
    crop_margin_mm: float,
) -> list[_Blob]:
    """Connected (26-neighbour) above-threshold components inside each group's crop, measured and
    sorted by (k, j, i) of their bounding box."""
    shape = (vox.shape[0], vox.shape[1], vox.shape[2])
    margin = tuple(math.ceil(crop_margin_mm / s) + 1 for s in (spacing[2], spacing[1], spacing[0]))
    blobs: list[_Blob] = []
    for box in boxes:
        crop_box = _expand(box, (margin[0], margin[1], margin[2]), shape)
        crop = vox[crop_box]
        labels, boxes_in_crop = components_26(crop >= threshold_hu)
        for lab, sl in enumerate(boxes_in_crop, start=1):
            blobs.append(_measure_component(crop, labels[sl] == lab, sl, crop_box, spacing))
    blobs.sort(key=lambda b: (b.box[0].start, b.box[1].start, b.box[2].start))
    return blobs


def components_26(mask: NDArray[np.bool_]) -> tuple[NDArray[Any], list[tuple[slice, ...]]]:
    """26-connected components of a 3-D mask: labels 1 … n (0 outside) and each one's (k, j, i) box.

    :func:`cc3d.connected_components` numbers them in raster order, as ``scipy.ndimage.label``
    with a 3 × 3 × 3 structure does (and the boxes equal ``scipy.ndimage.find_objects``), without
    scipy.ndimage's import (0.3–1 s, more than the detection of a 512² × 192 scan; measured by
    benchmarks/bench_detect_process.py).
    """
    labels, n = cc3d.connected_components(mask, connectivity=26, return_N=True)
    return labels, (list(cc3d.statistics(labels)["bounding_boxes"][1 : n + 1]) if n else [])


def _measure_component(
    crop: NDArray[Any],
    sub: NDArray[np.bool_],
    sl: tuple[slice, ...],
    crop_box: tuple[slice, slice, slice],
    spacing: F64,
) -> _Blob:
    kk, jj, ii = np.nonzero(sub)
    off = (
        crop_box[0].start + sl[0].start,
        crop_box[1].start + sl[1].start,
        crop_box[2].start + sl[2].start,
    )
    full_box = (
        slice(off[0], off[0] + sub.shape[0]),
        slice(off[1], off[1] + sub.shape[1]),
        slice(off[2], off[2] + sub.shape[2]),
    )
    return _Blob(
        box=full_box,
        n_voxels=int(sub.sum()),
        peak_hu=float(crop[sl][sub].max()),
        centroid_voxel=np.array([ii.mean() + off[2], jj.mean() + off[1], kk.mean() + off[0]]),
        extent_mm=np.array(sub.shape[::-1], dtype=np.float64) * spacing,
    )


def _ellipsoid(semi_axes_vox: tuple[float, float, float]) -> NDArray[np.bool_]:
    """Boolean (k, j, i) ellipsoid with the given semi-axes in voxels (at least the centre voxel)."""
    half = [math.floor(a) for a in semi_axes_vox]
    kk, jj, ii = np.ogrid[-half[0] : half[0] + 1, -half[1] : half[1] + 1, -half[2] : half[2] + 1]
    a = [max(x, 1e-9) for x in semi_axes_vox]
    return np.asarray((kk / a[0]) ** 2 + (jj / a[1]) ** 2 + (ii / a[2]) ** 2 <= 1.0)


SUPPORT_GROW_VOXELS: Final = 1.0
"""A split core's support is its opened mask dilated by this many voxels: the opening shaved the
bloom edge by up to a voxel, and the circle finder needs the 2000 → 500 HU edge ramp (≈ 1 voxel at
0.4 mm pixels with a 0.8 mm PSF) around it."""


def split_blob(
    vox: NDArray[Any], b: _Blob, threshold_hu: float, spacing: F64, params: DetectionParams
) -> list[_Blob]:
    """The sphere-core components of an oversized blob: its metal mask opened by an ellipsoid.

    The opening (radius ``split_core_fraction`` × the nominal radius, per axis in voxels) removes
    streaks and bloom bridges narrower than that, so a sphere with streak tails, or spheres joined
    by them, fall apart into cores; a rod stays one elongated component.  Returns the cores as
    blobs (measured on the opened mask, peak from the raw voxels), in (k, j, i) order.
    """
    from scipy import ndimage  # here only: an oversized blob is rare, the import costs 0.3–1 s

    shape = (vox.shape[0], vox.shape[1], vox.shape[2])
    rho_mm = params.split_core_fraction * params.radius_mm
    semi = (rho_mm / float(spacing[2]), rho_mm / float(spacing[1]), rho_mm / float(spacing[0]))
    pad = tuple(math.floor(a) + 1 for a in semi)
    crop_box = _expand(b.box, (pad[0], pad[1], pad[2]), shape)
    crop = vox[crop_box]
    opened = ndimage.binary_opening(crop >= threshold_hu, structure=_ellipsoid(semi))
    labels, _ = ndimage.label(opened, structure=np.ones((3, 3, 3), dtype=bool))
    grow = _ellipsoid((SUPPORT_GROW_VOXELS, SUPPORT_GROW_VOXELS, SUPPORT_GROW_VOXELS))
    cores = []
    for lab, sl in enumerate(ndimage.find_objects(labels), start=1):
        if sl is None:
            continue
        core = _measure_component(crop, labels[sl] == lab, sl, crop_box, spacing)
        core.support = (crop_box, ndimage.binary_dilation(labels == lab, structure=grow))
        cores.append(core)
    cores.sort(key=lambda c: (c.box[0].start, c.box[1].start, c.box[2].start))
    return cores


@dataclass(frozen=True)
class SizeLimits:
    """What a sphere-sized blob may measure, from the nominal diameter, blooming and voxel size."""

    voxel_mm3: float
    v_nominal_mm3: float
    v_max_mm3: float
    ext_min_mm: float
    ext_max_mm: float

    @classmethod
    def of(cls, params: DetectionParams, spacing: F64) -> SizeLimits:
        r = params.radius_mm
        return cls(
            voxel_mm3=float(np.prod(spacing)),
            v_nominal_mm3=4.0 / 3.0 * math.pi * r**3,
            v_max_mm3=4.0 / 3.0 * math.pi * (r + params.bloom_mm) ** 3,
            ext_min_mm=params.min_extent_fraction * params.sphere_diameter_mm,
            # blooming on both sides, plus one voxel each side for the quantised extent of the blob
            ext_max_mm=params.sphere_diameter_mm + 2.0 * params.bloom_mm + 2.0 * float(spacing.max()),
        )


NO_CIRCLE_REASON: Final = "wrong shape for a sphere (bone edge, streak crossing or merged objects)"
"""End of the circle cross-check's rejection; such a blob gets the 3-D core test of a split."""

OVERSIZED_REASONS: Final = ("elongated or oversized metal", "blob volume", "sparse metal")
"""Reasons of :func:`blob_reject_reason` that a split into sphere cores may resolve."""


def blob_reject_reason(b: _Blob, limits: SizeLimits, params: DetectionParams) -> str | None:
    """Why a blob is not a sphere by size or brightness (rod, wrong size, bone, streak), or None."""
    size = " × ".join(f"{e:.1f}" for e in b.extent_mm)
    n_sl = b.box[0].stop - b.box[0].start
    if b.extent_mm.max() > limits.ext_max_mm:
        return (
            f"elongated or oversized metal ({size} mm over {n_sl} slices, sphere ≤ "
            f"{limits.ext_max_mm:.1f} mm with blooming): connecting rod or other hardware"
        )
    vol_mm3 = b.n_voxels * limits.voxel_mm3
    if vol_mm3 > limits.v_max_mm3:
        return (
            f"blob volume {vol_mm3:.1f} mm³ > {limits.v_max_mm3:.1f} mm³ "
            f"(Ø{params.sphere_diameter_mm} mm sphere with blooming): wrong size"
        )
    if b.peak_hu < params.min_peak_hu:
        return (
            f"not bright enough for metal (peak {b.peak_hu:.0f} HU < {params.min_peak_hu:.0f} HU): "
            "bone edge or streak crossing"
        )
    if b.extent_mm.min() < limits.ext_min_mm or vol_mm3 < params.min_volume_fraction * limits.v_nominal_mm3:
        return (
            f"too small ({size} mm, {vol_mm3:.2f} mm³; a Ø{params.sphere_diameter_mm} mm sphere is "
            f"≥ {limits.ext_min_mm:.2f} mm across): streak crossing or noise"
        )
    fill = b.n_voxels / math.prod(s.stop - s.start for s in b.box)
    if fill < params.min_fill_fraction:
        return (
            f"sparse metal (fills {fill:.2f} of its bounding box < {params.min_fill_fraction}; a sphere "
            "fills about 0.5): streak fragment"
        )
    return None


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


def slice_circles(
    vox: NDArray[Any],
    k_range: range,
    centre_ijk: F64,
    params: DetectionParams,
    pixel_mm: float,
    timer: StageTimer,
    support: Support | None = None,
) -> list[_SliceCircle]:
    """The accepted circle nearest the 3-D centre in each slice of ``k_range`` (MAR as configured).

    With ``paper`` + MAR every patch is MAR-filtered first (Bai 2018); otherwise MAR runs only on a
    patch whose raw cross-section fails the circle test.
    """
    shape = vox.shape
    half_px = max(math.ceil(params.patch_half_mm / pixel_mm), params.min_patch_half_px)
    ci, cj = float(centre_ijk[0]), float(centre_ijk[1])
    j0, j1 = max(round(cj) - half_px, 0), min(round(cj) + half_px + 1, shape[1])
    i0, i1 = max(round(ci) - half_px, 0), min(round(ci) + half_px + 1, shape[2])
    r_app_px = (params.radius_mm + params.bloom_mm) / pixel_mm
    mar_every_patch = params.use_mar and params.method == "paper"

    def circle(patch: NDArray[np.float32], k: int) -> _SliceCircle | None:
        with timer.stage("circles_s"):
            return _circle_near(patch, k, (i0, j0), (ci, cj), r_app_px, pixel_mm, params.circles)

    circles: list[_SliceCircle] = []
    for k in k_range:
        patch = np.asarray(vox[k, j0:j1, i0:i1], dtype=np.float32)
        if support is not None:
            patch = _flatten_outside(patch, k, (j0, i0), support, params.circles.window_hu[0])
        best = None if mar_every_patch else circle(patch, k)
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
    inside = _support_mask(lo, hi, support)[0]
    return np.where(inside, patch, np.minimum(patch, np.float32(floor_hu)))


@dataclass(frozen=True, eq=False)
class SpherePatch:
    """The raw voxels around one sphere, for estimators that look at intensities.

    ``values_hu`` (V,) and ``coords_mm`` (V, 3) = voxel index (i, j, k) × spacing; ``spacing_mm``
    (i, j, k); ``saturation_hu`` (inf if the crop is not clipped); ``radius_mm`` nominal;
    ``core``: the ``core`` method's weights; ``near_edge``: the sphere is within the patch
    radius of an edge of the imaged region (slab end, matrix edge, circular FOV), so the patch is
    cut or holds padding; ``edge_centre_ijk``: then the ``core`` method's centre, measured on the
    volume with the symmetric edge window (:func:`core_edge_centre`).
    """

    values_hu: F64
    coords_mm: F64
    spacing_mm: F64
    saturation_hu: float
    radius_mm: float
    fit: FitParams = field(default_factory=FitParams)
    core: CoreWeights | None = None
    near_edge: bool = False
    edge_centre_ijk: F64 | None = None
    rays: RayFit | None = None


def sphere_patch(vox: NDArray[Any], centre_ijk: F64, spacing: F64, params: DetectionParams) -> SpherePatch:
    """Voxels within ``radius + bloom + background_shell`` mm of ``centre_ijk`` (clamped to the volume)."""
    r_out = params.radius_mm + params.bloom_mm + params.background_shell_mm
    half = np.ceil(r_out / spacing).astype(int) + 1
    c = np.rint(centre_ijk).astype(int)
    lo = np.maximum(c - half, 0)
    hi = np.minimum(c + half + 1, (vox.shape[2], vox.shape[1], vox.shape[0]))
    crop = np.asarray(vox[lo[2] : hi[2], lo[1] : hi[1], lo[0] : hi[0]], dtype=np.float64)
    kk, jj, ii = np.meshgrid(
        np.arange(lo[2], hi[2]), np.arange(lo[1], hi[1]), np.arange(lo[0], hi[0]), indexing="ij"
    )
    coords = np.stack([ii.ravel(), jj.ravel(), kk.ravel()], axis=1).astype(np.float64) * spacing
    keep = np.sum((coords - centre_ijk * spacing) ** 2, axis=1) <= r_out**2
    values = crop.ravel()[keep]
    peak = float(values.max()) if len(values) else math.nan
    saturated = len(values) > 0 and int(np.count_nonzero(values == peak)) >= SATURATION_MIN_VOXELS
    core = CoreWeights(
        params.core,
        margin_hu=params.centroid_margin_hu,
        shell_mm=params.background_shell_mm,
        min_shell_voxels=LINEAR_BACKGROUND_MIN_VOXELS,
    )
    return SpherePatch(
        values, coords[keep], spacing, peak if saturated else math.inf, params.radius_mm, core=core
    )


class CentreEstimator(Protocol):
    """(circles, subvoxel centre (i, j, k), fitted radius mm, slice spacing mm, raw patch) →
    (centre (i, j, k) or None, why not)."""

    def __call__(
        self,
        circles: list[_SliceCircle],
        centre_sv: F64,
        radius_fit_mm: float,
        dz_mm: float,
        patch: SpherePatch | None = None,
    ) -> tuple[F64 | None, str]: ...


def _subvoxel_estimate(
    circles: list[_SliceCircle],
    centre_sv: F64,
    radius_fit_mm: float,
    dz_mm: float,
    patch: SpherePatch | None = None,
) -> tuple[F64 | None, str]:
    """The 3-D sub-voxel centre on the raw volume; the circles are only its cross-check."""
    return centre_sv, ""


def _model_estimate(
    circles: list[_SliceCircle],
    centre_sv: F64,
    radius_fit_mm: float,
    dz_mm: float,
    patch: SpherePatch | None = None,
) -> tuple[F64 | None, str]:
    """A blurred, saturated ball of the nominal radius fitted to the raw voxels, from the centroid."""
    if patch is None or len(patch.values_hu) < MODEL_MIN_VOXELS:
        return None, "model method: no raw voxels around the sphere to fit"
    fit = fit_sphere_model(
        patch.values_hu,
        patch.coords_mm,
        centre_sv * patch.spacing_mm,
        patch.radius_mm,
        patch.saturation_hu,
        patch.fit,
    )
    if not fit.ok:
        return None, f"model fit failed: {fit.reason}"
    return fit.centre_mm / patch.spacing_mm, ""


MODEL_MIN_VOXELS: Final = 27
"""The model has 6 parameters; fewer than a 3 × 3 × 3 block of voxels cannot constrain it."""


def _core_estimate(
    circles: list[_SliceCircle],
    centre_sv: F64,
    radius_fit_mm: float,
    dz_mm: float,
    patch: SpherePatch | None = None,
) -> tuple[F64 | None, str]:
    """Centroid of the saturated core (:mod:`registration.core_centroid`), from the sub-voxel
    centre; near an edge of the imaged region the core's edge-corrected centre
    (``patch.edge_centre_ijk``), else the sub-voxel one."""
    if patch is not None and patch.near_edge:
        return (centre_sv if patch.edge_centre_ijk is None else patch.edge_centre_ijk), ""
    if patch is None or patch.core is None:
        return centre_sv, ""
    c = core_centroid(
        patch.values_hu,
        patch.coords_mm,
        centre_sv * patch.spacing_mm,
        patch.radius_mm,
        patch.saturation_hu,
        patch.core,
    )
    return (centre_sv, "") if c is None else (c / patch.spacing_mm, "")


def _rays_estimate(
    circles: list[_SliceCircle],
    centre_sv: F64,
    radius_fit_mm: float,
    dz_mm: float,
    patch: SpherePatch | None = None,
) -> tuple[F64 | None, str]:
    """The in-plane centre of the sphere's outline (:mod:`registration.ray_fit`,
    ``patch.rays``) with the slice coordinate of ``centre_sv`` (the centroid's per-slice profile,
    :func:`axial_profile_centre`; with the rays' own axial offset too, cone-beam steel SPR 0.3
    measured 0.052 mm mean against 0.037 mm at an earlier 1.5 mm reach).  Near an edge of the imaged region
    (``patch.near_edge``, where the caller casts no rays) ``centre_sv`` itself, edge-corrected:
    rays that run into the edge have no crossing and the lost directions bias the fit (a steel
    sphere 1.5 mm inside the FOV circle erred 0.091 mm against 0.039 mm for the edge-corrected
    centroid, ``steel partial x40`` seed 6).  None (refused) if the rays did not outline a sphere."""
    fit = None if patch is None or patch.near_edge else patch.rays
    if fit is None:
        return centre_sv, ""
    c = fit.centre_ijk
    if c is None:
        return None, fit.reason
    return np.array([c[0], c[1], centre_sv[2]]), ""


def _paper_estimate(
    circles: list[_SliceCircle],
    centre_sv: F64,
    radius_fit_mm: float,
    dz_mm: float,
    patch: SpherePatch | None = None,
) -> tuple[F64 | None, str]:
    """Bai 2018: in-plane mean of the circle centres, depth by Pythagoras with the fitted radius."""
    if len({c.k for c in circles}) < 2 or not math.isfinite(radius_fit_mm) or radius_fit_mm <= 0:
        return None, (
            f"paper method: {len(circles)} circle slice(s), the per-slice radii do not fit a sphere "
            "(r_i² + z_i² = c + 2·z0·z_i needs ≥ 2 slices); try --method subvoxel"
        )
    k_c = _paper_depth(circles, radius_fit_mm, dz_mm)
    return np.array([np.mean([c.i for c in circles]), np.mean([c.j for c in circles]), k_c]), ""


CENTRE_ESTIMATORS: Final[Mapping[str, CentreEstimator]] = {
    "subvoxel": _subvoxel_estimate,
    "model": _model_estimate,
    "paper": _paper_estimate,
    "core": _core_estimate,
    "rays": _rays_estimate,
}
"""The centre estimator of each :data:`METHODS` entry."""


PATCH_METHODS: Final = ("model", "core")
"""Methods whose estimator looks at the raw voxels around the sphere (:class:`SpherePatch`)."""

AXIAL_PROFILE_METHODS: Final = ("subvoxel", "rays")
"""Methods whose estimator starts from the centroid with its slice coordinate from the per-slice
profile (:func:`axial_profile_centre`)."""


def _near_edge(
    centre_ijk: F64, shape: tuple[int, int, int], spacing: F64, fov_radius_mm: float | None, reach_mm: float
) -> bool:
    """Whether an edge of the imaged region (:func:`_boundaries`) is within ``reach_mm`` of the centre."""
    return any(
        edge_mm - float(u @ (centre_ijk * spacing)) <= reach_mm
        for _, u, edge_mm, _ in _boundaries(centre_ijk, shape, spacing, fov_radius_mm)
    )


def rays_patch(
    scan: _Scan, centre_sv: F64, centre_est: F64, saturation_hu: float, params: DetectionParams
) -> SpherePatch:
    """What the ``rays`` estimator needs: the ray fit (:func:`registration.ray_fit.ray_centre`)
    from ``centre_est``, or none near an edge of the imaged region (``near_edge``, judged at
    ``centre_sv`` as for the other patch methods).  No voxels: the rays sample the volume."""
    vox, spacing = scan.volume.voxels, scan.spacing
    shape = (vox.shape[0], vox.shape[1], vox.shape[2])
    reach_mm = params.radius_mm + params.bloom_mm + params.background_shell_mm
    near = _near_edge(centre_sv, shape, spacing, scan.fov_radius_mm, reach_mm)
    fit = (
        None
        if near
        else ray_centre(
            vox, centre_est, spacing, params.radius_mm, saturation_hu, params.rays, scan.fov_radius_mm
        )
    )
    empty = np.zeros(0)
    return SpherePatch(
        empty, empty.reshape(0, 3), spacing, saturation_hu, params.radius_mm, near_edge=near, rays=fit
    )


def core_edge_centre(
    vox: NDArray[Any],
    centre_ijk: F64,
    spacing: F64,
    params: DetectionParams,
    fov_radius_mm: float | None,
    support: Support | None = None,
) -> F64:
    """The ``core`` method's centre of a sphere near an edge of the imaged region: the default
    centroid and its symmetric edge window (:func:`edge_refined_centre`) with the core's ball and
    margin (``params.core``).  On the cached tungsten-carbide sweep scans, 6 spheres near an edge:
    mean / max 0.048 / 0.113 mm against 0.067 / 0.181 mm for the default ball and margin."""
    cp = replace(params, bloom_mm=params.core.bloom_mm, centroid_margin_fraction=params.core.margin_fraction)
    c, _, _ = _subvoxel_centre(vox, centre_ijk, spacing, cp, support)
    c, _ = edge_refined_centre(vox, c, spacing, cp, fov_radius_mm, support)
    return c


def sphere_score(
    circles: list[_SliceCircle], centre_sv: F64, spacing: F64, n_slices: int, radius_mm: float
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


@dataclass(frozen=True)
class _Scan:
    """What every blob's measurement needs from the volume (internal)."""

    volume: Volume
    spacing: F64
    pixel_mm: float
    dz_mm: float
    fov_radius_mm: float | None


def _measure_sphere(
    b: _Blob, scan: _Scan, limits: SizeLimits, params: DetectionParams, timer: StageTimer
) -> DetectedSphere | str:
    """The sphere a blob is, or the reason it is rejected."""
    reason = blob_reject_reason(b, limits, params)
    if reason is not None:
        return reason
    vox, spacing, r = scan.volume.voxels, scan.spacing, params.radius_mm
    shape = (vox.shape[0], vox.shape[1], vox.shape[2])
    with timer.stage("centres_s"):
        centre_sv, bg, peak = _subvoxel_centre(vox, b.centroid_voxel, spacing, params, b.support)
        centre_sv, reason = edge_refined_centre(
            vox, centre_sv, spacing, params, scan.fov_radius_mm, b.support
        )
        bw_sv = _ball_weights(vox, centre_sv, spacing, params, None)
        ratio = core_axis_ratio(bw_sv, spacing)
    if reason is None and ratio > MAX_CORE_AXIS_RATIO:
        reason = (
            f"elongated core (axis ratio {ratio:.1f} > {MAX_CORE_AXIS_RATIO} of the weights around the "
            "centre): a streak, not a sphere"
        )
    reason = (
        reason
        or edge_reject_reason(centre_sv, shape, spacing, r)
        or fov_reject_reason(centre_sv, scan.fov_radius_mm, shape, spacing, r)
    )
    if reason is not None:
        return reason
    circles = slice_circles(
        vox, range(b.box[0].start, b.box[0].stop), centre_sv, params, scan.pixel_mm, timer, b.support
    )
    # A split core already passed a 3-D shape test (it survived the opening and is sphere-sized on
    # every axis); its cross-sections are bloomed along the streaks that joined it (axis ratio
    # down to 0.5 for tungsten carbide under strong scatter), so the 2-D circle test is not a gate.
    if len(circles) < params.min_circle_slices and b.support is None:
        return (
            f"{len(circles)} slice(s) with a circular cross-section (need {params.min_circle_slices}): "
            + NO_CIRCLE_REASON
        )
    radius_fit, _ = _fit_radius(circles, scan.dz_mm)
    patch = sphere_patch(vox, centre_sv, spacing, params) if params.method in PATCH_METHODS else None
    if patch is not None:
        reach_mm = params.radius_mm + params.bloom_mm + params.background_shell_mm
        near = _near_edge(centre_sv, shape, spacing, scan.fov_radius_mm, reach_mm)
        edge_c = (
            core_edge_centre(vox, centre_sv, spacing, params, scan.fov_radius_mm, b.support)
            if near and params.method == "core"
            else None
        )
        patch = replace(patch, near_edge=near, edge_centre_ijk=edge_c)
    with timer.stage("centres_s"):
        centre_est = (
            axial_profile_centre(vox, centre_sv, spacing, params, b.support)
            if params.method in AXIAL_PROFILE_METHODS
            else centre_sv
        )
        if params.method == "rays":
            patch = rays_patch(
                scan, centre_sv, centre_est, bw_sv.peak_hu if bw_sv.saturated else math.inf, params
            )
        centre, reason = CENTRE_ESTIMATORS[params.method](circles, centre_est, radius_fit, scan.dz_mm, patch)
    if centre is None:
        return reason
    log.debug(
        "sphere at voxel %s: bg %.0f HU, peak %.0f HU, %d circles, R_fit %.2f mm",
        centre,
        bg,
        peak,
        len(circles),
        radius_fit,
    )
    return DetectedSphere(
        center_image_mm=scan.volume.voxel_to_image(centre).astype(np.float64),
        radius_mm=float(radius_fit),
        n_slices=len(circles),
        score=sphere_score(circles, centre_sv, spacing, b.box[0].stop - b.box[0].start, r),
        center_voxel=centre.astype(np.float64),
    )


def _measure_blob(
    b: _Blob, scan: _Scan, limits: SizeLimits, params: DetectionParams, threshold_hu: float, timer: StageTimer
) -> list[tuple[_Blob, DetectedSphere | str]]:
    """(blob, sphere or rejection reason) for a blob, or for each sphere core of an oversized one.

    A blob too large for one sphere is split (:func:`split_blob`); if none of its cores is
    sphere-sized the blob is rejected with its own reason (a rod stays a rod).
    """
    reason = blob_reject_reason(b, limits, params)
    if reason is None:
        found = _measure_sphere(b, scan, limits, params, timer)
        if not (isinstance(found, str) and found.endswith(NO_CIRCLE_REASON)):
            return [(b, found)]
        reason = found  # streak-bloomed cross-sections: the 3-D core test decides
    elif not reason.startswith(OVERSIZED_REASONS):
        return [(b, reason)]
    with timer.stage("components_s"):
        cores = split_blob(scan.volume.voxels, b, threshold_hu, scan.spacing, params)
    sized = [c for c in cores if blob_reject_reason(c, limits, params) is None]
    if not sized:
        return [(b, reason)]
    out = [(c, _measure_sphere(c, scan, limits, params, timer)) for c in sized]
    rest = [c for c in cores if blob_reject_reason(c, limits, params) is not None]
    out.extend((c, f"part of a split blob: {blob_reject_reason(c, limits, params)}") for c in rest)
    return out


# ----------------------------------------------------------------------------- main entry


def detect_spheres(volume: Volume, params: DetectionParams = DetectionParams()) -> DetectionResult:
    """Find the metal spheres of a calibration phantom in a CT volume.

    Parameters
    ----------
    volume : Volume
        ``voxels[k, j, i]`` in HU (int16 or float), with ``image_from_voxel``.
    params : DetectionParams

    Returns
    -------
    DetectionResult
        Spheres (centres in the image frame, LPS mm) in order of increasing
        (k, j, i) of their candidate blob, every rejected candidate with its
        reason, and per-stage timings.  An empty result is not an error: the
        caller decides how many spheres it needs.

    Raises
    ------
    DetectionError
        If the volume is not 3-D or has a degenerate geometry.
    """
    t_start = time.perf_counter()
    timer = StageTimer(TIMED_STAGES)
    spacing = _checked_spacing(volume)  # (i, j, k) mm
    vox = volume.voxels
    with timer.stage("threshold_s"):
        flat, thr_cast = threshold_hits(vox, params.candidate_threshold_hu)
    with timer.stage("group_s"):
        boxes = _group_hits(flat, volume.shape) if len(flat) else []
    with timer.stage("components_s"):
        blobs = find_blobs(vox, boxes, thr_cast, spacing, params.crop_margin_mm)
    scan = _Scan(
        volume,
        spacing,
        pixel_mm=float(0.5 * (spacing[0] + spacing[1])),
        dz_mm=float(spacing[2]),
        fov_radius_mm=_circular_fov_radius_mm(vox, spacing),
    )
    limits = SizeLimits.of(params, spacing)
    spheres: list[DetectedSphere] = []
    metal_voxels: list[int] = []
    rejections: list[Rejection] = []
    for b in blobs:
        for part, found in _measure_blob(b, scan, limits, params, thr_cast, timer):
            if isinstance(found, DetectedSphere):
                spheres.append(found)
                metal_voxels.append(part.n_voxels)
            else:
                where = volume.voxel_to_image(part.centroid_voxel)
                rejections.append(Rejection((float(where[0]), float(where[1]), float(where[2])), found))
    spheres, crowded = _separate(spheres, params.min_separation_mm, metal_voxels)
    rejections.extend(crowded)
    timings = dict(timer.seconds)
    timings["total_s"] = time.perf_counter() - t_start
    log.info(
        "series %s: %d spheres, %d rejected, method %s, %.3f s",
        volume.series_uid,
        len(spheres),
        len(rejections),
        params.method,
        timings["total_s"],
    )
    return DetectionResult(tuple(spheres), tuple(rejections), params.method, timings)


FRAGMENT_METAL_FRACTION: Final = 0.5
"""A candidate with less than this fraction of the metal voxels of another one closer than the
phantom allows is a fragment of it (issue #11 sweep: the streak fragments that displaced
tungsten-carbide spheres held 21–31 voxels, ≤ 0.27 of the sphere's 116–122; two candidates of
one sphere held 118 and 165, 0.72)."""


def _separate(
    spheres: list[DetectedSphere], min_separation_mm: float, metal_voxels: list[int] | None = None
) -> tuple[list[DetectedSphere], list[Rejection]]:
    """Spheres at least ``min_separation_mm`` apart and a rejection for each one dropped.

    Of a closer pair the one kept is not a fragment (:data:`FRAGMENT_METAL_FRACTION` of the
    other's metal voxels), then has more circle slices, then the higher score; input order kept.
    The fragment test comes first because a split core's circle test is not a gate (it may have 0
    circle slices): a streak fragment with one circular slice outranked the tungsten-carbide
    sphere 5 mm from it (issue #11, cone-beam).
    """
    metal = np.asarray(metal_voxels if metal_voxels is not None else [0] * len(spheres), dtype=np.float64)
    centres = np.array([sp.center_image_mm for sp in spheres]).reshape(-1, 3)
    close = np.linalg.norm(centres[:, None] - centres[None], axis=2) < min_separation_mm
    fragment = metal < FRAGMENT_METAL_FRACTION * np.max(
        np.where(close, metal[None, :], 0.0), axis=1, initial=0.0
    )
    rank = sorted(
        range(len(spheres)), key=lambda n: (bool(fragment[n]), -spheres[n].n_slices, -spheres[n].score, n)
    )
    kept: list[int] = []
    dropped: list[Rejection] = []
    for n in rank:
        c = spheres[n].center_image_mm
        near = [m for m in kept if float(np.linalg.norm(spheres[m].center_image_mm - c)) < min_separation_mm]
        if not near:
            kept.append(n)
            continue
        d = float(np.linalg.norm(spheres[near[0]].center_image_mm - c))
        dropped.append(
            Rejection(
                (float(c[0]), float(c[1]), float(c[2])),
                f"{d:.1f} mm from a sphere with more metal, circle slices or score (spheres are "
                f"≥ {min_separation_mm} mm apart): a second core of the same sphere or a streak fragment",
            )
        )
    return [spheres[n] for n in sorted(kept)], dropped


def _circle_near(
    patch: NDArray[np.float32],
    k: int,
    origin_ij: tuple[int, int],
    centre_ij: tuple[float, float],
    max_offset_px: float,
    pixel_mm: float,
    circle_params: CircleParams,
) -> _SliceCircle | None:
    """The accepted circle of slice ``k``'s patch nearest the 3-D centre, within ``max_offset_px``."""
    best: _SliceCircle | None = None
    best_d = math.inf
    for c in find_circles(patch, pixel_mm, circle_params):
        if not c.accepted:
            continue
        i = c.center_px[0] + origin_ij[0]
        j = c.center_px[1] + origin_ij[1]
        d = math.hypot(i - centre_ij[0], j - centre_ij[1])
        if d <= max_offset_px and d < best_d:
            best_d = d
            best = _SliceCircle(i, j, k, c.radius_px * pixel_mm)
    return best
