"""Write a :class:`~mocks.oarm.simulator.SimulatedScan` as a DICOM CT series.

One CT Image Storage file (SOP class 1.2.840.10008.5.1.4.1.1.2) per slice,
Explicit VR Little Endian.  Files arrive the way a real export reaches a
folder: each is written as ``.<name>.part`` and then ``os.replace``d to
``<name>.dcm``, so a watcher never sees a half-written ``.dcm``; ``truth.json``
is written (the same way) after the last slice.

Geometry tags follow PS3.3 C.7.6.2: ImagePositionPatient (0020,0032) is the
centre of the first transmitted pixel, ImageOrientationPatient (0020,0037) the
row and column direction cosines, PixelSpacing (0028,0030) is
(row spacing, column spacing).  Decimal strings are written with at most 16
characters (PS3.5 6.2), which keeps the geometry exact to ~1e-10 mm.
"""

from __future__ import annotations

import datetime as dt
import json
import logging
import os
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from mocks.oarm.simulator import HU_MAX, HU_MIN, SimulatedScan
from registration.errors import ConfigError

log = logging.getLogger(__name__)

CT_IMAGE_STORAGE = "1.2.840.10008.5.1.4.1.1.2"
MANUFACTURER = "oarmreg-sim"
"""Manufacturer (0008,0070).  The series mimics an O-arm export; the name says it is simulated."""


@dataclass(frozen=True, eq=False)
class ExportResult:
    """What :func:`write_dicom_series` wrote."""

    series_uid: str
    frame_of_reference_uid: str
    paths: list[Path] = field(default_factory=list)
    truth_path: Path | None = None
    study_uid: str = ""
    elapsed_s: float = 0.0


def _ds(value: float) -> str:
    from pydicom.valuerep import format_number_as_ds

    return str(format_number_as_ds(float(value)))


def _write_atomic(path: Path, data: bytes, fsync: bool) -> None:
    tmp = path.with_name(f".{path.name}.part")
    with open(tmp, "wb") as f:
        f.write(data)
        if fsync:
            f.flush()
            os.fsync(f.fileno())
    os.replace(tmp, path)


def write_dicom_series(
    scan: SimulatedScan,
    out_dir: Path,
    *,
    reverse_order: bool = False,
    unsigned: bool = False,
    bits_stored: int = 16,
    series_uid: str | None = None,
    write_truth: bool = True,
    file_interval_s: float = 0.0,
    fsync: bool = False,
    study_uid: str | None = None,
    patient_id: str = "SIM0001",
    patient_name: str = "Phantom^Calibration",
    series_number: int = 1,
    acquisition_time: dt.datetime | None = None,
    images_in_acquisition: int | bool = False,
    frame_of_reference_uid: str | None = None,
) -> ExportResult:
    """Write ``scan`` to ``out_dir`` as one CT Image Storage file per slice.

    Parameters
    ----------
    scan : SimulatedScan
    out_dir : Path
        Created if missing.  Files are named ``CT_<series>_<instance:04d>.dcm``.
    reverse_order : bool
        InstanceNumber (0020,0013) runs *against* the slice position (as in some vendor exports,
        research note §1.3); the files also arrive in that order.
    unsigned : bool
        PixelRepresentation 0 with RescaleIntercept −1024 (stored = HU + 1024); otherwise signed
        pixels with intercept 0.
    bits_stored : int
        12 or 16.  12 bits needs ``unsigned`` (−1024…3071 HU is 0…4095).
    series_uid : str, optional
        SeriesInstanceUID (0020,000E); generated if omitted.
    write_truth : bool
        Write ``truth.json`` beside the series after the last slice.
    file_interval_s : float
        Pause between files (a slow export trickling in; for watcher tests).
    fsync : bool
        fsync each file before renaming it into place.
    images_in_acquisition : bool or int
        Write ImagesInAcquisition (0020,1002) in every slice: ``True`` the number of slices written,
        an int that count (announce more than are written to simulate an unfinished export); the
        default ``False`` leaves it out, as many exports do (both branches of the loader's count rule).
    frame_of_reference_uid : str, optional
        FrameOfReferenceUID (0020,0052): one per O-arm placement, so scans of one calibration session
        share it (:func:`mocks.oarm.placement.placement_frame_of_reference_uid`); a new one if omitted.

    Raises
    ------
    ConfigError
        Bad ``bits_stored`` / signedness combination.
    """
    from pydicom.uid import generate_uid

    _check_pixel_format(bits_stored, unsigned)
    t_start = time.perf_counter()
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    series_uid = str(series_uid or generate_uid())
    study_uid = str(study_uid or generate_uid())
    for_uid = str(frame_of_reference_uid or generate_uid())
    when = acquisition_time or dt.datetime.now()
    n = scan.hu.shape[0]
    series = _Series(
        scan=scan,
        series_uid=series_uid,
        study_uid=study_uid,
        frame_of_reference_uid=for_uid,
        date=when.strftime("%Y%m%d"),
        time=when.strftime("%H%M%S.%f"),
        patient_id=patient_id,
        patient_name=patient_name,
        series_number=series_number,
        images_in_acquisition=_announced_count(images_in_acquisition, n),
        unsigned=unsigned,
        bits_stored=bits_stored,
    )
    order = list(range(n))[::-1] if reverse_order else list(range(n))
    paths: list[Path] = []
    for inst, k in enumerate(order, start=1):
        path = out / f"CT_{series_number:03d}_{inst:04d}.dcm"
        _write_atomic(path, _encoded(_slice_dataset(series, inst, k)), fsync)
        paths.append(path)
        if file_interval_s > 0 and inst < n:
            time.sleep(file_interval_s)  # paces a simulated slow export (not test synchronisation)
    truth_path = _write_truth(series, out, reverse_order, fsync) if write_truth else None
    elapsed = time.perf_counter() - t_start
    log.info("wrote %d CT files of series %s to %s in %.2f s", len(paths), series_uid, out, elapsed)
    return ExportResult(
        series_uid=series_uid,
        frame_of_reference_uid=for_uid,
        paths=paths,
        truth_path=truth_path,
        study_uid=study_uid,
        elapsed_s=elapsed,
    )


def _announced_count(images_in_acquisition: int | bool, n_written: int) -> int | None:
    """ImagesInAcquisition to write: ``False`` none, ``True`` the slices written, an int that."""
    if images_in_acquisition is False:
        return None
    return n_written if images_in_acquisition is True else int(images_in_acquisition)


def _check_pixel_format(bits_stored: int, unsigned: bool) -> None:
    if bits_stored not in (12, 16):
        raise ConfigError(f"bits_stored must be 12 or 16, got {bits_stored}")
    if bits_stored == 12 and not unsigned:
        raise ConfigError(
            "bits_stored=12 holds −2048…2047 signed, which cannot store 3071 HU; use unsigned=True "
            "(RescaleIntercept −1024) or bits_stored=16"
        )


@dataclass(frozen=True, eq=False)
class _Series:
    """What every slice file of one :func:`write_dicom_series` call shares."""

    scan: SimulatedScan
    series_uid: str
    study_uid: str
    frame_of_reference_uid: str
    date: str
    time: str
    patient_id: str
    patient_name: str
    series_number: int
    images_in_acquisition: int | None
    """ImagesInAcquisition (0020,1002) in every slice; ``None`` leaves it out."""
    unsigned: bool
    bits_stored: int

    @property
    def row_dir(self) -> NDArray[np.float64]:
        return np.asarray(self.scan.image_from_voxel[:3, 0] / self.scan.settings.pixel_mm)

    @property
    def col_dir(self) -> NDArray[np.float64]:
        return np.asarray(self.scan.image_from_voxel[:3, 1] / self.scan.settings.pixel_mm)


def _slice_dataset(series: _Series, inst: int, k: int) -> Any:
    """The CT Image Storage dataset of slice ``k``, written as instance ``inst``."""
    import pydicom
    from pydicom.dataset import Dataset, FileMetaDataset
    from pydicom.uid import ExplicitVRLittleEndian, generate_uid

    meta = FileMetaDataset()
    meta.MediaStorageSOPClassUID = pydicom.uid.UID(CT_IMAGE_STORAGE)
    sop_uid = generate_uid()
    meta.MediaStorageSOPInstanceUID = sop_uid
    meta.TransferSyntaxUID = ExplicitVRLittleEndian
    ds = Dataset()
    ds.file_meta = meta
    ds.SOPInstanceUID = sop_uid
    ds.InstanceNumber = inst
    _set_study_and_series(ds, series)
    _set_geometry(ds, series, k)
    _set_pixels(ds, series, k)
    return ds


def _set_study_and_series(ds: Any, series: _Series) -> None:
    """The tags every slice of the series carries alike (patient, study, series, equipment)."""
    s = series.scan.settings
    ds.SpecificCharacterSet = "ISO_IR 100"
    ds.ImageType = ["ORIGINAL", "PRIMARY", "AXIAL"]
    ds.SOPClassUID = CT_IMAGE_STORAGE
    ds.StudyDate = ds.SeriesDate = ds.AcquisitionDate = ds.ContentDate = series.date
    ds.StudyTime = ds.SeriesTime = ds.AcquisitionTime = ds.ContentTime = series.time
    ds.AccessionNumber = ""
    ds.Modality = "CT"
    # Mimics a Medtronic O-arm export (tags as commonly seen on CT exports; the real O-arm
    # conformance statement was not available, research note image-side.md §1.1).
    ds.Manufacturer = MANUFACTURER
    ds.ManufacturerModelName = "O-arm simulator"
    ds.InstitutionName = "oarmreg"
    ds.ReferringPhysicianName = ""
    ds.StudyDescription = "Robot registration phantom"
    ds.SeriesDescription = f"Simulated O-arm 3D ({s.preset_name})"
    ds.PatientName = series.patient_name
    ds.PatientID = series.patient_id
    ds.PatientBirthDate = ""
    ds.PatientSex = "O"
    ds.BodyPartExamined = "SPINE"
    ds.SliceThickness = _ds(s.slice_spacing_mm)
    ds.SpacingBetweenSlices = _ds(s.slice_spacing_mm)
    ds.KVP = _ds(s.kvp)
    ds.PatientPosition = "HFS"
    ds.StudyInstanceUID = series.study_uid
    ds.SeriesInstanceUID = series.series_uid
    ds.StudyID = "1"
    ds.SeriesNumber = series.series_number
    ds.AcquisitionNumber = 1
    if series.images_in_acquisition is not None:
        ds.ImagesInAcquisition = series.images_in_acquisition
    ds.FrameOfReferenceUID = series.frame_of_reference_uid
    ds.PositionReferenceIndicator = ""


def _set_geometry(ds: Any, series: _Series, k: int) -> None:
    """Where slice ``k`` lies (PS3.3 C.7.6.2: the first pixel's centre, the direction cosines)."""
    a = series.scan.image_from_voxel
    row_dir, col_dir = series.row_dir, series.col_dir
    ipp = a[:3, :3] @ np.array([0.0, 0.0, float(k)]) + a[:3, 3]
    ds.ImagePositionPatient = [_ds(v) for v in ipp]
    ds.ImageOrientationPatient = [_ds(v) for v in (*row_dir, *col_dir)]
    ds.SliceLocation = _ds(float(ipp @ np.cross(row_dir, col_dir)))
    ds.PixelSpacing = [_ds(series.scan.settings.pixel_mm), _ds(series.scan.settings.pixel_mm)]


def _set_pixels(ds: Any, series: _Series, k: int) -> None:
    """Slice ``k``'s pixels and how to read them (stored value → HU)."""
    hu = series.scan.hu
    ds.SamplesPerPixel = 1
    ds.PhotometricInterpretation = "MONOCHROME2"
    ds.Rows, ds.Columns = int(hu.shape[1]), int(hu.shape[2])
    ds.BitsAllocated = 16
    ds.BitsStored = series.bits_stored
    ds.HighBit = series.bits_stored - 1
    ds.PixelRepresentation = 0 if series.unsigned else 1
    ds.RescaleIntercept = _ds(HU_MIN if series.unsigned else 0.0)
    ds.RescaleSlope = "1"
    ds.RescaleType = "HU"
    ds.WindowCenter = "500"
    ds.WindowWidth = "3000"
    ds.PixelData = _stored_pixels(hu[k], series.unsigned, series.bits_stored).tobytes()


def _encoded(ds: Any) -> bytes:
    """``ds`` as a DICOM file (preamble, file meta) in memory."""
    import io

    import pydicom

    buf = io.BytesIO()
    pydicom.dcmwrite(buf, ds, enforce_file_format=True)
    return buf.getvalue()


def _write_truth(series: _Series, out: Path, reverse_order: bool, fsync: bool) -> Path:
    """``truth.json`` beside the series: the scan's truth and how the series was written."""
    truth = series.scan.truth_dict()
    truth.update(
        series_uid=series.series_uid,
        study_uid=series.study_uid,
        frame_of_reference_uid=series.frame_of_reference_uid,
        reverse_order=reverse_order,
        unsigned=series.unsigned,
        bits_stored=series.bits_stored,
    )
    truth_path = out / "truth.json"
    _write_atomic(truth_path, json.dumps(truth, indent=1).encode("utf-8"), fsync)
    return truth_path


def _stored_pixels(hu: NDArray[Any], unsigned: bool, bits_stored: int) -> NDArray[Any]:
    h = np.clip(hu, HU_MIN, HU_MAX)
    if unsigned:
        return np.asarray(h - HU_MIN, dtype=np.uint16)
    return np.asarray(h, dtype=np.int16)
