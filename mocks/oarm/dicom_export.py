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

    Raises
    ------
    ConfigError
        Bad ``bits_stored`` / signedness combination.
    """
    import pydicom
    from pydicom.dataset import Dataset, FileMetaDataset
    from pydicom.uid import ExplicitVRLittleEndian, generate_uid

    if bits_stored not in (12, 16):
        raise ConfigError(f"bits_stored must be 12 or 16, got {bits_stored}")
    if bits_stored == 12 and not unsigned:
        raise ConfigError(
            "bits_stored=12 holds −2048…2047 signed, which cannot store 3071 HU; use unsigned=True "
            "(RescaleIntercept −1024) or bits_stored=16"
        )
    t_start = time.perf_counter()
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    s = scan.settings
    series_uid = str(series_uid or generate_uid())
    study_uid = str(study_uid or generate_uid())
    for_uid = str(generate_uid())
    when = acquisition_time or dt.datetime.now()
    date, tm = when.strftime("%Y%m%d"), when.strftime("%H%M%S.%f")

    a = scan.image_from_voxel
    row_dir = a[:3, 0] / s.pixel_mm
    col_dir = a[:3, 1] / s.pixel_mm
    iop = [_ds(v) for v in (*row_dir, *col_dir)]
    intercept = HU_MIN if unsigned else 0.0
    hu = scan.hu
    n = hu.shape[0]
    order = list(range(n))[::-1] if reverse_order else list(range(n))
    paths: list[Path] = []
    for inst, k in enumerate(order, start=1):
        ipp = a[:3, :3] @ np.array([0.0, 0.0, float(k)]) + a[:3, 3]
        stored = _stored_pixels(hu[k], unsigned, bits_stored)
        meta = FileMetaDataset()
        meta.MediaStorageSOPClassUID = pydicom.uid.UID(CT_IMAGE_STORAGE)
        sop_uid = generate_uid()
        meta.MediaStorageSOPInstanceUID = sop_uid
        meta.TransferSyntaxUID = ExplicitVRLittleEndian
        ds = Dataset()
        ds.file_meta = meta
        ds.SpecificCharacterSet = "ISO_IR 100"
        ds.ImageType = ["ORIGINAL", "PRIMARY", "AXIAL"]
        ds.SOPClassUID = CT_IMAGE_STORAGE
        ds.SOPInstanceUID = sop_uid
        ds.StudyDate = ds.SeriesDate = ds.AcquisitionDate = ds.ContentDate = date
        ds.StudyTime = ds.SeriesTime = ds.AcquisitionTime = ds.ContentTime = tm
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
        ds.PatientName = patient_name
        ds.PatientID = patient_id
        ds.PatientBirthDate = ""
        ds.PatientSex = "O"
        ds.BodyPartExamined = "SPINE"
        ds.SliceThickness = _ds(s.slice_spacing_mm)
        ds.SpacingBetweenSlices = _ds(s.slice_spacing_mm)
        ds.KVP = _ds(s.kvp)
        ds.PatientPosition = "HFS"
        ds.StudyInstanceUID = study_uid
        ds.SeriesInstanceUID = series_uid
        ds.StudyID = "1"
        ds.SeriesNumber = series_number
        ds.AcquisitionNumber = 1
        ds.InstanceNumber = inst
        if images_in_acquisition is not False:
            ds.ImagesInAcquisition = n if images_in_acquisition is True else int(images_in_acquisition)
        ds.ImagePositionPatient = [_ds(v) for v in ipp]
        ds.ImageOrientationPatient = iop
        ds.FrameOfReferenceUID = for_uid
        ds.PositionReferenceIndicator = ""
        ds.SliceLocation = _ds(float(ipp @ np.cross(row_dir, col_dir)))
        ds.SamplesPerPixel = 1
        ds.PhotometricInterpretation = "MONOCHROME2"
        ds.Rows, ds.Columns = int(hu.shape[1]), int(hu.shape[2])
        ds.PixelSpacing = [_ds(s.pixel_mm), _ds(s.pixel_mm)]
        ds.BitsAllocated = 16
        ds.BitsStored = bits_stored
        ds.HighBit = bits_stored - 1
        ds.PixelRepresentation = 0 if unsigned else 1
        ds.RescaleIntercept = _ds(intercept)
        ds.RescaleSlope = "1"
        ds.RescaleType = "HU"
        ds.WindowCenter = "500"
        ds.WindowWidth = "3000"
        ds.PixelData = stored.tobytes()
        name = f"CT_{series_number:03d}_{inst:04d}.dcm"
        path = out / name
        import io

        buf = io.BytesIO()
        pydicom.dcmwrite(buf, ds, enforce_file_format=True)
        _write_atomic(path, buf.getvalue(), fsync)
        paths.append(path)
        if file_interval_s > 0 and inst < n:
            time.sleep(file_interval_s)  # paces a simulated slow export (not test synchronisation)
    truth_path = None
    if write_truth:
        truth = scan.truth_dict()
        truth.update(
            series_uid=series_uid,
            study_uid=study_uid,
            frame_of_reference_uid=for_uid,
            reverse_order=reverse_order,
            unsigned=unsigned,
            bits_stored=bits_stored,
        )
        truth_path = out / "truth.json"
        _write_atomic(truth_path, json.dumps(truth, indent=1).encode("utf-8"), fsync)
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


def _stored_pixels(hu: NDArray[Any], unsigned: bool, bits_stored: int) -> NDArray[Any]:
    h = np.clip(hu, HU_MIN, HU_MAX)
    if unsigned:
        return np.asarray(h - HU_MIN, dtype=np.uint16)
    return np.asarray(h, dtype=np.int16)
