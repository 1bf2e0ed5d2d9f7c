"""The detection's entry point: :func:`detect_spheres` runs the steps in order, one blob at a time.

1. :mod:`.candidates`: threshold, grouping, labelling, the split of oversized blobs;
2. :mod:`.rejections`: size and brightness tests of each blob;
3. :mod:`.centroid`: the sub-voxel centroid on the raw volume;
4. :mod:`.refine` and :mod:`.fov`: near an edge of the imaged region, the centre re-measured or
   the sphere refused as cut;
5. :mod:`.cross_check`: the circles in the sphere's slices;
6. :mod:`.estimators`: the centre estimator named by ``DetectionParams.method``, found by name
   in a table (no estimator is imported until a detection asks for it); then the separation rule.

Coordinates: the work is done in voxel indices (i, j, k) = (column, row, slice) and mapped to the
image frame (LPS, mm) by ``volume.image_from_voxel``, so flipped orientations and reversed slice
order need no special case.
"""

from __future__ import annotations

import logging
import math
import time
from dataclasses import dataclass
from typing import Any, Final

import numpy as np

from registration.arrays import F64
from registration.detection.candidates import Blob, find_blobs, group_hits, split_blob, threshold_hits
from registration.detection.centroid import ball_weights, subvoxel_centre
from registration.detection.cross_check import fit_radius, slice_circles, sphere_score
from registration.detection.estimators.base import CentreEstimator, MeasuredSphere, centre_estimator
from registration.detection.fov import circular_fov_radius_mm, edge_reject_reason, fov_reject_reason
from registration.detection.params import DetectionParams
from registration.detection.records import DetectedSphere, DetectionResult, Rejection
from registration.detection.refine import edge_refined_centre
from registration.detection.rejections import (
    MAX_CORE_AXIS_RATIO,
    NO_CIRCLE_REASON,
    OVERSIZED_REASONS,
    SizeLimits,
    blob_reject_reason,
    core_axis_ratio,
    separate,
)
from registration.detection.timing import TIMED_STAGES, StageTimer
from registration.errors import DetectionError
from registration.imaging.volume import Volume

log = logging.getLogger(__name__)


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


@dataclass(frozen=True)
class _Scan:
    """What every blob's measurement needs from the volume (internal)."""

    volume: Volume
    spacing: F64
    pixel_mm: float
    dz_mm: float
    fov_radius_mm: float | None
    estimator: CentreEstimator[Any]


def _measure_sphere(
    b: Blob, scan: _Scan, limits: SizeLimits, params: DetectionParams, timer: StageTimer
) -> DetectedSphere | str:
    """The sphere a blob is, or the reason it is rejected."""
    reason = blob_reject_reason(b, limits, params)
    if reason is not None:
        return reason
    vox, spacing, r = scan.volume.voxels, scan.spacing, params.radius_mm
    shape = (vox.shape[0], vox.shape[1], vox.shape[2])
    with timer.stage("centres_s"):
        centre_sv, bg, peak = subvoxel_centre(vox, b.centroid_voxel, spacing, params, b.support)
        centre_sv, reason = edge_refined_centre(
            vox, centre_sv, spacing, params, scan.fov_radius_mm, b.support
        )
        bw_sv = ball_weights(vox, centre_sv, spacing, params, None)
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
        vox,
        range(b.box[0].start, b.box[0].stop),
        centre_sv,
        params,
        scan.pixel_mm,
        timer,
        b.support,
        mar_every_patch=scan.estimator.circles_are_the_measurement,
    )
    # A split core already passed a 3-D shape test (it survived the opening and is sphere-sized on
    # every axis); its cross-sections are bloomed along the streaks that joined it (axis ratio
    # down to 0.5 for tungsten carbide under strong scatter), so the 2-D circle test is not a gate.
    if len(circles) < params.min_circle_slices and b.support is None:
        return (
            f"{len(circles)} slice(s) with a circular cross-section (need {params.min_circle_slices}): "
            + NO_CIRCLE_REASON
        )
    radius_fit, _ = fit_radius(circles, scan.dz_mm)
    saturation_hu = bw_sv.peak_hu if bw_sv.saturated else math.inf
    sphere = MeasuredSphere(
        vox,
        spacing,
        scan.fov_radius_mm,
        centre_sv,
        saturation_hu,
        b.support,
        circles,
        radius_fit,
        scan.dz_mm,
        params,
    )
    with timer.stage("centres_s"):
        centre, reason = scan.estimator.estimate(scan.estimator.prepare(sphere))
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
    b: Blob, scan: _Scan, limits: SizeLimits, params: DetectionParams, threshold_hu: float, timer: StageTimer
) -> list[tuple[Blob, DetectedSphere | str]]:
    """(blob, sphere or rejection reason) for a blob, or for each sphere core of an oversized one.

    A blob too large for one sphere is split (:func:`split_blob`), and split again with the wider
    ``split_retry_core_fraction`` opening when no core of the first is sphere-sized; if none of
    its cores is sphere-sized then the blob is rejected with its own reason (a rod stays a rod).
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
        if not sized:  # streaks thicker than the first opening: split again, wider
            cores = split_blob(
                scan.volume.voxels, b, threshold_hu, scan.spacing, params, params.split_retry_core_fraction
            )
            sized = [c for c in cores if blob_reject_reason(c, limits, params) is None]
    if not sized:
        return [(b, reason)]
    out = [(c, _measure_sphere(c, scan, limits, params, timer)) for c in sized]
    rest = [c for c in cores if blob_reject_reason(c, limits, params) is not None]
    out.extend((c, f"part of a split blob: {blob_reject_reason(c, limits, params)}") for c in rest)
    return out


DEFAULT_PARAMS: Final = DetectionParams()
"""The settings :func:`detect_spheres` uses when given none (the library defaults, ``subvoxel``)."""


def detect_spheres(volume: Volume, params: DetectionParams = DEFAULT_PARAMS) -> DetectionResult:
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
        boxes = group_hits(flat, volume.shape) if len(flat) else []
    with timer.stage("components_s"):
        blobs = find_blobs(vox, boxes, thr_cast, spacing, params.crop_margin_mm)
    scan = _Scan(
        volume,
        spacing,
        pixel_mm=float(0.5 * (spacing[0] + spacing[1])),
        dz_mm=float(spacing[2]),
        fov_radius_mm=circular_fov_radius_mm(vox, spacing),
        estimator=centre_estimator(params.method),
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
    spheres, crowded = separate(spheres, params.min_separation_mm, metal_voxels)
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
