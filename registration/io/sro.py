"""DICOM Spatial Registration object (SOP Class 1.2.840.10008.5.1.4.1.1.66.1) for one
robot ↔ image registration: an archival / audit artefact beside the live OpenIGTLink push
(research §4).

IOD (PS3.3 A.39.1): Patient, General Study, General Series, Spatial Registration Series
(Modality ``REG``), Frame of Reference, General Equipment, Spatial Registration, Common
Instance Reference, SOP Common.  Built by hand with pydicom (highdicom has no SRO).

Direction (PS3.3 C.20.2.1.1, tag (3006,00C6) Frame of Reference Transformation Matrix): the
matrix ``ᴬM_B`` of a Registration Sequence item maps coordinates of that item's RCS ``B``
(its Frame of Reference UID, the *source*) into the *Registered RCS* ``A``, the SRO's own
Frame of Reference UID.  Here the Registered RCS is the scan's, so

* item 1: the scan's Frame of Reference with the identity (and its images referenced);
* item 2: the robot base frame's Frame of Reference UID (minted once per installation,
  :func:`service.registrations.robot_frame.robot_frame_uid`) with ``image_from_robot @
  ROBOT_NATIVE_FROM_DICOM``.

The robot frame's DICOM coordinates (one convention, docs/slicer.md "The registration in
Slicer: one convention").  The robot base frame is not a patient frame, so the REG object
must say which coordinates of it the matrix takes.  A DICOM reader that shows the scene in
RAS (3D Slicer with SlicerRT, ``vtkSlicerDicomSroReader::LoadSpatialRegistration``) treats
*both* sides of the matrix as LPS and flips both: it shows ``F @ M @ F`` with
``F = diag(-1, -1, 1, 1)``.  The OpenIGTLink ``RobotToImage`` (robot-native points, image
RAS) is ``F @ image_from_robot``.  So the REG declares the robot frame's DICOM coordinates as
the controller's ``(-x, -y, z)`` ("LPS" whose RAS reading is the controller's own axes) and
writes ``M = image_from_robot @ F``: then ``F @ M @ F = F @ image_from_robot``, the same
transform as ``RobotToImage``, and a strict DICOM reader maps ``(-x, -y, z)`` to the same
LPS point REST's ``image_from_robot`` gives for ``(x, y, z)``.

REG objects written before this convention (their transformation comment starts with
:data:`ARCHIVED_COMMENT_PREFIX`) hold ``image_from_robot`` itself; :func:`image_from_robot_of`
reads both.

The 16 values are written row-major (PS3.3: M11 M12 M13 M14 M21 … M44) as DS strings.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from datetime import datetime

import numpy as np
import numpy.typing as npt
from pydicom.dataset import Dataset, FileMetaDataset
from pydicom.uid import PYDICOM_IMPLEMENTATION_UID, UID, ExplicitVRLittleEndian, generate_uid

from registration.arrays import F64
from registration.errors import SroError

SPATIAL_REGISTRATION_STORAGE = UID("1.2.840.10008.5.1.4.1.1.66.1")
FIDUCIAL_ALIGNMENT = ("125022", "DCM", "Fiducial Alignment")
"""CID 7100 code for a registration from fiducials (the phantom's spheres)."""
ROBOT_NATIVE_FROM_DICOM: F64 = np.diag([-1.0, -1.0, 1.0, 1.0])
"""The robot frame's DICOM coordinates ``(-x, -y, z)`` → the controller's ``(x, y, z)`` (its own inverse)."""
COMMENT_PREFIX = "robot DICOM (-x,-y,z) to image LPS mm"
"""Start of the robot item's transformation comment: the convention of the module docstring."""
ARCHIVED_COMMENT_PREFIX = "image_from_robot LPS mm"
"""Start of the comment of REG objects written before the convention: their matrix is
``image_from_robot`` (controller-native robot coordinates)."""
RIGIDITY_TOLERANCE = 1e-6
"""Max |RᵀR − I| and |det R − 1| for a matrix written as ``RIGID``."""
_PATIENT_STUDY_KEYS = (
    "PatientName", "PatientID", "PatientBirthDate", "PatientSex", "StudyInstanceUID", "StudyDate",
    "StudyTime", "ReferringPhysicianName", "StudyID", "AccessionNumber",
)  # fmt: skip


def _check_rigid(m: F64) -> None:
    if m.shape != (4, 4) or not np.all(np.isfinite(m)):
        raise SroError(f"image_from_robot must be a finite 4×4 matrix, got shape {m.shape}")
    r = m[:3, :3]
    ortho = float(np.abs(r.T @ r - np.eye(3)).max())
    det = float(np.linalg.det(r))
    last = float(np.abs(m[3] - [0, 0, 0, 1]).max())
    if ortho > RIGIDITY_TOLERANCE or abs(det - 1) > RIGIDITY_TOLERANCE or last > 0:
        raise SroError(
            f"image_from_robot is not rigid (|RᵀR−I| = {ortho:.2e}, det R = {det:.9f}, last row off by "
            f"{last:.2e}); a RIGID matrix needs an orthonormal proper rotation"
        )


def _code(value: str, scheme: str, meaning: str) -> Dataset:
    c = Dataset()
    c.CodeValue, c.CodingSchemeDesignator, c.CodeMeaning = value, scheme, meaning
    return c


def _ds(v: float) -> str:
    """A DS value (≤ 16 characters) that keeps ~1e-10 relative precision."""
    for digits in range(16, 6, -1):
        s = f"{v:.{digits}g}"
        if len(s) <= 16:
            return s
    raise SroError(f"cannot write {v!r} as a 16-character DS")


def _registration_item(for_uid: str, m: F64, comment: str, images: Sequence[Dataset] = ()) -> Dataset:
    mat = Dataset()
    mat.FrameOfReferenceTransformationMatrixType = "RIGID"
    mat.FrameOfReferenceTransformationMatrix = [_ds(float(v)) for v in m.reshape(16)]  # row-major
    mreg = Dataset()
    mreg.RegistrationTypeCodeSequence = [_code(*FIDUCIAL_ALIGNMENT)]
    mreg.FrameOfReferenceTransformationComment = comment[:64]
    mreg.MatrixSequence = [mat]
    item = Dataset()
    item.FrameOfReferenceUID = for_uid
    if images:
        item.ReferencedImageSequence = [_ref(d) for d in images]
    item.MatrixRegistrationSequence = [mreg]
    return item


def _ref(d: Dataset) -> Dataset:
    r = Dataset()
    r.ReferencedSOPClassUID, r.ReferencedSOPInstanceUID = d.SOPClassUID, d.SOPInstanceUID
    return r


def _check_scan(ct: Sequence[Dataset]) -> Dataset:
    if not ct:
        raise SroError("no CT instances given: the SRO references the scan it registers")
    first = ct[0]
    for key in ("StudyInstanceUID", "SeriesInstanceUID", "FrameOfReferenceUID"):
        values = {str(d.get(key, "")) for d in ct}
        if "" in values or len(values) != 1:
            raise SroError(f"the CT instances must share one non-empty {key}; found {sorted(values)}")
    return first


def build_spatial_registration(
    image_from_robot: npt.ArrayLike,
    ct: Sequence[Dataset],
    *,
    robot_frame_of_reference_uid: str,
    fre_mm: float,
    status: str,
    registration_id: str,
    content_datetime: datetime,
    tre_pred_mm: float | None = None,
    chain_error_mm: float | None = None,
    sop_instance_uid: str | None = None,
    series_instance_uid: str | None = None,
    manufacturer: str = "oarmreg",
    software_version: str = "",
) -> Dataset:
    """Build the SRO for one registration.

    Parameters
    ----------
    image_from_robot : (4, 4) array, float64
        Robot base frame (mm) → image, DICOM patient LPS (mm).  Must be rigid.
    ct : sequence of pydicom Dataset
        The registered scan's instances (headers suffice): one Study, Series and Frame of
        Reference.  Patient and study attributes are copied from the first.
    robot_frame_of_reference_uid : str
        The robot base frame's Frame of Reference UID (stable per installation).
    fre_mm, tre_pred_mm : float
        Fiducial registration error (RMS) and predicted TRE, written into the comments.
    chain_error_mm : float, optional
        The registration's ``predicted_chain_error_mm``, written into the
        transformation comment.
    status : str
        The registration's state (``current``, ``refused``…), written into the comments.
    content_datetime : datetime
        Content Date / Time (0008,0023) / (0008,0033): when the registration was computed.

    Returns
    -------
    pydicom.Dataset
        With ``file_meta`` (Explicit VR Little Endian); save with
        ``ds.save_as(path, enforce_file_format=True)``.
    """
    m = np.asarray(image_from_robot, dtype=np.float64)
    _check_rigid(m)
    if not math.isfinite(fre_mm) or fre_mm < 0:
        raise SroError(f"fre_mm must be a finite value >= 0, got {fre_mm}")
    first = _check_scan(ct)
    ds = Dataset()
    ds.SpecificCharacterSet = "ISO_IR 192"
    ds.SOPClassUID = SPATIAL_REGISTRATION_STORAGE
    ds.SOPInstanceUID = sop_instance_uid or generate_uid()
    for key in _PATIENT_STUDY_KEYS:  # Patient + General Study: copy (type 2: empty if absent)
        setattr(ds, key, first.get(key, ""))
    ds.Modality = "REG"  # Spatial Registration Series module
    ds.SeriesInstanceUID = series_instance_uid or generate_uid()
    ds.SeriesNumber = 9000
    ds.SeriesDescription = "robot to image registration"
    # General Series (0020,0060) Laterality is type 2C: dciodvfy errors when it is absent and only
    # warns when it is empty, so copy it from the scan, empty if the scan has none.
    ds.Laterality = first.get("Laterality", "")
    ds.FrameOfReferenceUID = first.FrameOfReferenceUID  # Registered RCS = the scan's
    ds.PositionReferenceIndicator = first.get("PositionReferenceIndicator", "")
    ds.Manufacturer = manufacturer
    if software_version:
        ds.SoftwareVersions = software_version
    ds.ContentDate = content_datetime.strftime("%Y%m%d")
    ds.ContentTime = content_datetime.strftime("%H%M%S.%f")
    ds.InstanceNumber = 1
    ds.ContentLabel = "ROBOT_REG"  # CS, ≤ 16 characters
    tre = "" if tre_pred_mm is None else f", TRE_pred {tre_pred_mm:.3g} mm"
    ds.ContentDescription = f"{registration_id} {status}: FRE {fre_mm:.3g} mm{tre}"[:64]
    chain = "" if chain_error_mm is None else f"; chain {chain_error_mm:.3g} mm"
    ds.ContentCreatorName = ""
    ds.RegistrationSequence = [
        _registration_item(str(first.FrameOfReferenceUID), np.eye(4), "scan frame (identity)", ct),
        _registration_item(
            robot_frame_of_reference_uid,
            m @ ROBOT_NATIVE_FROM_DICOM,
            f"{COMMENT_PREFIX}; FRE {fre_mm:.3g} mm; {status}{chain}",
        ),
    ]
    ser = Dataset()  # Common Instance Reference: the scan's series and instances
    ser.SeriesInstanceUID = first.SeriesInstanceUID
    ser.ReferencedInstanceSequence = [_ref(d) for d in ct]
    ds.ReferencedSeriesSequence = [ser]
    ds.file_meta = FileMetaDataset()
    ds.file_meta.MediaStorageSOPClassUID = ds.SOPClassUID
    ds.file_meta.MediaStorageSOPInstanceUID = ds.SOPInstanceUID
    ds.file_meta.TransferSyntaxUID = ExplicitVRLittleEndian
    ds.file_meta.ImplementationClassUID = PYDICOM_IMPLEMENTATION_UID
    return ds


def image_from_robot_of(ds: Dataset, robot_frame_of_reference_uid: str) -> F64:
    """Read ``image_from_robot`` (controller-native robot mm → image LPS mm) back from an SRO built by
    :func:`build_spatial_registration`, in the current convention or an archived one (module docstring).

    For the scan's own frame of reference the matrix is returned as written (the identity).
    """
    for item in ds.RegistrationSequence:
        if str(item.get("FrameOfReferenceUID", "")) == robot_frame_of_reference_uid:
            mreg = item.MatrixRegistrationSequence[0]
            values = mreg.MatrixSequence[0].FrameOfReferenceTransformationMatrix
            m = np.asarray([float(v) for v in values], dtype=np.float64).reshape(4, 4)
            comment = str(mreg.get("FrameOfReferenceTransformationComment", ""))
            return m @ ROBOT_NATIVE_FROM_DICOM if comment.startswith(COMMENT_PREFIX) else m
    raise SroError(f"the SRO has no registration item for frame of reference {robot_frame_of_reference_uid}")
