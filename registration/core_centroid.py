"""Moved to :mod:`registration.detection.estimators.core_centroid`.

This old path re-exports its public names for one release (``CHANGELOG.md``, "Unreleased"):
import from the new place."""

from registration.detection.estimators.core_centroid import (
    CoreParams,
    CoreWeights,
    core_centroid,
)

__all__ = [
    "CoreParams",
    "CoreWeights",
    "core_centroid",
]
