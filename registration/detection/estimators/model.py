"""The ``model`` estimator: a blurred, saturated ball of the nominal radius fitted to the raw voxels.

Prepares the raw voxels around the sphere (:class:`.base.SpherePatch`) and fits the model of
:mod:`.sphere_fit` from the sub-voxel centroid.  Its optimiser (``scipy.optimize``) is imported
only when a fit runs.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Final

from registration.arrays import F64
from registration.detection.estimators.base import MeasuredSphere, SpherePatch, sphere_patch
from registration.detection.estimators.sphere_fit import FitParams, fit_sphere_model

MODEL_MIN_VOXELS: Final = 27
"""The model has 6 parameters; fewer than a 3 × 3 × 3 block of voxels cannot constrain it."""


@dataclass(frozen=True, eq=False)
class ModelInput:
    """What the fit starts from: the sub-voxel centre (i, j, k), the voxels around it, the fit's settings."""

    start_ijk: F64
    patch: SpherePatch
    fit: FitParams = field(default_factory=FitParams)


class ModelEstimator:
    """``prepare``: the voxel patch around the centroid; ``estimate``: the fitted ball's centre."""

    circles_are_the_measurement = False

    def prepare(self, sphere: MeasuredSphere) -> ModelInput:
        return ModelInput(
            sphere.centre_ijk, sphere_patch(sphere.vox, sphere.centre_ijk, sphere.spacing, sphere.params)
        )

    def estimate(self, prepared: ModelInput) -> tuple[F64 | None, str]:
        """A blurred, saturated ball of the nominal radius fitted to the raw voxels, from the centroid."""
        patch = prepared.patch
        if len(patch.values_hu) < MODEL_MIN_VOXELS:
            return None, "model method: no raw voxels around the sphere to fit"
        fit = fit_sphere_model(
            patch.values_hu,
            patch.coords_mm,
            prepared.start_ijk * patch.spacing_mm,
            patch.radius_mm,
            patch.saturation_hu,
            prepared.fit,
        )
        if not fit.ok:
            return None, f"model fit failed: {fit.reason}"
        return fit.centre_mm / patch.spacing_mm, ""


ESTIMATOR = ModelEstimator()
