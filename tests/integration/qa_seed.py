"""Write a QA series (registrations, verifications and their qa_checks rows) through the
service's own store into a data folder before the service starts (issue #21's trend and drift)."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

from service.records import (
    NewScan,
    RegistrationFigures,
    RegistrationRecord,
    SphereError,
    VerificationFigures,
    VerificationRecord,
)
from service.store import Database
from service.store.calibrations import CalibrationRecord
from service.store.qa import QaCheck, QaPose

IDENTITY = ((1.0, 0.0, 0.0, 0.0), (0.0, 1.0, 0.0, 0.0), (0.0, 0.0, 1.0, 0.0), (0.0, 0.0, 0.0, 1.0))
POSES = (
    QaPose("p1", (0.0, 0.0, 1.5708, 0.0, 0.7854, 0.0)),
    QaPose("p2", (0.0, 0.0, 1.5708, 0.0, 0.7854, 0.3)),
)


def _figures(calibration_id: int | None, face_offset_mm: float | None = None) -> RegistrationFigures:
    cal = None if calibration_id is None else {"calibration_id": calibration_id, "calibration_hash": "x"}
    return RegistrationFigures(
        fle_mm=0.1, n_expected=28, n_detected=28, n_matched=28, symmetry_margin=12, rotation_det=1.0,
        predicted_tre_mm=(0.1,), targets_image_mm=((0.0, 0.0, 0.0),), targets_source="request",
        spheres=(), provenance={"series_uid": "seed", "calibration": cal},
        face_offset_mm=face_offset_mm, face_offset_se_mm=None if face_offset_mm is None else 0.003,
    )  # fmt: skip


def seed_calibration(data_dir: Path) -> int:
    """A (refused, never active) calibration row, so records can name it."""
    db = Database.open(data_dir / "oarmreg.sqlite3")
    try:
        return db.calibrations.insert(
            CalibrationRecord(
                created_at="2026-01-01T00:00:00+00:00", status="refused", scan_ids=(), params={},
                config_hash="seed", software_version="seed", reason="seeded for a test",
            )
        )  # fmt: skip
    finally:
        db.close()


def seed_qa_series(
    data_dir: Path,
    means_mm: Sequence[float],
    *,
    protocol: str = "weekly",
    calibration_id: int | None = None,
    fre_mm: float = 0.2,
    gate_mm: float = 1.0,
    face_offset_mm: float | None = None,
) -> tuple[int, list[int]]:
    """One accepted registration (FRE ``fre_mm``, made under ``calibration_id``) and one QA check
    per mean, poses alternating; returns the registration id and the verification ids, oldest first."""
    db = Database.open(data_dir / "oarmreg.sqlite3")
    try:
        pid = p.id if (p := db.qa.find_by_name(protocol)) else db.qa.insert_protocol(protocol, "", POSES)
        n = len(db.verifications.list(1000))
        sid, _ = db.scans.upsert(
            NewScan(series_uid=f"1.2.826.0.1.{n}.{len(means_mm)}", folder="/seed", status="complete")
        )
        rid = db.registrations.insert(
            RegistrationRecord(
                created_at=f"2026-01-01T00:{n % 60:02d}:00+00:00", status="accepted", config_hash="seed",
                software_version="seed", scan_id=sid, image_from_robot=IDENTITY, fre_mm=fre_mm,
                figures=_figures(calibration_id, face_offset_mm),
            ),
            make_current=False,
        )  # fmt: skip
        vids: list[int] = []
        for i, m in enumerate(means_mm):
            vid = db.verifications.insert(
                VerificationRecord(
                    created_at=f"2026-01-02T{(n + i) // 60 % 24:02d}:{(n + i) % 60:02d}:00+00:00",
                    registration_id=rid, scan_id=sid, series_uid="seed", passed=m * 2 <= gate_mm,
                    mean_mm=m, rms_mm=m, max_mm=m * 2,
                    figures=VerificationFigures(
                        errors=(SphereError(sphere="+x-r0c0", robot_index=0, error_mm=m),), n_expected=28,
                        n_detected=28, n_matched=1, max_verification_error_mm=gate_mm,
                    ),
                    config_hash="seed", software_version="seed",
                )
            )  # fmt: skip
            db.qa.insert_check(QaCheck(vid, pid, POSES[i % 2].name))
            vids.append(vid)
        return rid, vids
    finally:
        db.close()
