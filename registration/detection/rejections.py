"""Steps 2 and 6 of the detection: what is not a sphere, with the reason it is refused.

A blob is refused by size and brightness before any centre is measured (:func:`blob_reject_reason`:
a rod, bone, a streak crossing; an oversized or sparse blob is split first), by the shape of its
centroid weights after (:func:`core_axis_ratio`: a streak line), and at the end of two reported
centres closer than the phantom allows the fragment or the weaker one is dropped
(:func:`separate`).  Every refusal is kept with its reason in ``DetectionResult.rejections``:
a false refusal is a defect too, so each must say why.  The cuts by the volume and FOV edges are
in :mod:`.fov` and :mod:`.refine`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Final

import numpy as np

from registration.arrays import F64
from registration.detection.candidates import Blob
from registration.detection.centroid import BallWeights
from registration.detection.params import DetectionParams
from registration.detection.records import DetectedSphere, Rejection


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


def blob_reject_reason(b: Blob, limits: SizeLimits, params: DetectionParams) -> str | None:
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


MAX_CORE_AXIS_RATIO: Final = 4.0
"""Largest axis ratio (√ of the largest / smallest eigenvalue of the weighted covariance) of a
sphere's centroid weights.  Measured over 480 detected spheres (cone-beam and parallel steel,
tungsten carbide with streaks, titanium): ≤ 2.5; a bright cone-beam streak line that passed the
size and peak tests: 8.2."""


def core_axis_ratio(bw: BallWeights, spacing: F64) -> float:
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


FRAGMENT_METAL_FRACTION: Final = 0.5
"""A candidate with less than this fraction of the metal voxels of another one closer than the
phantom allows is a fragment of it (hard sweep: the streak fragments that displaced
tungsten-carbide spheres held 21–31 voxels, ≤ 0.27 of the sphere's 116–122; two candidates of
one sphere held 118 and 165, 0.72)."""


def separate(
    spheres: list[DetectedSphere], min_separation_mm: float, metal_voxels: list[int] | None = None
) -> tuple[list[DetectedSphere], list[Rejection]]:
    """Spheres at least ``min_separation_mm`` apart and a rejection for each one dropped.

    Of a closer pair the one kept is not a fragment (:data:`FRAGMENT_METAL_FRACTION` of the
    other's metal voxels), then has more circle slices, then the higher score; input order kept.
    The fragment test comes first because a split core's circle test is not a gate (it may have 0
    circle slices): a streak fragment with one circular slice outranked the tungsten-carbide
    sphere 5 mm from it (cone-beam).
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
