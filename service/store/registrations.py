"""The ``registrations`` table and the ``current_registration`` pointer."""

from __future__ import annotations

import sqlite3
from dataclasses import dataclass
from typing import cast

from service.records import (
    RegistrationFigures,
    RegistrationRecord,
    RegistrationStatus,
    floats,
    matrix4,
    points3,
)
from service.store.base import Connection, dumps, loads, utc_now


def retire_accepted(c: sqlite3.Connection, now: str, cal_id: int, *, also_withdrawn: bool) -> list[int]:
    """Mark the accepted, not yet retired registrations retired by calibration ``cal_id`` (inside the
    caller's transaction); returns their ids.  ``also_withdrawn=False`` leaves withdrawn ones as they
    are (a withdrawal of the active calibration); activation retires them too."""
    where = "status = 'accepted' AND retired_at IS NULL" + (
        "" if also_withdrawn else " AND withdrawn_at IS NULL"
    )
    ids = [int(r[0]) for r in c.execute(f"SELECT id FROM registrations WHERE {where}")]
    c.execute(
        f"UPDATE registrations SET retired_at = ?, retired_by_calibration = ? WHERE {where}", (now, cal_id)
    )
    return ids


@dataclass(frozen=True)
class DerivedWithdrawal:
    """What :meth:`RegistrationStore.withdraw_derived` withdrew."""

    verification_ids: tuple[int, ...]
    calibration_ids: tuple[int, ...]
    deactivated_calibration_id: int | None
    """The active calibration, if it was withdrawn (the nominal model is used again)."""
    retired_registration_ids: tuple[int, ...]
    """Registrations retired because they were made with that calibration's model."""


class RegistrationStore:
    """Every registration, accepted or refused, and which one is current."""

    def __init__(self, db: Connection) -> None:
        self._db = db

    def insert(self, record: RegistrationRecord, *, make_current: bool) -> int:
        """Store a registration (its ``id`` is ignored); if ``make_current``, point to it (same transaction).

        Raises
        ------
        ValueError
            ``make_current`` for a registration that was not accepted.
        """
        now = utc_now()
        if make_current and record.status != "accepted":
            raise ValueError("only an accepted registration can be made current")
        with self._db.transaction() as c:
            cur = c.execute(
                "INSERT INTO registrations (created_at, scan_id, series_uid, status, reason, problem_title, "
                "http_status, image_from_robot_json, fre_mm, figures_json, targets_image_mm_json, "
                "joints_json, "
                "joints_received_at, config_hash, software_version, duration_s) "
                "VALUES (?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?)",
                _values(record),
            )
            reg_id = int(cur.lastrowid or 0)
            if make_current:
                c.execute(
                    "INSERT INTO current_registration (singleton, registration_id, set_at) VALUES (1, ?, ?) "
                    "ON CONFLICT(singleton) DO UPDATE SET registration_id = excluded.registration_id, "
                    "set_at = excluded.set_at",
                    (reg_id, now),
                )
            return reg_id

    def withdraw_for_scan(self, scan_id: int, reason: str) -> tuple[list[int], bool]:
        """Withdraw every accepted registration of ``scan_id`` (one transaction).

        Returns the withdrawn ids and whether the current one was among them (the current pointer is
        then removed: no registration is current, every push channel says INVALID).
        """
        now = utc_now()
        with self._db.transaction() as c:
            ids = [int(r[0]) for r in c.execute(_Withdraw.SELECT, (scan_id,)).fetchall()]
            for reg_id in ids:
                c.execute(_Withdraw.UPDATE, (now, reason, reg_id))
            row = c.execute("SELECT registration_id FROM current_registration WHERE singleton = 1").fetchone()
            was_current = row is not None and int(row[0]) in ids
            if was_current:
                c.execute("DELETE FROM current_registration WHERE singleton = 1")
            return ids, was_current

    def withdraw_derived(self, scan_id: int, reason: str) -> DerivedWithdrawal:
        """Withdraw the verifications and calibrations made from ``scan_id`` (its content changed).

        If the active calibration is among them it stops being active in the same transaction: the
        nominal model is used again and every accepted registration is retired (they were made
        with the withdrawn model), so nothing is current until the next ``/register``."""
        now = utc_now()
        with self._db.transaction() as c:
            vers = [
                int(r[0])
                for r in c.execute(
                    "SELECT id FROM verifications WHERE scan_id = ? AND withdrawn_at IS NULL", (scan_id,)
                )
            ]
            c.executemany(
                "UPDATE verifications SET withdrawn_at = ?, withdrawn_reason = ? WHERE id = ?",
                [(now, reason, v) for v in vers],
            )
            cals = [
                int(r[0])
                for r in c.execute(
                    "SELECT id FROM calibrations WHERE withdrawn_at IS NULL AND EXISTS "
                    "(SELECT 1 FROM json_each(calibrations.scan_ids_json) WHERE value = ?)",
                    (scan_id,),
                )
            ]
            c.executemany(
                "UPDATE calibrations SET withdrawn_at = ?, withdrawn_reason = ? WHERE id = ?",
                [(now, reason, k) for k in cals],
            )
            active = c.execute("SELECT calibration_id FROM active_calibration WHERE singleton = 1").fetchone()
            if active is None or int(active[0]) not in cals:
                return DerivedWithdrawal(tuple(vers), tuple(cals), None, ())
            cal_id = int(active[0])
            retired = retire_accepted(c, now, cal_id, also_withdrawn=False)
            c.execute("DELETE FROM current_registration WHERE singleton = 1")
            c.execute("DELETE FROM active_calibration WHERE singleton = 1")
            return DerivedWithdrawal(tuple(vers), tuple(cals), cal_id, tuple(retired))

    def latest_withdrawn(self) -> RegistrationRecord | None:
        rows = self._db.query(
            "SELECT * FROM registrations WHERE withdrawn_at IS NOT NULL ORDER BY withdrawn_at DESC, id DESC "
            "LIMIT 1"
        )
        return _record(rows[0], self.current_id()) if rows else None

    def current_id(self) -> int | None:
        rows = self._db.query("SELECT registration_id FROM current_registration WHERE singleton = 1")
        return int(rows[0][0]) if rows else None

    def get(self, reg_id: int) -> RegistrationRecord | None:
        rows = self._db.query("SELECT * FROM registrations WHERE id = ?", (reg_id,))
        return _record(rows[0], self.current_id()) if rows else None

    def current(self) -> RegistrationRecord | None:
        """The registration the service serves (restored from disk after a restart), or None."""
        cur = self.current_id()
        return None if cur is None else self.get(cur)

    def list(self, limit: int = 100, offset: int = 0) -> list[RegistrationRecord]:
        cur = self.current_id()
        rows = self._db.query(
            "SELECT * FROM registrations ORDER BY id DESC LIMIT ? OFFSET ?", (limit, offset)
        )
        return [_record(r, cur) for r in rows]


class _Withdraw:
    """SQL of :meth:`RegistrationStore.withdraw_for_scan`."""

    SELECT = "SELECT id FROM registrations WHERE scan_id = ? AND status = 'accepted' AND withdrawn_at IS NULL"
    UPDATE = "UPDATE registrations SET withdrawn_at = ?, withdrawn_reason = ? WHERE id = ?"


def _values(r: RegistrationRecord) -> tuple[object, ...]:
    return (
        r.created_at,
        r.scan_id,
        r.series_uid,
        r.status,
        r.reason,
        r.problem_title,
        r.http_status,
        dumps(None if r.image_from_robot is None else [list(row) for row in r.image_from_robot]),
        r.fre_mm,
        dumps(None if r.figures is None else r.figures.to_json()),
        dumps(None if r.targets_image_mm is None else [list(p) for p in r.targets_image_mm]),
        dumps(None if r.joints_rad is None else list(r.joints_rad)),
        r.joints_received_at,
        r.config_hash,
        r.software_version,
        r.duration_s,
    )


def _record(r: sqlite3.Row, current_id: int | None) -> RegistrationRecord:
    matrix = loads(r["image_from_robot_json"])
    figures = loads(r["figures_json"])
    targets = loads(r["targets_image_mm_json"])
    withdrawn = r["withdrawn_at"] is not None
    return RegistrationRecord(
        id=int(r["id"]),
        created_at=r["created_at"],
        scan_id=r["scan_id"],
        series_uid=r["series_uid"],
        status=(
            "withdrawn"
            if withdrawn
            else "retired"
            if r["retired_at"] is not None
            else cast(RegistrationStatus, r["status"])
        ),
        reason=r["withdrawn_reason"] if withdrawn else r["reason"],
        withdrawn_at=r["withdrawn_at"],
        problem_title=r["problem_title"],
        http_status=r["http_status"],
        image_from_robot=None if matrix is None else matrix4(matrix),
        fre_mm=r["fre_mm"],
        figures=None if figures is None else RegistrationFigures.from_json(figures),
        targets_image_mm=None if targets is None else points3(targets),
        joints_rad=floats(loads(r["joints_json"])),
        joints_received_at=r["joints_received_at"],
        config_hash=r["config_hash"],
        software_version=r["software_version"],
        duration_s=r["duration_s"],
        is_current=current_id is not None and int(r["id"]) == current_id,
        retired_at=r["retired_at"],
        retired_by_calibration=r["retired_by_calibration"],
    )
