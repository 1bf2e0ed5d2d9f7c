"""Detection settings, and the one function that chooses them from the phantom's spheres.

:class:`DetectionParams` holds every threshold of the detection (unit in each name, origin in
each docstring); :func:`params_for_spheres` is where the service and every command take them
from: the centre estimator follows the sphere material (:data:`METHOD_FOR_MATERIAL`), the
diameter the phantom file.  The figures behind the defaults are in ``docs/validation.md``
("Sphere detection") with the commands that reproduce them.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any, Final

from registration.detection.estimators import METHODS
from registration.detection.estimators.core_centroid import CoreParams
from registration.detection.estimators.ray_fit import RayParams
from registration.errors import DetectionError
from registration.imaging.circles import CircleParams
from registration.imaging.mar import MarParams

METHOD_FOR_MATERIAL: Final[Mapping[str, str]] = {
    "tungsten_carbide": "core",
    "steel": "rays",
    "titanium": "rays",
}
"""Centre estimator per sphere material (``registration.model.phantom``'s names) where it is not the
default ``subvoxel``.  On the simulator's hard scans (``python -m benchmarks.bench_detection
--hard 40``, and held-out seeds) ``core`` measured best on tungsten carbide and worse on steel and
titanium, ``rays`` best on steel and titanium and worse than ``core`` on tungsten carbide:
``docs/validation.md``, "Sphere detection".  Chosen again on TRE at the working poses (tilts up to
40°, both hole models, slice-wise and cone-beam, with the face-offset fit; ``python -m
benchmarks.bench_detection --face-offset 6 --face-offset-methods subvoxel,rays,core``): the same
two, ``docs/validation.md``, "Face offset"."""


BACKGROUND_MODELS: Final = ("linear", "constant")
"""Background under a sphere for the centroid weights (:class:`DetectionParams`)."""


@dataclass(frozen=True)
class DetectionParams:
    """Sphere-detection settings.  Every threshold has its unit in its name.

    The defaults were measured on the simulator's scans (``docs/validation.md``, "Sphere
    detection", with the commands); what each one does and why it is where it is:

    Attributes
    ----------
    method : str
        Centre estimator (:data:`registration.detection.estimators.METHODS`): ``subvoxel``
        (intensity-weighted 3-D centroid), ``paper`` (per-slice Pythagoras, Bai 2018), ``model``,
        ``core``, ``rays``; :func:`params_for_spheres` picks it by sphere material.
    sphere_diameter_mm : float
        Nominal sphere diameter (phantom definition, 2.5 mm in Bai 2018 §2.1).
    use_mar : bool
        Apply the polar MAR before circle recognition.  With ``paper`` on every slice patch (the
        circles *are* the measurement); otherwise only on a patch whose raw cross-section fails
        the circle test: MAR on every patch gave the same centres at ~3× the time.
    candidate_threshold_hu : float
        Metal threshold of the candidate pass: metal spheres saturate at 3071 HU (12-bit export),
        cortical bone and streaks stay below ~1800 HU (image-side.md §3.3).
    min_peak_hu : float
        A sphere's brightest voxel reaches this (a blurred 2.5 mm steel sphere still clips);
        bone edges and streak crossings that cross the candidate threshold peak lower.
    bloom_mm : float
        Allowance for the apparent growth of a sphere by PSF and clipping (apparent radius up to
        1.9 mm for a 1.25 mm sphere, image-side.md §3.3).
    min_extent_fraction, min_volume_fraction : float
        Smallest thresholded extent (per axis, fraction of the diameter) and volume (fraction of
        the nominal ball): smaller blobs are streak crossings or noise.
    min_fill_fraction : float
        Smallest fraction of its bounding box a blob fills (a ball ≈ 0.52, streak-tailed spheres
        down to 0.16, a cone-beam streak fragment 0.079); a sparser blob is split into cores.
    centroid_margin_hu, centroid_margin_fraction : float
        ``subvoxel`` weights are ``HU − (background + margin)`` clipped at 0, the margin at least
        this many HU (keeps ±200 HU noise and streaks out) and this fraction of the sphere signal
        (0.5: the half-maximum core, which keeps the face the spheres sit on out).
    centroid_iterations : int
        Re-centrings of the weighting ball.
    min_circle_slices : int
        Slices with an accepted circle needed to accept a sphere (the circles cross-check the 3-D
        estimate; ``paper`` needs ≥ 2 for its radius fit).
    patch_half_mm, min_patch_half_px : float, int
        Half-size of the square slice patch for MAR and circles, at least this many pixels.
    crop_margin_mm : float
        Margin around a group of threshold hits when its components are labelled: more than a
        voxel of blooming each side, far below the 15 mm pitch.
    split_core_fraction : float
        An oversized blob is split by a morphological opening with an ellipsoid of this fraction
        of the nominal radius: streaks (1–2 voxels wide) vanish, sphere cores and the rod stay.
    split_retry_core_fraction : float
        When the first split leaves no sphere-sized core, the blob is split again with an opening
        of this fraction of the nominal radius before it is called oversized (bright
        tungsten-carbide streaks more than 2 mm thick survived the 0.75 R opening and left a
        6.78 mm core against the 6.75 mm limit, three spheres of forty in one row missed; 1.0 R
        gave 3.0–3.8 mm cores, 40 / 40, and rods and bone stayed rejected).  A rod thicker than
        the sphere survives both openings.
    background_shell_mm : float
        Thickness of the shell outside the weighting ball that gives the local background.
    background_model : str
        ``linear`` (a plane through the shell, so a sphere on the phantom face is weighted over
        its own signal) or ``constant`` (the shell's median; biased along the face normal).
    axial_profile_margin_fraction, axial_profile_min_fraction : float
        ``subvoxel`` / ``rays``: margin of the weights whose per-slice sums give the slice
        coordinate (:func:`registration.detection.centroid.axial_profile_position`), and the
        fraction of the largest sum below which a slice (a blurred tip) is left out of the fit.
    edge_plateau_fraction : float
        Near the FOV circle or the matrix edge, a sphere whose image is still above this fraction
        of its contrast where the data end is refused (its clipped plateau runs into the edge, no
        window locates it: :func:`registration.detection.fov.plateau_reaches_edge`).  The highest
        level that let no cut sphere through, below the levels that mistake a dark band for the
        plateau's end (``python -m benchmarks.bench_fov_edge``).
    min_separation_mm : float
        Reported centres are at least this far apart (half the 15 mm hole pitch of Bai 2018); of
        a closer pair the fragment, then the one with fewer circle slices, is dropped.
    core, rays : CoreParams, RayParams
        The ``core`` and ``rays`` estimators' own settings.
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
    split_retry_core_fraction: float = 1.0
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
