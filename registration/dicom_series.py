"""Load one CT series from a folder or a DICOMDIR file-set into a :class:`~registration.volume.Volume`.

The loader is the one I/O edge of :mod:`registration` (design.md §3,
research/image-side.md §1.2):

1. **Find files.**  A folder is walked recursively; a ``DICOMDIR`` (or a folder
   holding one at its root) is read as a File-set with
   :class:`pydicom.fileset.FileSet`.  Temporary files (``*.part``, written by
   the exporter before an atomic rename) are skipped.
2. **Read headers** (one pass, native pixel data never read): every file is
   parsed once by ``pydicom.dcmread(defer_size=...)``, which skips the large
   PixelData value and records where it starts.  Keep CT Image
   Storage (1.2.840.10008.5.1.4.1.1.2) and Enhanced CT Image Storage
   (1.2.840.10008.5.1.4.1.1.2.1) objects; skip localizers (ImageType
   (0008,0008) contains ``LOCALIZER``), structured reports, secondary
   captures, non-DICOM and truncated files.  Every skipped file is logged with
   its reason and reported (:class:`SkippedFile`).
3. **Group** by SeriesInstanceUID (0020,000E) and **pick** the series: the one
   named by UID, else the largest consistent (axial first) stack.
4. **Check and sort** the slices by their position along the slice normal
   ``s = IPP · (row × col)`` (never SliceThickness (0018,0050), never
   InstanceNumber (0020,0013) or file order).  Every inconsistency is refused
   with a typed error naming the files (see :func:`check_series_geometry`).
5. **Read pixels** once, straight into one preallocated array (uncompressed
   little-endian data is ``readinto`` the output from the PixelData offset
   pydicom reported; compressed transfer syntaxes are decoded by pydicom's
   pixel plugins, pylibjpeg included), and apply the Modality LUT rescale
   ``HU = RescaleSlope (0028,1053) · stored + RescaleIntercept (0028,1052)``.

Geometry (DICOM PS3.3 C.7.6.2.1.1): ImagePositionPatient (0020,0032) is the
centre of the first transmitted pixel; the first three values of
ImageOrientationPatient (0020,0037) are the direction cosines of a *row*
(direction of increasing column index i), the last three of a *column*
(increasing row index j); PixelSpacing (0028,0030) is (row spacing = distance
between rows, along j; column spacing = distance between columns, along i).
"""

from __future__ import annotations

import logging
import math
import os
import statistics
from collections import Counter, defaultdict
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Final

import numpy as np
from numpy.typing import NDArray
from pydicom import dcmread
from pydicom.datadict import tag_for_keyword
from pydicom.dataelem import RawDataElement
from pydicom.dataset import Dataset
from pydicom.errors import InvalidDicomError
from pydicom.uid import UID

from registration.errors import DicomSeriesError
from registration.volume import Volume

log = logging.getLogger(__name__)

F64 = NDArray[np.float64]

# --------------------------------------------------------------------------- constants

CT_IMAGE_STORAGE: Final = "1.2.840.10008.5.1.4.1.1.2"
ENHANCED_CT_IMAGE_STORAGE: Final = "1.2.840.10008.5.1.4.1.1.2.1"
MEDIA_STORAGE_DIRECTORY_STORAGE: Final = "1.2.840.10008.1.3.10"
"""SOP class of a DICOMDIR (PS3.4 Annex F)."""

CT_SOP_CLASSES: Final = frozenset({CT_IMAGE_STORAGE, ENHANCED_CT_IMAGE_STORAGE})

NATIVE_LITTLE_ENDIAN_SYNTAXES: Final = frozenset(
    {
        "1.2.840.10008.1.2",  # Implicit VR Little Endian
        "1.2.840.10008.1.2.1",  # Explicit VR Little Endian
    }
)
"""Transfer syntaxes whose PixelData bytes are the little-endian pixel values themselves."""

TEMP_FILE_SUFFIXES: Final = (".part",)
"""Names the O-arm simulator / exporters use while a file is still being written (then ``os.replace``)."""

HEADER_DEFER_SIZE_BYTES: Final = 4096
"""Values larger than this are not read in the header pass (only PixelData, or a big private blob, is that
large in a CT file; the header attributes the loader uses are a few bytes each)."""

ORIENTATION_TOLERANCE: Final = 1e-4
"""Max difference of any ImageOrientationPatient direction cosine between slices of one series
(dimensionless).  1e-4 rad tilts a plane by 0.0057°, i.e. 0.01 mm at 100 mm from the origin; slices of
one acquisition carry byte-identical values in practice, so anything above is a different orientation."""

ORTHONORMAL_TOLERANCE: Final = 1e-3
"""Max | |row| − 1 |, | |col| − 1 | and |row · col| accepted for ImageOrientationPatient.  Writers that
round cosines to 4–6 decimals stay well below; a hand-edited or corrupt header does not."""

PIXEL_SPACING_TOLERANCE_MM: Final = 5e-5
"""Max PixelSpacing difference between slices (mm).  A difference d moves the far edge of a 512-pixel
row by 512·d: 5e-5 mm keeps that under 0.026 mm, half the 0.05 mm localisation budget (issue #3)."""

SPACING_TOLERANCE_FRACTION: Final = 0.01
"""Max deviation of any slice step (and of any slice position from the uniform grid) from the nominal
spacing, as a fraction of it.  1 % of 0.833 mm = 0.008 mm, a sixth of the 0.05 mm localisation budget;
dicom2nifti and ITK likewise refuse (not resample) non-uniform stacks by default (image-side.md §1.2)."""

SPACING_TOLERANCE_MIN_MM: Final = 0.01
"""Floor of the spacing tolerance (mm): positions written as DS with 2 decimals are rounded by up to
0.005 mm, so one step can be off by 0.01 mm without anything being wrong.  Also the duplicate-position
threshold: two slices closer than this along the normal are the same slice."""

SHEAR_TOLERANCE_MM: Final = 0.02
"""Max sideways offset (mm) of any slice origin from the line through the first origin along the slice
normal.  5 % of a 0.415 mm pixel, 4x the 0.005 mm DS rounding; a 1° gantry tilt already gives
0.015 mm per 0.833 mm step and 2.8 mm over 192 slices."""

AXIAL_MIN_NORMAL_Z: Final = math.cos(math.radians(45.0))
"""A stack counts as axial when |n_z| of its slice normal is at least cos 45°; axial stacks are
preferred when no series UID is given (issue #3: "the largest consistent axial stack")."""

MAX_FILES_IN_MESSAGE: Final = 4
"""How many file names an error message lists before "(+N more)"."""

HEADER_TAGS: Final = [
    "SOPClassUID",
    "SOPInstanceUID",
    "Modality",
    "ImageType",
    "Manufacturer",
    "ManufacturerModelName",
    "SeriesDate",
    "SeriesTime",
    "AcquisitionDate",
    "AcquisitionTime",
    "StudyInstanceUID",
    "SeriesInstanceUID",
    "FrameOfReferenceUID",
    "SeriesDescription",
    "SeriesNumber",
    "InstanceNumber",
    "ImagePositionPatient",
    "ImageOrientationPatient",
    "PixelSpacing",
    "SamplesPerPixel",
    "PhotometricInterpretation",
    "NumberOfFrames",
    "Rows",
    "Columns",
    "BitsAllocated",
    "BitsStored",
    "PixelRepresentation",
    "RescaleIntercept",
    "RescaleSlope",
]
"""The attributes the header pass converts (through :class:`_Header`); everything else stays raw.

Measured per file on the simulator's export (2-core VM, page cache warm, under load):
``dcmread(defer_size=...)`` ~0.5 ms; converting these values through pydicom ~0.5 ms more, ~0.2 ms
with :class:`_Header`'s cache (``benchmarks/bench_loader.py``: list_series)."""


# --------------------------------------------------------------------------- errors


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


# --------------------------------------------------------------------------- data classes


@dataclass(frozen=True)
class SkippedFile:
    """A file the loader ignored, and why.

    ``series_uid`` is set when the file was readable enough to name its series.
    """

    path: Path
    reason: str
    series_uid: str = ""


@dataclass(frozen=True)
class SliceHeader:
    """What the header pass keeps of one frame (one slice) of one file.

    Single-frame CT files give one ``SliceHeader`` with ``frame = 0``; an
    Enhanced CT file gives one per frame.  ``pixel_offset`` is the byte offset
    of this frame's native little-endian pixel values in the file (from the
    ``value_tell`` of pydicom's deferred PixelData element), or ``None`` when the
    data must be decoded by pydicom (compressed, big endian, ...).
    """

    path: Path
    frame: int
    n_frames: int
    sop_class_uid: str
    sop_instance_uid: str
    series_uid: str
    frame_of_reference_uid: str
    study_uid: str
    modality: str
    series_description: str
    instance_number: int | None
    position_mm: tuple[float, ...] | None  # 3 values, LPS mm
    orientation: tuple[float, ...] | None  # 6 direction cosines
    pixel_spacing_mm: tuple[float, ...] | None  # (row spacing, column spacing) mm
    rows: int
    columns: int
    samples_per_pixel: int
    photometric: str
    bits_allocated: int
    bits_stored: int
    pixel_representation: int
    slope: float
    intercept: float
    transfer_syntax_uid: str
    pixel_offset: int | None
    manufacturer: str = ""
    acquisition: str = ""


@dataclass(frozen=True)
class SeriesSummary:
    """Header-only description of one CT series (what the folder watcher needs).

    Attributes
    ----------
    series_uid, frame_of_reference_uid, study_uid : str
        (0020,000E), (0020,0052) (the first slice's if mixed), (0020,000D).
    modality, series_description : str
    n_files : int
        Files that belong to the series (after skipping junk).
    n_slices : int
        Frames (= files for single-frame CT).
    rows, columns : int
        Most common Rows / Columns.
    pixel_spacing_mm : tuple of 2 float or None
        (row spacing, column spacing) of the first slice.
    orientation : tuple of 6 float or None
        ImageOrientationPatient of the first slice.
    slice_spacing_mm : float or None
        From the sorted positions, ``None`` unless consistent.
    first_position_mm, last_position_mm : tuple of 3 float or None
        IPP (LPS, mm) of the first and last slice along the normal, ``None`` unless consistent.
    is_axial : bool
        Slice normal within 45° of the patient z axis.
    problem : str
        ``""`` when the series is loadable, else the refusal message :func:`load_series` would raise.
    problem_type : str
        The refusal's exception class name, ``""`` when loadable.
    files : tuple of Path
        In slice order when consistent, else in path order.
    """

    series_uid: str
    frame_of_reference_uid: str
    study_uid: str
    modality: str
    series_description: str
    n_files: int
    n_slices: int
    rows: int
    columns: int
    pixel_spacing_mm: tuple[float, ...] | None
    orientation: tuple[float, ...] | None
    slice_spacing_mm: float | None
    first_position_mm: tuple[float, ...] | None
    last_position_mm: tuple[float, ...] | None
    is_axial: bool
    problem: str
    problem_type: str
    files: tuple[Path, ...]

    @property
    def consistent(self) -> bool:
        """True when :func:`load_series` would accept this series."""
        return not self.problem


@dataclass(frozen=True)
class FolderScan:
    """Result of the header pass over a folder / file-set: every CT series and every skipped file."""

    root: Path
    series: tuple[SeriesSummary, ...]
    skipped: tuple[SkippedFile, ...]


@dataclass(frozen=True, eq=False)
class SeriesGeometry:
    """A checked, sorted series: slices in increasing position along the normal, and its affine.

    Attributes
    ----------
    slices : tuple of SliceHeader
        Sorted by ``s = IPP · n`` ascending.
    image_from_voxel : ndarray, shape (4, 4), float64
        ``(i, j, k, 1)`` → LPS mm (see :func:`check_series_geometry`).
    positions_mm : ndarray, shape (n,), float64
        ``s`` of every sorted slice (mm along the normal).
    slice_spacing_mm : float
        ``(s_last − s_first) / (n − 1)``.
    """

    slices: tuple[SliceHeader, ...]
    image_from_voxel: F64
    positions_mm: F64
    slice_spacing_mm: float
    normal: F64 = field(repr=False)
    """(3,) float64: unit slice normal ``row × col`` in LPS."""


# --------------------------------------------------------------------------- public API


def load_series(path: str | Path, *, series_uid: str | None = None) -> Volume:
    """Load one CT series as a :class:`Volume` in Hounsfield units.

    Parameters
    ----------
    path : str or Path
        A folder (searched recursively), a ``DICOMDIR`` file, a folder with a
        ``DICOMDIR`` at its root (read as a File-set), or a single file.
    series_uid : str, optional
        SeriesInstanceUID (0020,000E) to load.  Without it the largest
        consistent stack is taken (axial stacks first); a tie is refused.

    Returns
    -------
    Volume
        ``voxels`` shape (n_slices, rows, columns), indexed ``[k, j, i]``,
        int16 HU when every slice's rescale is integral and the values fit,
        else float32 HU.  ``image_from_voxel`` as in
        :func:`check_series_geometry`.  ``meta`` holds ``files`` (slice order),
        ``skipped`` ((path, reason) pairs), ``slice_spacing_mm``,
        ``positions_mm``, ``instance_numbers``, ``transfer_syntax_uids``,
        ``rescale`` ((slope, intercept) set), ``manufacturer``,
        ``acquisition``, ``study_uid``, ``series_description``.

    Raises
    ------
    SeriesError
        A subclass of :class:`~registration.errors.DicomSeriesError` saying what
        was wrong, naming the files, and what to do: :class:`NoCtSeriesError`,
        :class:`SeriesNotFoundError`, :class:`AmbiguousSeriesError`, the
        geometry refusals of :func:`check_series_geometry`, :class:`PixelDataError`.
    """
    root = Path(path)
    headers, skipped = _scan(root)
    groups = _group(headers)
    chosen_uid, geometry = _select(root, groups, skipped, series_uid)
    voxels = _read_voxels(geometry.slices, chosen_uid)
    first = geometry.slices[0]
    meta: dict[str, Any] = {
        "source": str(root),
        "files": tuple(str(h.path) for h in geometry.slices),
        "frames": tuple(h.frame for h in geometry.slices),
        "skipped": tuple((str(s.path), s.reason) for s in skipped),
        "slice_spacing_mm": geometry.slice_spacing_mm,
        "positions_mm": tuple(float(s) for s in geometry.positions_mm),
        "instance_numbers": tuple(h.instance_number for h in geometry.slices),
        "transfer_syntax_uids": tuple(sorted({h.transfer_syntax_uid for h in geometry.slices})),
        "rescale": tuple(sorted({(h.slope, h.intercept) for h in geometry.slices})),
        "sop_class_uid": first.sop_class_uid,
        "modality": first.modality,
        "manufacturer": first.manufacturer,
        "acquisition": first.acquisition,
        "study_uid": first.study_uid,
        "series_description": first.series_description,
    }
    log.info(
        "loaded series %s: %d slices of %dx%d, spacing %.4f mm, %s, %d file(s) skipped",
        chosen_uid,
        voxels.shape[0],
        voxels.shape[1],
        voxels.shape[2],
        geometry.slice_spacing_mm,
        voxels.dtype,
        len(skipped),
    )
    return Volume(
        voxels=voxels,
        image_from_voxel=geometry.image_from_voxel,
        series_uid=chosen_uid,
        frame_of_reference_uid=first.frame_of_reference_uid,
        meta=meta,
    )


def list_series(path: str | Path) -> list[SeriesSummary]:
    """Header-only list of the CT series under ``path``, largest first.

    Cheap (pixel data are never read or decoded) so a folder watcher can call
    it on every change: a series is complete and loadable when
    ``summary.consistent`` and its ``n_files`` stopped changing.
    """
    return list(read_series_headers(path).series)


def read_series_headers(path: str | Path) -> FolderScan:
    """Header pass over ``path``: every CT series summarised, every skipped file with its reason."""
    root = Path(path)
    headers, skipped = _scan(root)
    groups = _group(headers)
    summaries = [_summarise(uid, hs) for uid, hs in groups.items()]
    summaries.sort(key=lambda s: (-s.n_slices, s.series_uid))
    return FolderScan(root=root, series=tuple(summaries), skipped=tuple(skipped))


def check_series_geometry(slices: Sequence[SliceHeader], series_uid: str = "") -> SeriesGeometry:
    """Check one series' slices, sort them along the slice normal and build ``image_from_voxel``.

    Rules, in the order they are checked (each raises the named error, naming the files):

    1. every slice has ImagePositionPatient (0020,0032), ImageOrientationPatient
       (0020,0037) with unit, orthogonal cosines, and PixelSpacing (0028,0030)
       → :class:`MissingGeometryError`;
    2. at least two slices → :class:`SingleSliceError`;
    3. one FrameOfReferenceUID (0020,0052) → :class:`MixedFrameOfReferenceError`;
    4. the same Rows (0028,0010), Columns (0028,0011) and PixelSpacing within
       :data:`PIXEL_SPACING_TOLERANCE_MM` → :class:`InconsistentImageSizeError`;
    5. the same orientation within :data:`ORIENTATION_TOLERANCE` → :class:`MixedOrientationError`;
    6. no two slices within :data:`SPACING_TOLERANCE_MIN_MM` along the normal
       → :class:`DuplicatePositionError`;
    7. every origin within :data:`SHEAR_TOLERANCE_MM` of the line through the
       first origin along the normal → :class:`GantryTiltError`;
    8. no step a whole multiple (≥ 2) of the nominal (median) step → :class:`MissingSliceError`;
    9. every step, and every position against the uniform grid, within
       ``max(SPACING_TOLERANCE_FRACTION · spacing, SPACING_TOLERANCE_MIN_MM)``
       → :class:`UnevenSpacingError`.

    Slices are sorted by ``s = IPP · n`` with ``n = row × col`` (the row and
    column direction cosines of (0020,0037)).  The affine maps the index
    vector ``(i, j, k, 1)`` (column, row, slice) to LPS mm::

        column 0 = row cosine    · PixelSpacing[1]   (step along i, between columns)
        column 1 = column cosine · PixelSpacing[0]   (step along j, between rows)
        column 2 = (IPP_last − IPP_first) / (n − 1)  (mean sorted IPP step, along k)
        column 3 = IPP_first                         (centre of voxel (0, 0, 0))

    Since k follows increasing ``s``, ``det(image_from_voxel[:3, :3]) > 0``.
    """
    files = [h.path for h in slices]
    _check_required(slices, series_uid)
    if len(slices) < 2:
        raise SingleSliceError(
            f"series {series_uid}: only {len(slices)} slice ({_names(files)}); a volume needs at least 2 "
            "slices to know the slice spacing. Export the whole 3D series, not a single image.",
            files=files,
            series_uid=series_uid,
        )
    _check_same(
        slices,
        lambda h: h.frame_of_reference_uid,
        MixedFrameOfReferenceError,
        "FrameOfReferenceUID (0020,0052)",
        series_uid,
        "the slices were not acquired in one coordinate system; re-export the series from the scanner "
        "(or pass the series UID of a clean series)",
    )
    _check_same(
        slices,
        lambda h: (h.rows, h.columns),
        InconsistentImageSizeError,
        "Rows x Columns (0028,0010)/(0028,0011)",
        series_uid,
        "remove the files that do not belong to this stack, or re-export the series",
    )
    _check_close(
        slices,
        lambda h: np.asarray(h.pixel_spacing_mm, dtype=np.float64),
        PIXEL_SPACING_TOLERANCE_MM,
        InconsistentImageSizeError,
        "PixelSpacing (0028,0030)",
        "mm",
        series_uid,
    )
    _check_close(
        slices,
        lambda h: np.asarray(h.orientation, dtype=np.float64),
        ORIENTATION_TOLERANCE,
        MixedOrientationError,
        "ImageOrientationPatient (0020,0037)",
        "",
        series_uid,
    )

    iop = np.asarray(slices[0].orientation, dtype=np.float64)
    row_cos = iop[:3] / np.linalg.norm(iop[:3])
    col_cos = iop[3:] / np.linalg.norm(iop[3:])
    normal = np.cross(row_cos, col_cos)
    normal /= np.linalg.norm(normal)
    ipp = np.array([h.position_mm for h in slices], dtype=np.float64)
    s_unsorted = ipp @ normal
    order = np.argsort(s_unsorted, kind="stable")
    ordered = tuple(slices[int(m)] for m in order)
    ipp = ipp[order]
    s = s_unsorted[order]
    steps = np.diff(s)

    # 6. duplicates
    dup = np.flatnonzero(steps < SPACING_TOLERANCE_MIN_MM)
    if dup.size:
        pairs = [(ordered[m], ordered[m + 1]) for m in dup]
        same_uid = [a for a, b in pairs if a.sop_instance_uid == b.sop_instance_uid]
        described = "; ".join(
            f"{_name(a)} and {_name(b)} at s = {s[m]:.3f} mm" for (a, b), m in zip(pairs, dup, strict=True)
        )
        hint = (
            " (same SOPInstanceUID: a copied file; delete the copy)"
            if same_uid
            else " (two acquisitions or reconstructions mixed into one series?)"
        )
        raise DuplicatePositionError(
            f"series {series_uid}: {dup.size} pair(s) of slices share a position along the slice normal "
            f"(closer than {SPACING_TOLERANCE_MIN_MM} mm): {described}{hint}. Expected one slice per "
            "position; remove the duplicates or re-export the series.",
            files=[p.path for pair in pairs for p in pair],
            series_uid=series_uid,
        )

    # 7. shear / gantry tilt
    d = ipp - ipp[0]
    sideways = d - np.outer(d @ normal, normal)
    offset_mm = np.linalg.norm(sideways, axis=1)
    worst = int(np.argmax(offset_mm))
    if offset_mm[worst] > SHEAR_TOLERANCE_MM:
        along = float(s[worst] - s[0])
        tilt_deg = math.degrees(math.atan2(float(offset_mm[worst]), abs(along))) if along else 90.0
        raise GantryTiltError(
            f"series {series_uid}: slice origins are not on one line along the slice normal: "
            f"{_name(ordered[worst])} is {offset_mm[worst]:.3f} mm sideways of the line through "
            f"{_name(ordered[0])} (tolerance {SHEAR_TOLERANCE_MM} mm; a gantry tilt of about {tilt_deg:.2f}° "
            "or a shifted slice). A sheared stack cannot be loaded as a rectangular volume: re-scan or "
            "re-export without gantry tilt.",
            files=[ordered[0].path, ordered[worst].path],
            series_uid=series_uid,
        )

    # 8./9. spacing
    nominal = float(statistics.median(steps.tolist()))
    tol = max(SPACING_TOLERANCE_FRACTION * nominal, SPACING_TOLERANCE_MIN_MM)
    multiples = np.rint(steps / nominal)
    gaps = np.flatnonzero((multiples >= 2) & (np.abs(steps - multiples * nominal) <= tol * multiples))
    if gaps.size:
        described = "; ".join(
            f"{int(multiples[m]) - 1} missing between {_name(ordered[m])} (s = {s[m]:.3f} mm) and "
            f"{_name(ordered[m + 1])} (s = {s[m + 1]:.3f} mm)"
            for m in gaps[:MAX_FILES_IN_MESSAGE]
        )
        more = f" (+{gaps.size - MAX_FILES_IN_MESSAGE} more gaps)" if gaps.size > MAX_FILES_IN_MESSAGE else ""
        raise MissingSliceError(
            f"series {series_uid}: slices are missing (spacing {nominal:.4f} mm): {described}{more}. "
            "The export is incomplete: wait for the transfer to finish or re-export the series.",
            files=[p for m in gaps for p in (ordered[m].path, ordered[m + 1].path)],
            series_uid=series_uid,
        )
    bad = np.flatnonzero(np.abs(steps - nominal) > tol)
    if bad.size:
        described = "; ".join(
            f"{_name(ordered[m])} → {_name(ordered[m + 1])}: {steps[m]:.4f} mm"
            for m in bad[:MAX_FILES_IN_MESSAGE]
        )
        more = f" (+{bad.size - MAX_FILES_IN_MESSAGE} more)" if bad.size > MAX_FILES_IN_MESSAGE else ""
        raise UnevenSpacingError(
            f"series {series_uid}: uneven slice spacing: expected every step to be {nominal:.4f} mm "
            f"± {tol:.4f} mm, found {described}{more}. A non-uniform stack is not resampled; re-export "
            "the series with uniform spacing.",
            files=[p for m in bad for p in (ordered[m].path, ordered[m + 1].path)],
            series_uid=series_uid,
        )
    n = len(ordered)
    spacing = float(s[-1] - s[0]) / (n - 1)
    drift = np.abs(s - (s[0] + spacing * np.arange(n)))
    worst = int(np.argmax(drift))
    if drift[worst] > tol:
        raise UnevenSpacingError(
            f"series {series_uid}: uneven slice spacing: {_name(ordered[worst])} is {drift[worst]:.4f} mm "
            f"off the uniform grid of {spacing:.4f} mm (tolerance {tol:.4f} mm). Re-export the series with "
            "uniform spacing.",
            files=[ordered[worst].path],
            series_uid=series_uid,
        )

    row_mm, col_mm = slices[0].pixel_spacing_mm or (0.0, 0.0)
    image_from_voxel = np.eye(4, dtype=np.float64)
    image_from_voxel[:3, 0] = row_cos * col_mm  # i: along a row, spacing between columns = PixelSpacing[1]
    image_from_voxel[:3, 1] = col_cos * row_mm  # j: down a column, spacing between rows = PixelSpacing[0]
    image_from_voxel[:3, 2] = (ipp[-1] - ipp[0]) / (n - 1)
    image_from_voxel[:3, 3] = ipp[0]
    return SeriesGeometry(
        slices=ordered,
        image_from_voxel=image_from_voxel,
        positions_mm=s,
        slice_spacing_mm=spacing,
        normal=normal,
    )


# --------------------------------------------------------------------------- finding and reading headers


def _scan(root: Path) -> tuple[list[SliceHeader], list[SkippedFile]]:
    """Header pass over every candidate file under ``root``."""
    paths = _candidate_files(root)
    headers: list[SliceHeader] = []
    skipped: list[SkippedFile] = []
    memo: dict[tuple[Any, ...], Any] = {}
    for p in paths:
        result = _read_headers(p, memo)
        if isinstance(result, SkippedFile):
            skipped.append(result)
        else:
            headers.extend(result)
    return headers, skipped


def _candidate_files(root: Path) -> list[Path]:
    """Files to look at: the File-set's instances when there is a DICOMDIR, else every file under ``root``."""
    if not root.exists():
        raise NoCtSeriesError(
            f"{root}: no such file or folder; expected a folder of DICOM files or a DICOMDIR.",
            files=[root],
        )
    if root.is_file():
        if root.name.upper() == "DICOMDIR":
            return _fileset_files(root)
        return [root]
    dicomdir = next((p for p in root.iterdir() if p.name.upper() == "DICOMDIR" and p.is_file()), None)
    if dicomdir is not None:
        return _fileset_files(dicomdir)
    out: list[Path] = []
    for dirpath, dirnames, filenames in os.walk(root):
        dirnames.sort()
        out.extend(Path(dirpath) / f for f in sorted(filenames))
    return out


def _fileset_files(dicomdir: Path) -> list[Path]:
    """Paths of every instance a DICOMDIR references (PS3.10 File-set)."""
    from pydicom.fileset import FileSet

    try:
        ds = dcmread(dicomdir)
        fs = FileSet(ds)
    except Exception as exc:  # pydicom raises many types for a damaged DICOMDIR
        raise NoCtSeriesError(
            f"{dicomdir}: cannot read the DICOMDIR file-set ({type(exc).__name__}: {exc}); "
            "point the loader at the folder of image files instead, or re-export the media.",
            files=[dicomdir],
        ) from exc
    paths = [Path(instance.path) for instance in fs]
    log.info("DICOMDIR %s references %d instance(s)", dicomdir, len(paths))
    return paths


def _skip(path: Path, reason: str, series_uid: str = "", *, damaged: bool = False) -> SkippedFile:
    (log.warning if damaged else log.info)("skipping %s: %s", path, reason)
    return SkippedFile(path=path, reason=reason, series_uid=series_uid)


def _read_headers(path: Path, memo: dict[tuple[Any, ...], Any]) -> list[SliceHeader] | SkippedFile:
    """Read one file's header with pydicom (PixelData deferred); return its slice(s) or why it was skipped.

    ``memo`` caches pydicom's converted values by raw bytes for the whole scan (see :class:`_Header`).
    """
    if path.name.endswith(TEMP_FILE_SUFFIXES):
        return _skip(path, "temporary file still being written (*.part)")
    try:
        with path.open("rb") as f:
            ds = dcmread(f, defer_size=HEADER_DEFER_SIZE_BYTES)
            file_size = os.fstat(f.fileno()).st_size
    except InvalidDicomError:
        return _skip(path, "not a DICOM Part-10 file (no 'DICM' marker at byte 128)")
    except OSError as exc:
        return _skip(path, f"unreadable file ({type(exc).__name__}: {exc})", damaged=True)
    except Exception as exc:  # truncated / corrupt headers raise EOFError, struct.error, ValueError, ...
        return _skip(path, f"unreadable DICOM header ({type(exc).__name__}: {exc})", damaged=True)
    try:
        return _headers_from(path, _Header(ds, memo), file_size)
    except _Skip as s:
        return _skip(path, s.reason, s.series_uid, damaged=s.damaged)
    except Exception as exc:  # malformed values (non-numeric DS, ...) in a file we cannot trust
        return _skip(path, f"malformed header values ({type(exc).__name__}: {exc})", damaged=True)


class _Skip(Exception):
    def __init__(self, reason: str, series_uid: str = "", *, damaged: bool = False) -> None:
        super().__init__(reason)
        self.reason = reason
        self.series_uid = series_uid
        self.damaged = damaged


class _Header:
    """The header values of one dataset, converted by pydicom, identical raw values converted once per scan.

    Converting a raw element through pydicom costs ~15 µs, ~0.5 ms for the ~30
    attributes of every file, more than reading the file.  All but a few of them
    (ImagePositionPatient, SOPInstanceUID, InstanceNumber) carry the same bytes in
    every slice of a series, so the converted value is cached under the raw bytes
    (with tag, VR, byte order and SpecificCharacterSet): the conversion is still
    pydicom's, done once per distinct value.
    """

    def __init__(self, ds: Dataset, memo: dict[tuple[Any, ...], Any]) -> None:
        self.ds = ds
        self.memo = memo
        charset = ds.get_item(_CHARSET_TAG, keep_deferred=True)
        self.charset_key = None if charset is None else repr(charset.value)

    def value(self, keyword: str) -> Any:
        """pydicom's value of ``keyword`` (``None`` when absent or deferred)."""
        tag = _TAG[keyword]
        elem = self.ds.get_item(tag, keep_deferred=True)
        if elem is None:
            return None
        if not isinstance(elem, RawDataElement):
            return elem.value
        if elem.value is None:  # deferred (larger than HEADER_DEFER_SIZE_BYTES): not a header value
            return None
        key = (tag, elem.VR, elem.is_little_endian, self.charset_key, elem.value)
        try:
            return self.memo[key]
        except KeyError:
            value = self.memo[key] = self.ds[tag].value
            return value

    def text(self, keyword: str) -> str:
        return "\\".join(str(v) for v in _as_list(self.value(keyword)))

    def integer(self, keyword: str, default: int) -> int:
        values = _as_list(self.value(keyword))
        return int(values[0]) if values and values[0] != "" else default

    def number(self, keyword: str, default: float) -> float:
        values = _as_list(self.value(keyword))
        return float(values[0]) if values and values[0] != "" else default


_TAG: Final = {keyword: int(tag_for_keyword(keyword) or 0) for keyword in HEADER_TAGS}
_CHARSET_TAG: Final = 0x00080005
_PIXEL_DATA_TAG: Final = 0x7FE00010


def _headers_from(path: Path, header: _Header, file_size: int) -> list[SliceHeader]:
    ds = header.ds
    meta = getattr(ds, "file_meta", None)
    sop_class = header.text("SOPClassUID") or (str(meta.get("MediaStorageSOPClassUID", "")) if meta else "")
    if sop_class == MEDIA_STORAGE_DIRECTORY_STORAGE:
        raise _Skip("DICOMDIR (file-set directory, not an image)")
    series_uid = header.text("SeriesInstanceUID")
    if sop_class not in CT_SOP_CLASSES:
        name = UID(sop_class).name if sop_class else "missing SOPClassUID"
        raise _Skip(f"not a CT image object (SOP class {name})", series_uid)
    image_type = [str(v).upper() for v in _as_list(header.value("ImageType"))]
    if "LOCALIZER" in image_type:
        raise _Skip(f"localizer (ImageType {'/'.join(image_type)})", series_uid)
    if not series_uid:
        raise _Skip("no SeriesInstanceUID (0020,000E)", damaged=True)
    pixel_data = ds.get_item(_PIXEL_DATA_TAG, keep_deferred=True)
    if pixel_data is None:  # pydicom drops an encapsulated PixelData cut before its delimiter
        raise _Skip("no PixelData (7FE0,0010): not an image, or truncated", series_uid, damaged=True)
    if not isinstance(pixel_data, RawDataElement):  # only if pydicom changed how it reads/defers
        raise _Skip("PixelData was converted by the header pass (pydicom behaviour changed?)", series_uid)

    transfer_syntax = str(meta.get("TransferSyntaxUID", "")) if meta else ""
    rows = header.integer("Rows", 0)
    columns = header.integer("Columns", 0)
    bits_allocated = header.integer("BitsAllocated", 0)
    samples = header.integer("SamplesPerPixel", 1)
    n_frames = header.integer("NumberOfFrames", 1)
    if rows <= 0 or columns <= 0 or bits_allocated <= 0:
        raise _Skip(
            f"no image size (Rows {rows}, Columns {columns}, BitsAllocated {bits_allocated})", series_uid
        )

    pixel_offset: int | None = None
    if pixel_data.length != 0xFFFFFFFF:  # native; encapsulated data is checked by pydicom's decoder
        length, value_offset = int(pixel_data.length), int(pixel_data.value_tell)
        expected = rows * columns * samples * n_frames * bits_allocated // 8
        if length < expected or length > expected + 1:  # +1: the pad byte of an odd-length value
            raise _Skip(
                f"truncated: PixelData holds {length} bytes, expected {expected}", series_uid, damaged=True
            )
        if value_offset + length > file_size:
            raise _Skip(
                f"truncated: file is {file_size} bytes, PixelData needs {value_offset + length}",
                series_uid,
                damaged=True,
            )
        if transfer_syntax in NATIVE_LITTLE_ENDIAN_SYNTAXES and bits_allocated in (8, 16, 32):
            pixel_offset = value_offset

    common: dict[str, Any] = {
        "path": path,
        "n_frames": n_frames,
        "sop_class_uid": sop_class,
        "sop_instance_uid": header.text("SOPInstanceUID"),
        "series_uid": series_uid,
        "study_uid": header.text("StudyInstanceUID"),
        "modality": header.text("Modality"),
        "series_description": header.text("SeriesDescription"),
        "rows": rows,
        "columns": columns,
        "samples_per_pixel": samples,
        "photometric": header.text("PhotometricInterpretation"),
        "bits_allocated": bits_allocated,
        "bits_stored": header.integer("BitsStored", bits_allocated),
        "pixel_representation": header.integer("PixelRepresentation", 0),
        "transfer_syntax_uid": transfer_syntax,
        "manufacturer": " ".join(
            t for k in ("Manufacturer", "ManufacturerModelName") if (t := header.text(k))
        ),
        "acquisition": " ".join(
            t
            for t in (
                header.text("AcquisitionDate") or header.text("SeriesDate"),
                header.text("AcquisitionTime") or header.text("SeriesTime"),
            )
            if t
        ),
    }
    if sop_class == ENHANCED_CT_IMAGE_STORAGE:
        frame_bytes = rows * columns * samples * bits_allocated // 8
        return _enhanced_frames(ds, common, pixel_offset, frame_bytes)
    if n_frames != 1:
        raise _Skip(f"CT Image Storage with NumberOfFrames {n_frames} (expected 1)", series_uid, damaged=True)
    return [
        SliceHeader(
            frame=0,
            frame_of_reference_uid=header.text("FrameOfReferenceUID"),
            instance_number=_opt_int(header.value("InstanceNumber")),
            position_mm=_opt_floats(header.value("ImagePositionPatient"), 3),
            orientation=_opt_floats(header.value("ImageOrientationPatient"), 6),
            pixel_spacing_mm=_opt_floats(header.value("PixelSpacing"), 2),
            slope=header.number("RescaleSlope", 1.0),
            intercept=header.number("RescaleIntercept", 0.0),
            pixel_offset=pixel_offset,
            **common,
        )
    ]


def _enhanced_frames(
    ds: Dataset, common: dict[str, Any], pixel_offset: int | None, frame_bytes: int
) -> list[SliceHeader]:
    """One :class:`SliceHeader` per frame of an Enhanced CT object (PS3.3 C.7.6.16 functional groups)."""
    shared_seq = ds.get("SharedFunctionalGroupsSequence")
    shared = shared_seq[0] if shared_seq else Dataset()
    per_frame = ds.get("PerFrameFunctionalGroupsSequence") or []
    n_frames = int(common["n_frames"])
    if len(per_frame) != n_frames:
        raise _Skip(
            f"Enhanced CT with {n_frames} frames but {len(per_frame)} PerFrameFunctionalGroupsSequence items",
            str(common["series_uid"]),
            damaged=True,
        )

    def group_value(item: Dataset, sequence: str, keyword: str) -> Any:
        for source in (item, shared):
            seq = source.get(sequence)
            if seq and keyword in seq[0]:
                return seq[0].get(keyword)
        return None

    out = []
    for f, item in enumerate(per_frame):
        slope = group_value(item, "PixelValueTransformationSequence", "RescaleSlope")
        intercept = group_value(item, "PixelValueTransformationSequence", "RescaleIntercept")
        out.append(
            SliceHeader(
                frame=f,
                frame_of_reference_uid=str(ds.get("FrameOfReferenceUID", "")),
                instance_number=_opt_int(ds.get("InstanceNumber")),
                position_mm=_opt_floats(
                    group_value(item, "PlanePositionSequence", "ImagePositionPatient"), 3
                ),
                orientation=_opt_floats(
                    group_value(item, "PlaneOrientationSequence", "ImageOrientationPatient"), 6
                ),
                pixel_spacing_mm=_opt_floats(group_value(item, "PixelMeasuresSequence", "PixelSpacing"), 2),
                slope=float(slope if slope not in (None, "") else 1.0),
                intercept=float(intercept if intercept not in (None, "") else 0.0),
                pixel_offset=None if pixel_offset is None else pixel_offset + f * frame_bytes,
                **common,
            )
        )
    return out


def _as_list(value: Any) -> list[Any]:
    if value is None or value == "":
        return []
    if isinstance(value, str | bytes):
        return [value]
    try:
        return list(value)
    except TypeError:
        return [value]


def _opt_int(value: Any) -> int | None:
    try:
        return int(value) if value not in (None, "") else None
    except (TypeError, ValueError):
        return None


def _opt_floats(value: Any, n: int) -> tuple[float, ...] | None:
    values = _as_list(value)
    if len(values) != n:
        return None
    out = tuple(float(v) for v in values)
    return out if all(math.isfinite(v) for v in out) else None


def _group(headers: Sequence[SliceHeader]) -> dict[str, list[SliceHeader]]:
    groups: dict[str, list[SliceHeader]] = defaultdict(list)
    for h in headers:
        groups[h.series_uid].append(h)
    return dict(groups)


# --------------------------------------------------------------------------- checks


def _name(h: SliceHeader) -> str:
    return f"{h.path}[frame {h.frame}]" if h.n_frames > 1 else str(h.path)


def _names(paths: Sequence[Path], limit: int = MAX_FILES_IN_MESSAGE) -> str:
    shown = ", ".join(str(p) for p in paths[:limit])
    return shown + (f" (+{len(paths) - limit} more)" if len(paths) > limit else "")


def _check_required(slices: Sequence[SliceHeader], series_uid: str) -> None:
    problems: dict[str, list[Path]] = defaultdict(list)
    for h in slices:
        if h.position_mm is None:
            problems["no valid ImagePositionPatient (0020,0032)"].append(h.path)
        if h.pixel_spacing_mm is None or min(h.pixel_spacing_mm) <= 0:
            problems["no valid PixelSpacing (0028,0030)"].append(h.path)
        if h.orientation is None:
            problems["no valid ImageOrientationPatient (0020,0037)"].append(h.path)
        else:
            iop = np.asarray(h.orientation, dtype=np.float64)
            norms = np.linalg.norm(iop.reshape(2, 3), axis=1)
            unit_err = float(np.max(np.abs(norms - 1.0)))
            if unit_err > ORTHONORMAL_TOLERANCE or abs(float(iop[:3] @ iop[3:])) > ORTHONORMAL_TOLERANCE:
                what = (
                    f"ImageOrientationPatient (0020,0037) {list(h.orientation)} is not two orthogonal "
                    "unit vectors"
                )
                problems[what].append(h.path)
        if h.samples_per_pixel != 1:
            problems[f"SamplesPerPixel {h.samples_per_pixel} (a CT slice has 1)"].append(h.path)
    if problems:
        described = "; ".join(f"{what}: {_names(paths)}" for what, paths in problems.items())
        raise MissingGeometryError(
            f"series {series_uid}: slices without usable geometry: {described}. Without position, "
            "orientation and pixel spacing the voxels cannot be placed in patient space; re-export the "
            "series from the scanner.",
            files=[p for paths in problems.values() for p in paths],
            series_uid=series_uid,
        )


def _check_same(
    slices: Sequence[SliceHeader],
    key: Any,
    error: type[SeriesError],
    what: str,
    series_uid: str,
    todo: str,
) -> None:
    by_value: dict[Any, list[Path]] = defaultdict(list)
    for h in slices:
        by_value[key(h)].append(h.path)
    if len(by_value) <= 1:
        return
    ranked = sorted(by_value.items(), key=lambda kv: -len(kv[1]))
    described = "; ".join(f"{value!s}: {len(paths)} file(s) ({_names(paths)})" for value, paths in ranked)
    minority = [p for _, paths in ranked[1:] for p in paths]
    raise error(
        f"series {series_uid}: slices disagree on {what}: expected one value, found {described}. {todo}.",
        files=minority,
        series_uid=series_uid,
    )


def _check_close(
    slices: Sequence[SliceHeader],
    key: Any,
    tol: float,
    error: type[SeriesError],
    what: str,
    unit: str,
    series_uid: str,
) -> None:
    ref = key(slices[0])
    off = [h for h in slices if float(np.max(np.abs(key(h) - ref))) > tol]
    if not off:
        return
    same = [h.path for h in slices if float(np.max(np.abs(key(h) - ref))) <= tol]
    values = sorted({tuple(np.round(key(h), 6).tolist()) for h in off})
    raise error(
        f"series {series_uid}: slices disagree on {what} (tolerance {tol:g}{unit and ' ' + unit}): "
        f"{len(same)} file(s) have {tuple(np.round(ref, 6).tolist())} ({_names(same)}), {len(off)} have "
        f"{', '.join(str(v) for v in values[:MAX_FILES_IN_MESSAGE])} ({_names([h.path for h in off])}). "
        "Expected one value for the whole stack: remove the stray files (a scout or a reformat?) or "
        "re-export the series.",
        files=[h.path for h in off],
        series_uid=series_uid,
    )


def _is_axial(orientation: Sequence[float] | None) -> bool:
    if orientation is None:
        return False
    iop = np.asarray(orientation, dtype=np.float64)
    n = np.cross(iop[:3], iop[3:])
    norm = float(np.linalg.norm(n))
    return norm > 0 and abs(float(n[2])) / norm >= AXIAL_MIN_NORMAL_Z


def _summarise(uid: str, slices: Sequence[SliceHeader]) -> SeriesSummary:
    first = slices[0]
    files_by_name = tuple(sorted({h.path for h in slices}))
    rows, columns = Counter((h.rows, h.columns) for h in slices).most_common(1)[0][0]
    problem, problem_type = "", ""
    spacing: float | None = None
    first_pos: tuple[float, ...] | None = None
    last_pos: tuple[float, ...] | None = None
    files = files_by_name
    try:
        geometry = check_series_geometry(slices, uid)
    except SeriesError as exc:
        problem, problem_type = str(exc), type(exc).__name__
    else:
        spacing = geometry.slice_spacing_mm
        first_pos = geometry.slices[0].position_mm
        last_pos = geometry.slices[-1].position_mm
        files = tuple(dict.fromkeys(h.path for h in geometry.slices))
    return SeriesSummary(
        series_uid=uid,
        frame_of_reference_uid=first.frame_of_reference_uid,
        study_uid=first.study_uid,
        modality=first.modality,
        series_description=first.series_description,
        n_files=len(files_by_name),
        n_slices=len(slices),
        rows=rows,
        columns=columns,
        pixel_spacing_mm=first.pixel_spacing_mm,
        orientation=first.orientation,
        slice_spacing_mm=spacing,
        first_position_mm=first_pos,
        last_position_mm=last_pos,
        is_axial=_is_axial(first.orientation),
        problem=problem,
        problem_type=problem_type,
        files=files,
    )


def _skipped_text(skipped: Sequence[SkippedFile], limit: int = 8) -> str:
    if not skipped:
        return "no files were skipped"
    shown = "; ".join(f"{s.path}: {s.reason}" for s in skipped[:limit])
    more = f" (+{len(skipped) - limit} more)" if len(skipped) > limit else ""
    return f"{len(skipped)} file(s) skipped: {shown}{more}"


def _checked_geometry(
    slices: Sequence[SliceHeader], series_uid: str, skipped: Sequence[SkippedFile]
) -> SeriesGeometry:
    """:func:`check_series_geometry`, naming this series' skipped files in a refusal (a truncated
    file of the series shows up as a missing slice; the user needs both facts)."""
    try:
        return check_series_geometry(slices, series_uid)
    except SeriesError as exc:
        lost = [sk for sk in skipped if sk.series_uid == series_uid]
        if not lost:
            raise
        raise type(exc)(
            f"{exc} Files of this series that could not be used: {_skipped_text(lost)}.",
            files=[*exc.files, *(sk.path for sk in lost)],
            series_uid=series_uid,
        ) from exc


def _select(
    root: Path,
    groups: dict[str, list[SliceHeader]],
    skipped: Sequence[SkippedFile],
    series_uid: str | None,
) -> tuple[str, SeriesGeometry]:
    """Pick the series to load and return its checked geometry (raising the refusal otherwise)."""
    if not groups:
        raise NoCtSeriesError(
            f"{root}: no CT image series found (CT Image Storage {CT_IMAGE_STORAGE} or Enhanced CT "
            f"{ENHANCED_CT_IMAGE_STORAGE}); {_skipped_text(skipped)}. Point the loader at the O-arm export "
            "folder (or its DICOMDIR) and check that the export finished.",
            files=[s.path for s in skipped],
        )
    available = "; ".join(f"{uid} ({len({h.path for h in hs})} files)" for uid, hs in groups.items())
    if series_uid is not None:
        if series_uid not in groups:
            lost = [s for s in skipped if s.series_uid == series_uid]
            extra = f"; its files were all skipped: {_skipped_text(lost)}" if lost else ""
            raise SeriesNotFoundError(
                f"{root}: no CT series with SeriesInstanceUID {series_uid}{extra}. Available CT series: "
                f"{available}. Pass one of these UIDs, or none to take the largest consistent stack.",
                files=[s.path for s in lost],
                series_uid=series_uid,
            )
        return series_uid, _checked_geometry(groups[series_uid], series_uid, skipped)

    good: list[tuple[str, SeriesGeometry]] = []
    bad: list[tuple[str, SeriesError]] = []
    for uid, hs in groups.items():
        try:
            good.append((uid, _checked_geometry(hs, uid, skipped)))
        except SeriesError as exc:
            bad.append((uid, exc))
    for uid, refused in bad:
        log.info("series %s is not loadable: %s", uid, refused)
    if not good:
        worst_uid, refusal = max(bad, key=lambda b: len(groups[b[0]]))
        if len(bad) == 1:
            raise refusal
        others = "; ".join(
            f"{u} ({len(groups[u])} slices): {type(e).__name__}" for u, e in bad if u != worst_uid
        )
        raise type(refusal)(
            f"{refusal} Other CT series under {root}, none loadable either: {others}.",
            files=refusal.files,
            series_uid=worst_uid,
        ) from refusal

    def rank(item: tuple[str, SeriesGeometry]) -> tuple[bool, int]:
        return (_is_axial(item[1].slices[0].orientation), len(item[1].slices))

    good.sort(key=rank, reverse=True)
    best_uid, best = good[0]
    if len(good) > 1 and rank(good[1]) == rank(good[0]):
        tied = [uid for uid, g in good if rank((uid, g)) == rank(good[0])]
        raise AmbiguousSeriesError(
            f"{root}: {len(tied)} consistent CT series with {len(best.slices)} slices each: "
            f"{', '.join(tied)}. Cannot tell which one is the scan to register; pass the series UID "
            "explicitly.",
            files=[g.slices[0].path for _, g in good[: len(tied)]],
        )
    for uid, g in good[1:]:
        log.info("also found consistent series %s (%d slices), not loaded", uid, len(g.slices))
    return best_uid, best


# --------------------------------------------------------------------------- pixels


def _output_dtype(slices: Sequence[SliceHeader]) -> type[np.int16] | type[np.float32]:
    """int16 when every slice's rescale is integral (values are range-checked while reading), else float32."""
    integral = all(float(h.slope).is_integer() and float(h.intercept).is_integer() for h in slices)
    return np.int16 if integral else np.float32


def _read_voxels(slices: Sequence[SliceHeader], series_uid: str) -> NDArray[Any]:
    """Fill one preallocated (n, rows, columns) array slice by slice, rescaled to HU."""
    n, rows, columns = len(slices), slices[0].rows, slices[0].columns
    out: NDArray[Any] = np.empty((n, rows, columns), dtype=_output_dtype(slices))
    scratch: dict[tuple[str, int], NDArray[Any]] = {}
    for k, h in enumerate(slices):
        try:
            if out.dtype == np.int16 and _direct_int16(h):
                _readinto(h, out[k])
                continue
            raw = _raw_frame(h, scratch)
        except SeriesError:
            raise
        except Exception as exc:
            raise PixelDataError(
                f"series {series_uid}: cannot read the pixel data of {_name(h)} (transfer syntax "
                f"{UID(h.transfer_syntax_uid).name}; {type(exc).__name__}: {exc}). The file is damaged or "
                "needs a decoder plugin that is not installed (pylibjpeg, pylibjpeg-libjpeg, "
                "pylibjpeg-openjpeg); re-export uncompressed or install the plugin.",
                files=[h.path],
                series_uid=series_uid,
            ) from exc
        if out.dtype == np.int16:
            slope, intercept = int(h.slope), int(h.intercept)
            ends = (int(raw.min()) * slope + intercept, int(raw.max()) * slope + intercept)
            lo, hi = min(ends), max(ends)
            if lo < -32768 or hi > 32767:
                log.info(
                    "series %s: %s has HU %d..%d outside int16; switching the volume to float32",
                    series_uid,
                    _name(h),
                    lo,
                    hi,
                )
                out = out.astype(np.float32)  # rare: one extra copy while converting
            else:  # in range: computed in int32, stored as int16 without overflow
                stored = raw if slope == 1 else raw.astype(np.int32) * slope
                np.add(stored, np.int32(intercept), out=out[k], casting="unsafe")
                continue
        np.multiply(raw, h.slope, out=out[k], casting="unsafe")
        out[k] += np.float32(h.intercept)
    return out


def _direct_int16(h: SliceHeader) -> bool:
    """The stored values are the HU values as little-endian int16: read them straight into the output."""
    return (
        h.pixel_offset is not None
        and h.bits_allocated == 16
        and h.bits_stored == 16
        and h.pixel_representation == 1
        and h.slope == 1.0
        and h.intercept == 0.0
    )


def _readinto(h: SliceHeader, target: NDArray[Any]) -> None:
    """Read one frame's native little-endian bytes from the file straight into ``target`` (C-contiguous)."""
    assert h.pixel_offset is not None
    view = target.data.cast("B")
    with h.path.open("rb", buffering=0) as f:
        f.seek(h.pixel_offset)
        got = f.readinto(view)
    if got != view.nbytes:
        raise PixelDataError(
            f"{_name(h)}: expected {view.nbytes} bytes of pixel data, read {got} (was the file truncated "
            "after the header pass?). Wait for the export to finish and load again.",
            files=[h.path],
            series_uid=h.series_uid,
        )


def _raw_frame(h: SliceHeader, scratch: dict[tuple[str, int], NDArray[Any]]) -> NDArray[Any]:
    """Stored values of one frame (rows, columns), unused high bits corrected as pydicom does."""
    if h.pixel_offset is not None:
        dtype = np.dtype(f"<{'i' if h.pixel_representation else 'u'}{h.bits_allocated // 8}")
        key = (dtype.str, h.rows * h.columns)
        buf = scratch.get(key)
        if buf is None:
            buf = scratch[key] = np.empty((h.rows, h.columns), dtype=dtype)
        _readinto(h, buf)
        arr = buf
    else:
        from pydicom.pixels.utils import pixel_array

        arr = pixel_array(os.fspath(h.path), index=h.frame if h.n_frames > 1 else None)
        if arr.ndim == 3 and h.n_frames == 1:
            arr = arr[0]
        if arr.shape != (h.rows, h.columns):
            raise PixelDataError(
                f"{_name(h)}: decoded pixel data has shape {arr.shape}, expected ({h.rows}, {h.columns}). "
                "The file is not a single-plane greyscale CT image; remove it or re-export the series.",
                files=[h.path],
                series_uid=h.series_uid,
            )
    shift = arr.dtype.itemsize * 8 - h.bits_stored
    if 0 < shift < arr.dtype.itemsize * 8 and arr.dtype.kind in "iu":
        if not arr.flags.writeable:
            arr = arr.copy()
        np.left_shift(arr, shift, out=arr)
        np.right_shift(arr, shift, out=arr)
    return arr
