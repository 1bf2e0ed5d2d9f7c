"""Moved to :mod:`registration.detection.fov`.

This old path re-exports its public names for one release (``CHANGELOG.md``, "Unreleased"):
import from the new place."""

from registration.detection.fov import (
    BUNDLE_OFFSET_FRACTION,
    PROFILE_STEP_MM,
    DataRegion,
    first_crossing,
    line_profile,
    plateau_level,
    plateau_reaches_edge,
    sample_trilinear,
)

__all__ = [
    "BUNDLE_OFFSET_FRACTION",
    "PROFILE_STEP_MM",
    "DataRegion",
    "first_crossing",
    "line_profile",
    "plateau_level",
    "plateau_reaches_edge",
    "sample_trilinear",
]
