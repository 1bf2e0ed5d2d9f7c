"""The header pass: one ``dcmread(stop_before_pixels=True)`` per file, its slice(s) or why it was skipped.

Keeps CT Image Storage (1.2.840.10008.5.1.4.1.1.2) and Enhanced CT Image Storage
(1.2.840.10008.5.1.4.1.1.2.1) objects; skips localizers (ImageType (0008,0008) contains
``LOCALIZER``), structured reports, secondary captures, non-DICOM and truncated files.  Every
skipped file is logged with its reason and reported (:class:`SkippedFile`).

Pixel data are never read here.  pydicom stops at the Pixel Data element (7FE0,0010); the loader
then reads that element's own header (PS3.5 §7.1.2: tag, VR, 32-bit length) to know where the value
starts and how long it is, so a truncated file is refused before any decoding, and the pixel pass
(:mod:`registration.dicom.pixels`) hands pydicom's decoder a file positioned at the value.
"""

from __future__ import annotations

import functools
import logging
import math
import os
import struct
from dataclasses import dataclass
from pathlib import Path
from typing import Any, BinaryIO, Final

from pydicom import dcmread
from pydicom.datadict import tag_for_keyword
from pydicom.dataset import Dataset
from pydicom.errors import InvalidDicomError
from pydicom.uid import UID

from registration.dicom.errors import NotRegularFileError
from registration.dicom.files import open_regular

log = logging.getLogger(__name__)

CT_IMAGE_STORAGE: Final = "1.2.840.10008.5.1.4.1.1.2"
ENHANCED_CT_IMAGE_STORAGE: Final = "1.2.840.10008.5.1.4.1.1.2.1"
MEDIA_STORAGE_DIRECTORY_STORAGE: Final = "1.2.840.10008.1.3.10"
"""SOP class of a DICOMDIR (PS3.4 Annex F)."""

CT_SOP_CLASSES: Final = frozenset({CT_IMAGE_STORAGE, ENHANCED_CT_IMAGE_STORAGE})

TEMP_FILE_SUFFIXES: Final = (".part",)
"""Names the O-arm simulator / exporters use while a file is still being written (then ``os.replace``)."""

HEADER_DEFER_SIZE_BYTES: Final = 4096
"""Values larger than this are not read in the header pass (only a big private blob is that large in
a CT header; the attributes the loader uses are a few bytes each).  pydicom reads one back from the
file if it is ever asked for."""

UNDEFINED_LENGTH: Final = 0xFFFFFFFF
"""The 32-bit length of an encapsulated (compressed) Pixel Data value (PS3.5 §7.1.2)."""

_PIXEL_DATA: Final = (0x7FE0, 0x0010)
_ITEM: Final = (0xFFFE, 0xE000)
_SEQUENCE_DELIMITER: Final = (0xFFFE, 0xE0DD)


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
    of the Pixel Data (7FE0,0010) *value* in the file (native or encapsulated),
    ``pixel_vr`` its VR (``"OB"``/``"OW"``; ``""`` for implicit VR): what
    pydicom's decoder needs to decode any frame straight from the file.
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
    pixel_offset: int
    manufacturer: str = ""
    acquisition: str = ""
    pixel_vr: str = ""
    expected_slices: int | None = None
    """ImagesInAcquisition (0020,1002) when present and positive: how many slices the scanner says the
    acquisition has (a folder export with fewer is unfinished)."""


def slice_name(h: SliceHeader) -> str:
    """The file (and frame, for a multi-frame file) a message names."""
    return f"{h.path}[frame {h.frame}]" if h.n_frames > 1 else str(h.path)


class _Skip(Exception):
    def __init__(self, reason: str, series_uid: str = "", *, damaged: bool = False) -> None:
        super().__init__(reason)
        self.reason = reason
        self.series_uid = series_uid
        self.damaged = damaged


def _skip(path: Path, reason: str, series_uid: str = "", *, damaged: bool = False) -> SkippedFile:
    (log.warning if damaged else log.info)("skipping %s: %s", path, reason)
    return SkippedFile(path=path, reason=reason, series_uid=series_uid)


@dataclass(frozen=True)
class _PixelElement:
    """Where the Pixel Data value is: ``offset`` (bytes from the file start), ``length``, ``vr``."""

    offset: int
    length: int
    vr: str
    complete: bool
    """False for an encapsulated value cut before its Sequence Delimitation Item."""


def read_headers(
    path: Path, memo: dict[tuple[Any, ...], Any] | None = None
) -> list[SliceHeader] | SkippedFile:
    """Read one file's header (pydicom stops before Pixel Data); its slice(s), or why it was skipped.

    ``memo`` caches pydicom's converted values by their undecoded bytes for a whole scan (see
    :class:`_Values`); pass the same dict for every file of a folder.
    """
    if path.name.endswith(TEMP_FILE_SUFFIXES):
        return _skip(path, "temporary file still being written (*.part)")
    try:
        with open_regular(path) as f:
            ds = dcmread(f, stop_before_pixels=True, defer_size=HEADER_DEFER_SIZE_BYTES)
            file_size = os.fstat(f.fileno()).st_size
            pixels = _pixel_element(f, ds, file_size)
    except NotRegularFileError as exc:
        return _skip(path, str(exc).removeprefix(f"{path}: "), damaged=True)
    except InvalidDicomError:
        return _skip(path, "not a DICOM Part-10 file (no 'DICM' marker at byte 128)")
    except OSError as exc:
        return _skip(path, f"unreadable file ({type(exc).__name__}: {exc})", damaged=True)
    except Exception as exc:  # truncated / corrupt headers raise EOFError, struct.error, ValueError, ...
        return _skip(path, f"unreadable DICOM header ({type(exc).__name__}: {exc})", damaged=True)
    try:
        return _headers_from(path, _Values(ds, {} if memo is None else memo), pixels, file_size)
    except _Skip as s:
        return _skip(path, s.reason, s.series_uid, damaged=s.damaged)
    except Exception as exc:  # malformed values (non-numeric DS, ...) in a file we cannot trust
        return _skip(path, f"malformed header values ({type(exc).__name__}: {exc})", damaged=True)


def _pixel_element(f: BinaryIO, ds: Dataset, file_size: int) -> _PixelElement | None:
    """The Pixel Data element header at ``f``'s position (where ``stop_before_pixels`` left it), or None.

    PS3.5 §7.1.2: tag (4 bytes), then a 32-bit length (implicit VR) or a 2-byte VR, 2 reserved bytes
    and a 32-bit length (explicit VR; OB/OW always take that form).
    """
    implicit, little = ds.original_encoding
    endian = "<" if little is not False else ">"
    head = f.read(8)
    if len(head) < 8 or struct.unpack(f"{endian}HH", head[:4]) != _PIXEL_DATA:
        return None
    if implicit:
        vr, (length,) = "", struct.unpack(f"{endian}L", head[4:])
    else:
        ext = f.read(4)
        if len(ext) < 4:
            return None
        vr, (length,) = head[4:6].decode("ascii", "replace"), struct.unpack(f"{endian}L", ext)
    offset = f.tell()
    complete = length != UNDEFINED_LENGTH or _encapsulation_complete(f, offset, file_size)
    return _PixelElement(offset=offset, length=int(length), vr=vr, complete=complete)


def _encapsulation_complete(f: BinaryIO, offset: int, file_size: int) -> bool:
    """True when the items of an encapsulated value (PS3.5 §A.4) end in a Sequence Delimitation Item.

    Walks the 8-byte item headers only (tag, 32-bit length), seeking over the fragments.
    """
    pos = offset
    while pos + 8 <= file_size:
        f.seek(pos)
        group, element, length = struct.unpack("<HHL", f.read(8))
        if (group, element) == _SEQUENCE_DELIMITER:
            return True
        if (group, element) != _ITEM or length == UNDEFINED_LENGTH:
            return False
        pos += 8 + int(length)
    return False


class _Values:
    """Header values of one dataset, identical raw values converted once per scan.

    Converting an element through pydicom costs ~15 µs, ~0.5 ms for the ~30 attributes of every
    file, more than reading the file.  All but a few of them (ImagePositionPatient, SOPInstanceUID,
    InstanceNumber) carry the same bytes in every slice of a series, so the converted value is cached
    under the element's undecoded bytes, as :meth:`pydicom.dataset.Dataset.get_item` returns them
    (with tag, VR, encoding and SpecificCharacterSet): the conversion is still pydicom's, done once
    per distinct value.
    """

    def __init__(self, ds: Dataset, memo: dict[tuple[Any, ...], Any]) -> None:
        self.ds = ds
        self.memo = memo
        charset = ds.get_item(_CHARSET_TAG, keep_deferred=True)
        self.encoding_key = (ds.original_encoding, None if charset is None else repr(charset.value))

    def get(self, keyword: str) -> Any:
        """pydicom's value of the top-level attribute ``keyword`` (``None`` when absent)."""
        tag = _tag(keyword)
        elem = self.ds.get_item(tag, keep_deferred=True)
        if elem is None:
            return None
        if not isinstance(elem.value, bytes):  # already converted (or deferred: pydicom reads it back)
            return self.ds[tag].value
        key = (tag, elem.VR, self.encoding_key, elem.value)
        try:
            return self.memo[key]
        except KeyError:
            value = self.memo[key] = self.ds[tag].value
            return value


_CHARSET_TAG: Final = 0x00080005


@functools.cache
def _tag(keyword: str) -> int:
    tag = tag_for_keyword(keyword)
    if tag is None:
        raise KeyError(f"{keyword!r} is not a DICOM keyword")
    return int(tag)


def _text(ds: _Values, keyword: str) -> str:
    return "\\".join(str(v) for v in _as_list(ds.get(keyword)))


def _integer(ds: _Values, keyword: str, default: int) -> int:
    values = _as_list(ds.get(keyword))
    return int(values[0]) if values and values[0] != "" else default


def _number(ds: _Values, keyword: str, default: float) -> float:
    values = _as_list(ds.get(keyword))
    return float(values[0]) if values and values[0] != "" else default


def _check_ct_object(ds: _Values) -> tuple[str, str]:
    """``(SOPClassUID, SeriesInstanceUID)`` of a CT image object; raise :class:`_Skip` for anything else."""
    meta = getattr(ds.ds, "file_meta", None)
    sop_class = _text(ds, "SOPClassUID") or (str(meta.get("MediaStorageSOPClassUID", "")) if meta else "")
    if sop_class == MEDIA_STORAGE_DIRECTORY_STORAGE:
        raise _Skip("DICOMDIR (file-set directory, not an image)")
    series_uid = _text(ds, "SeriesInstanceUID")
    if sop_class not in CT_SOP_CLASSES:
        name = UID(sop_class).name if sop_class else "missing SOPClassUID"
        raise _Skip(f"not a CT image object (SOP class {name})", series_uid)
    image_type = [str(v).upper() for v in _as_list(ds.get("ImageType"))]
    if "LOCALIZER" in image_type:
        raise _Skip(f"localizer (ImageType {'/'.join(image_type)})", series_uid)
    if not series_uid:
        raise _Skip("no SeriesInstanceUID (0020,000E)", damaged=True)
    return sop_class, series_uid


def _check_pixel_size(
    pixels: _PixelElement | None, ds: _Values, series_uid: str, file_size: int
) -> _PixelElement:
    """The Pixel Data element, refused (:class:`_Skip`) when absent, unsized or truncated."""
    if pixels is None or not pixels.complete:  # absent, or an encapsulated value cut before its delimiter
        raise _Skip("no PixelData (7FE0,0010): not an image, or truncated", series_uid, damaged=True)
    rows, columns = _integer(ds, "Rows", 0), _integer(ds, "Columns", 0)
    bits_allocated = _integer(ds, "BitsAllocated", 0)
    if rows <= 0 or columns <= 0 or bits_allocated <= 0:
        raise _Skip(
            f"no image size (Rows {rows}, Columns {columns}, BitsAllocated {bits_allocated})", series_uid
        )
    if pixels.length != UNDEFINED_LENGTH:  # native; encapsulated data is checked by pydicom's decoder
        samples, n_frames = _integer(ds, "SamplesPerPixel", 1), _integer(ds, "NumberOfFrames", 1)
        expected = rows * columns * samples * n_frames * bits_allocated // 8
        if pixels.length < expected or pixels.length > expected + 1:  # +1: pad byte of an odd length
            raise _Skip(
                f"truncated: PixelData holds {pixels.length} bytes, expected {expected}",
                series_uid,
                damaged=True,
            )
        if pixels.offset + pixels.length > file_size:
            raise _Skip(
                f"truncated: file is {file_size} bytes, PixelData needs {pixels.offset + pixels.length}",
                series_uid,
                damaged=True,
            )
    return pixels


def _common_fields(
    path: Path, ds: _Values, sop_class: str, series_uid: str, pixels: _PixelElement
) -> dict[str, Any]:
    """The :class:`SliceHeader` fields every frame of one file shares."""
    meta = getattr(ds.ds, "file_meta", None)
    bits_allocated = _integer(ds, "BitsAllocated", 0)
    return {
        "path": path,
        "n_frames": _integer(ds, "NumberOfFrames", 1),
        "sop_class_uid": sop_class,
        "sop_instance_uid": _text(ds, "SOPInstanceUID"),
        "series_uid": series_uid,
        "study_uid": _text(ds, "StudyInstanceUID"),
        "modality": _text(ds, "Modality"),
        "series_description": _text(ds, "SeriesDescription"),
        "rows": _integer(ds, "Rows", 0),
        "columns": _integer(ds, "Columns", 0),
        "samples_per_pixel": _integer(ds, "SamplesPerPixel", 1),
        "photometric": _text(ds, "PhotometricInterpretation"),
        "bits_allocated": bits_allocated,
        "bits_stored": _integer(ds, "BitsStored", bits_allocated),
        "pixel_representation": _integer(ds, "PixelRepresentation", 0),
        "transfer_syntax_uid": str(meta.get("TransferSyntaxUID", "")) if meta else "",
        "pixel_offset": pixels.offset,
        "pixel_vr": pixels.vr,
        "expected_slices": _announced_count(ds),
        "manufacturer": " ".join(t for k in ("Manufacturer", "ManufacturerModelName") if (t := _text(ds, k))),
        "acquisition": " ".join(
            t
            for t in (
                _text(ds, "AcquisitionDate") or _text(ds, "SeriesDate"),
                _text(ds, "AcquisitionTime") or _text(ds, "SeriesTime"),
            )
            if t
        ),
    }


def _headers_from(path: Path, ds: _Values, pixels: _PixelElement | None, file_size: int) -> list[SliceHeader]:
    sop_class, series_uid = _check_ct_object(ds)
    checked = _check_pixel_size(pixels, ds, series_uid, file_size)
    common = _common_fields(path, ds, sop_class, series_uid, checked)
    if sop_class == ENHANCED_CT_IMAGE_STORAGE:
        return _enhanced_frames(ds.ds, common)
    if common["n_frames"] != 1:
        raise _Skip(
            f"CT Image Storage with NumberOfFrames {common['n_frames']} (expected 1)",
            series_uid,
            damaged=True,
        )
    return [
        SliceHeader(
            frame=0,
            frame_of_reference_uid=_text(ds, "FrameOfReferenceUID"),
            instance_number=_opt_int(ds.get("InstanceNumber")),
            position_mm=_opt_floats(ds.get("ImagePositionPatient"), 3),
            orientation=_opt_floats(ds.get("ImageOrientationPatient"), 6),
            pixel_spacing_mm=_opt_floats(ds.get("PixelSpacing"), 2),
            slope=_number(ds, "RescaleSlope", 1.0),
            intercept=_number(ds, "RescaleIntercept", 0.0),
            **common,
        )
    ]


def _enhanced_frames(ds: Dataset, common: dict[str, Any]) -> list[SliceHeader]:
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
                **common,
            )
        )
    return out


def _announced_count(ds: _Values) -> int | None:
    """ImagesInAcquisition (0020,1002) if it is a positive integer, else None (absent or unusable)."""
    n = _opt_int(ds.get("ImagesInAcquisition"))
    return n if n is not None and n > 0 else None


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
