"""The typed refusals of the DICOM loader: one class per rule, each naming the files and series involved.

Every class is a :class:`~registration.errors.DicomSeriesError` (exit code 4 in the CLI, a 4xx problem
in the API).  Messages say what was expected, what was found and what to do.
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence
from pathlib import Path
from typing import Final

from registration.errors import DicomSeriesError

MAX_FILES_IN_MESSAGE: Final = 4
"""How many file names an error message lists before "(+N more)"."""


def file_names(paths: Sequence[Path], limit: int = MAX_FILES_IN_MESSAGE) -> str:
    """``paths`` joined for a message, the first ``limit`` of them then "(+N more)"."""
    shown = ", ".join(str(p) for p in paths[:limit])
    return shown + (f" (+{len(paths) - limit} more)" if len(paths) > limit else "")


class SeriesError(DicomSeriesError):
    """A DICOM series problem naming the files and series involved.

    Attributes
    ----------
    files : tuple of Path
        The files the problem is about (possibly empty).
    series_uid : str
        The SeriesInstanceUID concerned, or ``""``.
    """

    def __init__(self, message: str, *, files: Iterable[Path] = (), series_uid: str = "") -> None:
        super().__init__(message)
        self.files: tuple[Path, ...] = tuple(files)
        self.series_uid = series_uid


class NoCtSeriesError(SeriesError):
    """The path holds no usable CT image object at all."""

    title = "No CT series found"


class SeriesNotFoundError(SeriesError):
    """The series UID asked for is not in the folder."""

    title = "Series not found"


class AmbiguousSeriesError(SeriesError):
    """Two or more equally good series; the caller must name one."""

    title = "Ambiguous DICOM series"


class SingleSliceError(SeriesError):
    """Fewer than two slices: no slice spacing, no volume."""

    title = "Single-slice series"


class MissingGeometryError(SeriesError):
    """A slice lacks ImagePositionPatient, ImageOrientationPatient or PixelSpacing, or they are invalid."""

    title = "Missing slice geometry"


class MixedFrameOfReferenceError(SeriesError):
    """Slices of one series carry different FrameOfReferenceUIDs (0020,0052)."""

    title = "Mixed frame of reference"


class InconsistentImageSizeError(SeriesError):
    """Rows, Columns or PixelSpacing differ between slices."""

    title = "Inconsistent slice size"


class MixedOrientationError(SeriesError):
    """ImageOrientationPatient differs between slices."""

    title = "Mixed slice orientation"


class DuplicatePositionError(SeriesError):
    """Two slices at the same position along the slice normal."""

    title = "Duplicate slice position"


class GantryTiltError(SeriesError):
    """Slice origins are not on one line along the slice normal (gantry tilt / shear)."""

    title = "Gantry tilt or sheared stack"


class UnevenSpacingError(SeriesError):
    """The slice steps are not uniform."""

    title = "Uneven slice spacing"


class MissingSliceError(UnevenSpacingError):
    """A step is a whole multiple of the spacing: slices are missing."""

    title = "Missing slices"


class PixelDataError(SeriesError):
    """Pixel data could not be read or decoded, or has an unsupported format."""

    title = "Unreadable pixel data"


class VolumeTooLargeError(PixelDataError):
    """Rows x Columns x slices is more than :data:`MAX_VOLUME_BYTES` (or more than the memory left)."""

    title = "Volume too large"


class InvalidRescaleError(SeriesError):
    """RescaleSlope (0028,1053) is zero or RescaleSlope / RescaleIntercept (0028,1052) is not finite."""

    title = "Invalid rescale"


class IncompleteSeriesError(MissingSliceError):
    """Fewer slices than the headers announce (ImagesInAcquisition (0020,1002)): the export is unfinished."""

    title = "Incomplete series"


class NotRegularFileError(SeriesError):
    """The path is a FIFO, device, socket, symlink loop or points outside the folder: never opened."""

    title = "Not a regular file"
