"""The ``rays`` estimator: the in-plane centre of the sphere's outline, robust to streaks.

For steel and titanium.  Prepares the ray fit of :mod:`.ray_fit` from the sub-voxel centroid
with its profile's slice coordinate
(:func:`~registration.detection.centroid.axial_profile_centre`) and keeps that slice coordinate
(the rays' own axial offset measured worse: the slices are coarse).  Near an edge of the imaged
region no rays are cast (rays that run into the edge have no crossing, and the lost directions
bias the fit): the edge-refined centroid stands.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from registration.arrays import F64
from registration.detection.centroid import axial_profile_centre
from registration.detection.estimators.base import MeasuredSphere
from registration.detection.estimators.ray_fit import RayFit, ray_centre


@dataclass(frozen=True, eq=False)
class RaysInput:
    """The start (i, j, k: the centroid with its profile's slice coordinate) and the ray fit from
    it, None near an edge of the imaged region (no rays cast)."""

    start_ijk: F64
    fit: RayFit | None


class RaysEstimator:
    """``prepare``: the ray fit from the profiled centroid (none near an edge); ``estimate``: its
    in-plane centre with the start's slice coordinate, or the start near an edge, or refused
    (None) if the rays did not outline a sphere."""

    circles_are_the_measurement = False

    def prepare(self, sphere: MeasuredSphere) -> RaysInput:
        p = sphere.params
        start = axial_profile_centre(sphere.vox, sphere.centre_ijk, sphere.spacing, p, sphere.support)
        if sphere.near_edge():
            return RaysInput(start, None)
        fit = ray_centre(
            sphere.vox, start, sphere.spacing, p.radius_mm, sphere.saturation_hu, p.rays, sphere.fov_radius_mm
        )
        return RaysInput(start, fit)

    def estimate(self, prepared: RaysInput) -> tuple[F64 | None, str]:
        fit, start = prepared.fit, prepared.start_ijk
        if fit is None:
            return start, ""
        c = fit.centre_ijk
        if c is None:
            return None, fit.reason
        return np.array([c[0], c[1], start[2]]), ""


ESTIMATOR = RaysEstimator()
