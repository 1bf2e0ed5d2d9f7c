"""The ``verifications`` table."""

from __future__ import annotations

import sqlite3
from collections.abc import Callable

from service.records import VerificationFigures, VerificationRecord
from service.store.base import Connection, dumps, loads, utc_now
from service.store.registrations import withdraw_by_verification


class VerificationStore:
    """Every verification of the current registration against a newer scan."""

    def __init__(self, db: Connection) -> None:
        self._db = db

    def insert(
        self, record: VerificationRecord, *, withdraw_reason: Callable[[int], str] | None = None
    ) -> int:
        """Store a verification (its ``id`` is ignored); returns the new id.  With ``withdraw_reason``
        (the reason, given the new id) a failed one withdraws the registration it verified, and removes
        the current pointer if it pointed there, in the same transaction (docs/safety.md)."""
        with self._db.transaction() as c:
            cur = c.execute(
                "INSERT INTO verifications (created_at, registration_id, scan_id, series_uid, passed, "
                "mean_mm, "
                "rms_mm, max_mm, figures_json, histogram_path, config_hash, software_version) "
                "VALUES (?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?)",
                (
                    record.created_at,
                    record.registration_id,
                    record.scan_id,
                    record.series_uid,
                    int(record.passed),
                    record.mean_mm,
                    record.rms_mm,
                    record.max_mm,
                    dumps(record.figures.to_json()),
                    record.histogram_path,
                    record.config_hash,
                    record.software_version,
                ),
            )
            ver_id = int(cur.lastrowid or 0)
            if withdraw_reason is not None and not record.passed:
                withdraw_by_verification(
                    c, utc_now(), record.registration_id, withdraw_reason(ver_id),
                    scan_id=record.scan_id, verification_id=ver_id,
                )  # fmt: skip
            return ver_id

    def set_histogram(self, ver_id: int, path: str) -> None:
        with self._db.transaction() as c:
            c.execute("UPDATE verifications SET histogram_path = ? WHERE id = ?", (path, ver_id))

    def get(self, ver_id: int) -> VerificationRecord | None:
        rows = self._db.query("SELECT * FROM verifications WHERE id = ?", (ver_id,))
        return _record(rows[0]) if rows else None

    def passed_for(self, registration_id: int) -> list[VerificationRecord]:
        """The verifications that passed against ``registration_id``, oldest first (its evidence)."""
        rows = self._db.query(
            "SELECT * FROM verifications WHERE registration_id = ? AND passed = 1 ORDER BY id",
            (registration_id,),
        )
        return [_record(r) for r in rows]

    def list(self, limit: int = 100, offset: int = 0) -> list[VerificationRecord]:
        """Newest first (``GET /verifications``)."""
        rows = self._db.query(
            "SELECT * FROM verifications ORDER BY id DESC LIMIT ? OFFSET ?", (limit, offset)
        )
        return [_record(r) for r in rows]


def _record(r: sqlite3.Row) -> VerificationRecord:
    return VerificationRecord(
        id=int(r["id"]),
        created_at=r["created_at"],
        registration_id=int(r["registration_id"]),
        scan_id=int(r["scan_id"]),
        series_uid=r["series_uid"],
        passed=bool(r["passed"]),
        mean_mm=float(r["mean_mm"]),
        rms_mm=float(r["rms_mm"]),
        max_mm=float(r["max_mm"]),
        figures=VerificationFigures.from_json(loads(r["figures_json"])),
        histogram_path=r["histogram_path"],
        config_hash=r["config_hash"],
        software_version=r["software_version"],
    )
