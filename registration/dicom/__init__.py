"""Load one CT series (folder or DICOMDIR) into a :class:`~registration.imaging.volume.Volume`.

The package, in the order a load runs:

* :mod:`~registration.dicom.selection`: find files (folder walk or DICOMDIR File-set), group them by
  SeriesInstanceUID (0020,000E), choose the series;
* :mod:`~registration.dicom.headers`: the header pass (``dcmread(stop_before_pixels=True)``), one
  :class:`SliceHeader` per frame, every unusable file a :class:`SkippedFile` with its reason;
* :mod:`~registration.dicom.geometry`: one function per geometry refusal, the sort along the slice
  normal and ``image_from_voxel``;
* :mod:`~registration.dicom.pixels`: decode through pydicom's decoder into one preallocated HU array;
* :mod:`~registration.dicom.errors`: the typed refusals;
* :mod:`~registration.dicom.loader`: :func:`load_series`, :func:`list_series`, :func:`read_series_headers`.
"""

from registration.dicom.errors import (
    AmbiguousSeriesError,
    DuplicatePositionError,
    GantryTiltError,
    IncompleteSeriesError,
    InconsistentImageSizeError,
    InvalidRescaleError,
    MissingGeometryError,
    MissingSliceError,
    MixedFrameOfReferenceError,
    MixedOrientationError,
    NoCtSeriesError,
    NotRegularFileError,
    PixelDataError,
    SeriesError,
    SeriesNotFoundError,
    SingleSliceError,
    UnevenSpacingError,
    VolumeTooLargeError,
)
from registration.dicom.geometry import SeriesGeometry, check_series_geometry
from registration.dicom.headers import CT_IMAGE_STORAGE, ENHANCED_CT_IMAGE_STORAGE, SkippedFile, SliceHeader
from registration.dicom.loader import list_series, load_series, read_series_headers
from registration.dicom.selection import FolderScan, SeriesSummary

__all__ = [
    "CT_IMAGE_STORAGE",
    "ENHANCED_CT_IMAGE_STORAGE",
    "AmbiguousSeriesError",
    "DuplicatePositionError",
    "FolderScan",
    "GantryTiltError",
    "IncompleteSeriesError",
    "InconsistentImageSizeError",
    "InvalidRescaleError",
    "MissingGeometryError",
    "MissingSliceError",
    "MixedFrameOfReferenceError",
    "MixedOrientationError",
    "NoCtSeriesError",
    "NotRegularFileError",
    "PixelDataError",
    "SeriesError",
    "SeriesGeometry",
    "SeriesNotFoundError",
    "SeriesSummary",
    "SingleSliceError",
    "SkippedFile",
    "SliceHeader",
    "UnevenSpacingError",
    "VolumeTooLargeError",
    "check_series_geometry",
    "list_series",
    "load_series",
    "read_series_headers",
]
