"""Moved to :mod:`registration.detection.estimators.sphere_fit`.

This old path re-exports its public names for one release (``CHANGELOG.md``, "Unreleased"):
import from the new place."""

from registration.detection.estimators.sphere_fit import (
    SMALL_R_MM,
    SQRT2,
    SQRT2PI,
    FitParams,
    SphereFit,
    blurred_ball,
    fit_sphere_model,
)

__all__ = [
    "SMALL_R_MM",
    "SQRT2",
    "SQRT2PI",
    "FitParams",
    "SphereFit",
    "blurred_ball",
    "fit_sphere_model",
]
