"""Issue #43: the pull of the detected centres along the hole axes, before and after the face-offset fit.

For each hole model (``tight``, ``drilled``; mocks/oarm/simulator.py ``SceneExtras.hole_model``) ×
geometry (slice-wise ``oarm-realistic``, cone-beam ``oarm-cbct``, both cropped around the phantom)
× sphere material (steel on bai2018_cube, tungsten carbide on wc_rows40), and a control with the
same spheres and no cube, at random phantom poses (tilts up to 40°):

- the mean error of the detected centres along their hole's outward axis, mm;
- the similarity scale of the detected pattern against the truth, ‰ (Umeyama with scale);
- FLE (mean distance from the truth, mm);

with the centres as detected and with the face offset β removed
(:func:`registration.matching.face_offset_grid.grid_face_offset`).  :func:`scan_metrics` is what
tests/accuracy/test_face_offset.py asserts on a cheap subset.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, Final

import numpy as np

from registration.arrays import F64

MATCH_MM: Final = 1.0
MAX_TILT_DEG: Final = 40.0
"""Largest tilt of the phantom's z axis from the scanner axis (issue #43's working poses)."""

HOLE_MODELS: Final = ("tight", "drilled")
GEOMETRIES: Final = ("slice", "cone")
MATERIALS: Final = {"steel": "bai2018_cube", "tungsten_carbide": "wc_rows40"}


def random_pose(seed: int, max_tilt_deg: float = MAX_TILT_DEG) -> F64:
    """image_from_phantom (4 × 4): any rotation about z, the z axis tilted up to ``max_tilt_deg``
    (uniform on the spherical cap), a few mm off the isocentre."""
    from scipy.spatial.transform import Rotation

    rng = np.random.default_rng(seed)
    cos_max = math.cos(math.radians(max_tilt_deg))
    tilt = math.acos(rng.uniform(cos_max, 1.0))
    azimuth = rng.uniform(0.0, 2.0 * math.pi)
    spin = rng.uniform(0.0, 2.0 * math.pi)
    axis = np.array([math.cos(azimuth), math.sin(azimuth), 0.0])
    rot = Rotation.from_rotvec(axis * tilt) * Rotation.from_rotvec([0.0, 0.0, spin])
    pose = np.eye(4)
    pose[:3, :3] = rot.as_matrix()
    pose[:3, 3] = rng.uniform(-3.0, 3.0, 3)
    return pose


def similarity_scale(source: F64, target: F64) -> float:
    """Umeyama's (1991, doi:10.1109/34.88573) least-squares scale of target ≈ s R source + t."""
    a = source - source.mean(axis=0)
    b = target - target.mean(axis=0)
    u, d, vt = np.linalg.svd(b.T @ a)
    sign = np.ones(3)
    sign[-1] = np.sign(np.linalg.det(u @ vt))
    return float(np.sum(d * sign) / np.sum(a * a))


@dataclass(frozen=True)
class ScanMetrics:
    """One scan's figures over its matched spheres (before / after the face-offset fit)."""

    axial_mm: F64  # (K,) error along each matched sphere's outward hole axis, as detected
    axial_after_mm: F64  # the same with β removed (NaN where the fit paired no hole)
    error_mm: F64  # (K,) distance from the truth, as detected
    error_after_mm: F64
    scale_permille: float
    scale_after_permille: float
    beta_mm: float
    beta_se_mm: float
    missed: int
    tre_mm: float = math.nan  # registration without the face-offset fit (worst target)
    tre_after_mm: float = math.nan  # with it


def scan_metrics(phantom: Any, scan: Any, method: str | None = None) -> ScanMetrics:
    """Detect, fit β over the hole grid, and measure against the scan's truth."""
    from mocks.oarm.simulator import scan_to_volume
    from registration.detection import detect_spheres, params_for_spheres
    from registration.matching.face_offset_grid import grid_face_offset

    params = params_for_spheres(
        scan.sphere_material, phantom.sphere_diameter_mm, **({} if method is None else {"method": method})
    )
    det = grid_face_offset(detect_spheres(scan_to_volume(scan), params), phantom)
    c = det.centres_image_mm
    corrected = det.face_offset.centres_image_mm if det.face_offset is not None else np.full_like(c, np.nan)
    truth = scan.spheres_image_mm
    d = np.linalg.norm(c[:, None, :] - truth[None], axis=2) if len(c) else np.zeros((0, len(truth)))
    nearest = d.argmin(axis=0) if len(c) else np.zeros(len(truth), dtype=np.int64)
    hit = (d.min(axis=0) < MATCH_MM) if len(c) else np.zeros(len(truth), dtype=bool)
    axes = phantom.axes_phantom[scan.sphere_indices] @ scan.image_from_phantom[:3, :3].T
    e = c[nearest[hit]] - truth[hit]
    e_after = corrected[nearest[hit]] - truth[hit]
    ax = axes[hit]
    ok = ~np.isnan(e_after).any(axis=1)
    fo = det.face_offset
    return ScanMetrics(
        axial_mm=np.einsum("ij,ij->i", e, ax),
        axial_after_mm=np.einsum("ij,ij->i", e_after, ax),
        error_mm=np.linalg.norm(e, axis=1),
        error_after_mm=np.linalg.norm(e_after, axis=1),
        scale_permille=1e3 * (similarity_scale(truth[hit], c[nearest[hit]]) - 1.0),
        scale_after_permille=(
            1e3 * (similarity_scale(truth[hit][ok], corrected[nearest[hit]][ok]) - 1.0)
            if ok.sum() >= 4
            else math.nan
        ),
        beta_mm=math.nan if fo is None else fo.beta_mm,
        beta_se_mm=math.nan if fo is None else fo.beta_se_mm,
        missed=int((~hit).sum()),
        tre_mm=registration_tre_mm(phantom, scan, c, face_offset=False),
        tre_after_mm=registration_tre_mm(phantom, scan, c, face_offset=True),
    )


def simulate(
    phantom: Any,
    material: str,
    hole_model: str,
    geometry: str,
    seed: int,
    *,
    cube: bool = True,
    crop: int = 256,
) -> Any:
    """One scan of ``phantom`` at :func:`random_pose` (``seed``): slice-wise ``oarm-realistic`` or
    cone-beam ``oarm-cbct`` physics and voxels (0.415 × 0.833 mm) on a ``crop``² matrix around it."""
    from mocks.oarm.simulator import AcquisitionSettings, SceneExtras, simulate_scan

    extras = SceneExtras(sphere_material=material, hole_model=hole_model, cube=cube)
    pose = random_pose(seed)
    subrays = {"tungsten_carbide": 4}.get(material)  # benchmarks/bench_detection.py WC_SUBRAYS
    grid: dict[str, Any] = {"rows": crop, "columns": crop, "n_slices": round(crop * 0.415 / 0.833) + 8}
    if geometry == "cone":
        from mocks.oarm.cbct import ConeBeamSettings, simulate_cbct

        extra = {"subrays": subrays} if subrays else {}
        cb = ConeBeamSettings.preset("oarm-cbct-roi", **grid, seed=seed, **extra)
        return simulate_cbct(phantom, pose, cb, extras)
    extra = {"detector_subsamples": subrays} if subrays else {}
    settings = AcquisitionSettings.preset("oarm-realistic", **grid, seed=seed, **extra)
    return simulate_scan(phantom, pose, settings, extras)


TRE_TARGETS_PHANTOM_MM: Final = np.array([[0.0, 0.0, 0.0], [0.0, 0.0, 100.0], [100.0, 0.0, 0.0]])
"""Where the estimator sweep measures TRE (phantom frame, mm): the phantom origin, 100 mm above it
(about where a tool tip sits over the phantom) and 100 mm to its side."""


def registration_tre_mm(phantom: Any, scan: Any, centres_image_mm: F64, *, face_offset: bool = True) -> float:
    """Largest TRE at :data:`TRE_TARGETS_PHANTOM_MM` of the registration of the detected centres to
    the phantom (mm; NaN when refused), with or without the face-offset fit."""
    from registration.errors import RegistrationError
    from registration.matching.records import RegistrationParams
    from registration.matching.register import register_points
    from registration.model import frames

    try:
        reg = register_points(
            phantom.centres_phantom_mm,
            centres_image_mm,
            phantom=phantom,
            params=RegistrationParams(face_offset_fit=face_offset),
        )
    except RegistrationError:
        return math.nan
    err = frames.apply(reg.image_from_robot, TRE_TARGETS_PHANTOM_MM) - frames.apply(
        scan.image_from_phantom, TRE_TARGETS_PHANTOM_MM
    )
    return float(np.linalg.norm(err, axis=1).max())
