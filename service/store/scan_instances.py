"""The ``scan_instances`` table: what a DICOM Spatial Registration object references of a scan.

Per SeriesInstanceUID (0020,000E): the patient / study attributes the SRO copies (PS3.3 A.39.1,
Patient and General Study modules), the Study / Frame of Reference UIDs and the SOP Class /
Instance UIDs of every slice in slice order (Common Instance Reference module).  Written when a
series is recorded complete (folder or C-STORE), read by ``GET /registrations/{id}/dicom``.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

from service.store.base import Connection, dumps, loads, utc_now

SRO_PATIENT_STUDY_KEYS = (
    "PatientName", "PatientID", "PatientBirthDate", "PatientSex", "StudyDate", "StudyTime",
    "ReferringPhysicianName", "StudyID", "AccessionNumber", "Laterality", "PositionReferenceIndicator",
)  # fmt: skip


@dataclass(frozen=True)
class ScanInstances:
    """The headers of one series that an SRO needs (JSON-ready strings)."""

    series_uid: str
    study_uid: str
    frame_of_reference_uid: str
    sop_class_uids: tuple[str, ...]
    sop_instance_uids: tuple[str, ...]
    attributes: dict[str, str] = field(default_factory=dict)
    """Patient / study attributes by keyword (:data:`SRO_PATIENT_STUDY_KEYS`), present ones only."""

    def to_json(self) -> dict[str, Any]:
        return {
            "study_uid": self.study_uid,
            "frame_of_reference_uid": self.frame_of_reference_uid,
            "sop_class_uids": list(self.sop_class_uids),
            "sop_instance_uids": list(self.sop_instance_uids),
            "attributes": dict(self.attributes),
        }


class ScanInstanceStore:
    def __init__(self, db: Connection) -> None:
        self._db = db

    def put(self, inst: ScanInstances) -> None:
        with self._db.transaction() as c:
            c.execute(
                "INSERT INTO scan_instances (series_uid, headers_json, updated_at) VALUES (?, ?, ?) "
                "ON CONFLICT(series_uid) DO UPDATE SET headers_json = excluded.headers_json, "
                "updated_at = excluded.updated_at",
                (inst.series_uid, dumps(inst.to_json()), utc_now()),
            )

    def get(self, series_uid: str) -> ScanInstances | None:
        rows = self._db.query("SELECT headers_json FROM scan_instances WHERE series_uid = ?", (series_uid,))
        if not rows:
            return None
        d = loads(rows[0]["headers_json"])
        return ScanInstances(
            series_uid=series_uid,
            study_uid=str(d["study_uid"]),
            frame_of_reference_uid=str(d["frame_of_reference_uid"]),
            sop_class_uids=tuple(str(v) for v in d["sop_class_uids"]),
            sop_instance_uids=tuple(str(v) for v in d["sop_instance_uids"]),
            attributes={str(k): str(v) for k, v in d.get("attributes", {}).items()},
        )
