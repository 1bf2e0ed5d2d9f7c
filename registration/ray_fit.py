"""Moved to :mod:`registration.detection.estimators.ray_fit`.

This old path re-exports its public names for one release (``CHANGELOG.md``, "Unreleased"):
import from the new place."""

from registration.detection.estimators.ray_fit import (
    CROP_MARGIN_VOXELS,
    IRLS_WEIGHT_TOLERANCE,
    MAD_TO_SIGMA,
    N_MODEL,
    SHELL_STEP_MM,
    TUKEY_C,
    RayFit,
    RayParams,
    ray_centre,
    robust_ellipsoid_fit,
    symmetric_directions,
)

__all__ = [
    "CROP_MARGIN_VOXELS",
    "IRLS_WEIGHT_TOLERANCE",
    "MAD_TO_SIGMA",
    "N_MODEL",
    "SHELL_STEP_MM",
    "TUKEY_C",
    "RayFit",
    "RayParams",
    "ray_centre",
    "robust_ellipsoid_fit",
    "symmetric_directions",
]
