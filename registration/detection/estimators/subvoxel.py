"""The ``subvoxel`` estimator: the intensity-weighted 3-D centroid on the raw volume.

The detection's own centroid (:mod:`registration.detection.centroid`), edge-refined, with its
slice coordinate from the quadratic through the weights' per-slice sums
(:func:`~registration.detection.centroid.axial_profile_centre`); the slice circles are only its
cross-check.  The default of :class:`~registration.detection.params.DetectionParams` and the peer
every other estimator is measured against (``docs/validation.md``).
"""

from __future__ import annotations

from registration.arrays import F64
from registration.detection.centroid import axial_profile_centre
from registration.detection.estimators.base import MeasuredSphere


class SubvoxelEstimator:
    """``prepare``: the centroid with its profile's slice coordinate; ``estimate``: that centre."""

    circles_are_the_measurement = False

    def prepare(self, sphere: MeasuredSphere) -> F64:
        return axial_profile_centre(
            sphere.vox, sphere.centre_ijk, sphere.spacing, sphere.params, sphere.support
        )

    def estimate(self, prepared: F64) -> tuple[F64 | None, str]:
        return prepared, ""


ESTIMATOR = SubvoxelEstimator()
