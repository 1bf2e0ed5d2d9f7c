"""The DICOM Spatial Registration object of a stored registration (``GET /registrations/{id}/dicom``).

Built by :func:`registration.io.sro.build_spatial_registration` from the registration record
(``image_from_robot``, FRE, predicted TRE, its state) and what was stored of its scan
(:mod:`service.store.scan_instances`).  The SOP Instance and Series Instance UIDs are derived
from the robot frame's UID and the registration id and time, so fetching the same
registration twice gives the same object.
"""

from __future__ import annotations

from datetime import datetime
from io import BytesIO

from pydicom.dataset import Dataset
from pydicom.uid import generate_uid

from registration import __version__
from service.errors import SroUnavailableError
from service.records import RegistrationRecord
from service.store.scan_instances import ScanInstances


def ct_headers(inst: ScanInstances) -> list[Dataset]:
    """Header-only datasets of the scan's instances, as :func:`build_spatial_registration` wants them."""
    out = []
    for cls, sop in zip(inst.sop_class_uids, inst.sop_instance_uids, strict=True):
        d = Dataset()
        d.SOPClassUID, d.SOPInstanceUID = cls, sop
        d.StudyInstanceUID, d.SeriesInstanceUID = inst.study_uid, inst.series_uid
        d.FrameOfReferenceUID = inst.frame_of_reference_uid
        out.append(d)
    if out:
        for key, value in inst.attributes.items():
            setattr(out[0], key, value)
    return out


def sro_dataset(
    rec: RegistrationRecord, inst: ScanInstances | None, *, robot_frame_uid: str, is_current: bool
) -> Dataset:
    """The SRO of ``rec``.

    Raises
    ------
    SroUnavailableError
        ``rec`` was refused (no matrix) or its scan's instance UIDs were not stored.
    SroError
        The stored matrix is not rigid (never for an accepted registration).
    """
    from registration.io.sro import build_spatial_registration

    if rec.status != "accepted" or rec.image_from_robot is None or rec.fre_mm is None:
        raise SroUnavailableError(
            f"registration {rec.id} was {rec.status} ({rec.reason or 'no matrix'}); only an accepted "
            "registration has a Spatial Registration object"
        )
    if inst is None or not inst.sop_instance_uids:
        raise SroUnavailableError(
            f"registration {rec.id}: the instance UIDs of its scan (series {rec.series_uid}) were not stored "
            "(recorded before this version, or the headers could not be read); send the scan again and "
            "register it"
        )
    tre = rec.figures.predicted_tre_mm if rec.figures is not None else ()
    seed = [robot_frame_uid, str(rec.id), rec.created_at]
    return build_spatial_registration(
        rec.image_from_robot,
        ct_headers(inst),
        robot_frame_of_reference_uid=robot_frame_uid,
        fre_mm=float(rec.fre_mm),
        status="current" if is_current else "accepted",
        registration_id=f"registration {rec.id}",
        content_datetime=datetime.fromisoformat(rec.created_at),
        tre_pred_mm=max(tre) if tre else None,
        chain_error_mm=None if rec.figures is None else rec.figures.predicted_chain_error_mm,
        sop_instance_uid=generate_uid(entropy_srcs=[*seed, "sop"]),
        series_instance_uid=generate_uid(entropy_srcs=[*seed, "series"]),
        software_version=rec.software_version or __version__,
    )


def to_bytes(ds: Dataset) -> bytes:
    """Part-10 file bytes (preamble, ``DICM``, file meta)."""
    buf = BytesIO()
    ds.save_as(buf, enforce_file_format=True)
    return buf.getvalue()
