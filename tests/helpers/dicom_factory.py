"""Build small, real DICOM CT series on disk (well-formed or deliberately broken).

Used by ``tests/unit/test_dicom_*.py`` and ``benchmarks/bench_loader.py``.
Every file is a genuine Part-10 file written by pydicom, so the loader is
exercised exactly as on a scanner export; a test breaks one property (one
slice's orientation, one file's length, ...) through the per-slice overrides.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np
from pydicom.dataset import Dataset, FileMetaDataset
from pydicom.uid import (
    PYDICOM_IMPLEMENTATION_UID,
    UID,
    CTImageStorage,
    ExplicitVRLittleEndian,
    generate_uid,
)


def ct_dataset(
    stored: np.ndarray,
    *,
    position_mm: Sequence[float],
    orientation: Sequence[float] = (1.0, 0.0, 0.0, 0.0, 1.0, 0.0),
    pixel_spacing_mm: Sequence[float] = (0.5, 0.5),
    series_uid: str,
    frame_of_reference_uid: str,
    study_uid: str,
    instance_number: int = 1,
    slope: float = 1.0,
    intercept: float = 0.0,
    bits_stored: int = 16,
    image_type: Sequence[str] = ("ORIGINAL", "PRIMARY", "AXIAL"),
    sop_class_uid: str = CTImageStorage,
) -> Dataset:
    """One CT Image Storage dataset holding ``stored`` (rows, columns) int16 or uint16 values."""
    stored = np.ascontiguousarray(stored)
    if stored.dtype not in (np.int16, np.uint16):
        raise TypeError(f"stored pixels must be int16 or uint16, got {stored.dtype}")
    meta = FileMetaDataset()
    meta.MediaStorageSOPClassUID = UID(sop_class_uid)
    meta.MediaStorageSOPInstanceUID = generate_uid()
    meta.TransferSyntaxUID = ExplicitVRLittleEndian
    meta.ImplementationClassUID = PYDICOM_IMPLEMENTATION_UID
    ds = Dataset()
    ds.file_meta = meta
    ds.SOPClassUID = sop_class_uid
    ds.SOPInstanceUID = meta.MediaStorageSOPInstanceUID
    ds.Modality = "CT"
    ds.ImageType = list(image_type)
    ds.PatientName = "Phantom^Test"
    ds.PatientID = "TEST"
    ds.StudyDate = "20240101"
    ds.StudyTime = "120000"
    ds.StudyID = "1"
    ds.AccessionNumber = ""
    ds.StudyInstanceUID = study_uid
    ds.SeriesInstanceUID = series_uid
    ds.FrameOfReferenceUID = frame_of_reference_uid
    ds.SeriesNumber = 1
    ds.InstanceNumber = instance_number
    ds.ImagePositionPatient = [float(v) for v in position_mm]
    ds.ImageOrientationPatient = [float(v) for v in orientation]
    ds.PixelSpacing = [float(v) for v in pixel_spacing_mm]
    ds.SliceThickness = 99.0  # deliberately wrong: the loader must never use it
    ds.Rows, ds.Columns = int(stored.shape[0]), int(stored.shape[1])
    ds.SamplesPerPixel = 1
    ds.PhotometricInterpretation = "MONOCHROME2"
    ds.BitsAllocated = 16
    ds.BitsStored = bits_stored
    ds.HighBit = bits_stored - 1
    ds.PixelRepresentation = 1 if stored.dtype == np.int16 else 0
    ds.RescaleSlope = slope
    ds.RescaleIntercept = intercept
    ds.RescaleType = "HU"
    ds.PixelData = stored.tobytes()
    return ds


def write_series(
    folder: Path,
    stored: np.ndarray,
    *,
    origin_mm: Sequence[float] = (-10.0, -20.0, 30.0),
    orientation: Sequence[float] = (1.0, 0.0, 0.0, 0.0, 1.0, 0.0),
    pixel_spacing_mm: Sequence[float] = (0.5, 0.5),
    slice_spacing_mm: float = 0.8,
    positions_mm: Sequence[Sequence[float]] | None = None,
    series_uid: str | None = None,
    frame_of_reference_uid: str | None = None,
    study_uid: str | None = None,
    slope: float = 1.0,
    intercept: float = 0.0,
    bits_stored: int = 16,
    name_format: str = "IM{:04d}.dcm",
    file_order: Sequence[int] | None = None,
    overrides: Mapping[int, Mapping[str, Any]] | None = None,
    compress_with: str | None = None,
) -> list[Path]:
    """Write ``stored[k]`` as slice k of a CT series; return the paths in slice order.

    Slice k sits at ``origin + k * slice_spacing * n`` with n = row × col cosines,
    unless ``positions_mm`` gives every position.  ``file_order[m] = k`` names
    file m (and gives it InstanceNumber m + 1) after slice k, so a test can make
    file order and InstanceNumber run against the geometry.  ``overrides[k]``
    sets extra attributes (keyword → value) on slice k's dataset, or, with the
    key ``"stored"``, replaces its pixels.  ``compress_with`` (a transfer syntax
    UID such as ``pydicom.uid.RLELossless``) compresses every file.
    """
    folder.mkdir(parents=True, exist_ok=True)
    n = stored.shape[0]
    iop = np.asarray(orientation, dtype=np.float64)
    normal = np.cross(iop[:3], iop[3:])
    if positions_mm is None:
        positions = [np.asarray(origin_mm) + k * slice_spacing_mm * normal for k in range(n)]
    else:
        positions = [np.asarray(p, dtype=np.float64) for p in positions_mm]
    series_uid = series_uid or generate_uid()
    frame_of_reference_uid = frame_of_reference_uid or generate_uid()
    study_uid = study_uid or generate_uid()
    order = list(file_order) if file_order is not None else list(range(n))
    overrides = overrides or {}
    paths: dict[int, Path] = {}
    for m, k in enumerate(order):
        extra = dict(overrides.get(k, {}))
        pixels = extra.pop("stored", stored[k])
        ds = ct_dataset(
            pixels,
            position_mm=positions[k].tolist(),
            orientation=extra.pop("orientation", orientation),
            pixel_spacing_mm=extra.pop("pixel_spacing_mm", pixel_spacing_mm),
            series_uid=series_uid,
            frame_of_reference_uid=extra.pop("frame_of_reference_uid", frame_of_reference_uid),
            study_uid=study_uid,
            instance_number=m + 1,
            slope=slope,
            intercept=intercept,
            bits_stored=bits_stored,
        )
        for keyword, value in extra.items():
            setattr(ds, keyword, value)
        if compress_with is not None:
            ds.compress(compress_with)
        path = folder / name_format.format(m)
        ds.save_as(path, enforce_file_format=True)
        paths[k] = path
    return [paths[k] for k in sorted(paths)]


def ramp_volume(n_slices: int, rows: int = 16, columns: int = 16, *, dtype: Any = np.int16) -> np.ndarray:
    """A volume whose voxel values are all different (``1000 k + 32 j + i``, for rows, columns <= 32)."""
    k, j, i = np.meshgrid(np.arange(n_slices), np.arange(rows), np.arange(columns), indexing="ij")
    return (1000 * k + 32 * j + i).astype(dtype)


def slice_header(k: int = 0, **overrides: Any) -> Any:
    """An in-memory :class:`~registration.dicom.SliceHeader` of slice k of a good 16 x 16 axial stack.

    Slice k sits at (-10, -20, 30 + 0.8 k) mm in ``/series/IM{k:04d}.dcm``; ``overrides`` replace
    fields (``position_mm=None``, ``rows=8``, ...), so a geometry rule can be tested without files.
    """
    from registration.dicom import SliceHeader

    fields: dict[str, Any] = {
        "path": Path(f"/series/IM{k:04d}.dcm"),
        "frame": 0,
        "n_frames": 1,
        "sop_class_uid": CTImageStorage,
        "sop_instance_uid": f"1.2.3.4.{k + 1}",
        "series_uid": "1.2.3.4",
        "frame_of_reference_uid": "1.2.3.5",
        "study_uid": "1.2.3.6",
        "modality": "CT",
        "series_description": "",
        "instance_number": k + 1,
        "position_mm": (-10.0, -20.0, 30.0 + 0.8 * k),
        "orientation": (1.0, 0.0, 0.0, 0.0, 1.0, 0.0),
        "pixel_spacing_mm": (0.5, 0.5),
        "rows": 16,
        "columns": 16,
        "samples_per_pixel": 1,
        "photometric": "MONOCHROME2",
        "bits_allocated": 16,
        "bits_stored": 16,
        "pixel_representation": 1,
        "slope": 1.0,
        "intercept": 0.0,
        "transfer_syntax_uid": ExplicitVRLittleEndian,
        "pixel_offset": 0,
    }
    fields.update(overrides)
    return SliceHeader(**fields)


def slice_stack(n: int = 6, overrides: Mapping[int, Mapping[str, Any]] | None = None) -> list[Any]:
    """``n`` :func:`slice_header` slices, ``overrides[k]`` replacing fields of slice k."""
    overrides = overrides or {}
    return [slice_header(k, **dict(overrides.get(k, {}))) for k in range(n)]


def rewrite_with_other_pixels(path: Path) -> None:
    """Re-export one slice with other pixel bytes under the same name, atomically (a temporary
    file renamed over it), as a scanner re-sending changed content would."""
    import os

    import pydicom

    ds = pydicom.dcmread(path)
    px = bytearray(ds.PixelData)
    px[100:104] = b"\xff\x0f\xff\x0f"
    ds.PixelData = bytes(px)
    tmp = path.with_name(f".{path.name}.part")
    ds.save_as(tmp, enforce_file_format=True)
    os.replace(tmp, path)
