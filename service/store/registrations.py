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


def withdraw_by_verification(
    c: sqlite3.Connection, now: str, reg_id: int, reason: str, *, scan_id: int, verification_id: int | None
) -> bool:
    """Withdraw registration ``reg_id`` because the verification of scan ``scan_id`` failed (inside
    the caller's transaction); removes the current pointer if it pointed there.  Returns whether it
    was current.  An already withdrawn registration is left as it is."""
    c.execute(
        "UPDATE registrations SET withdrawn_at = ?, withdrawn_reason = ?, withdrawn_by_scan = ?, "
        "withdrawn_by_verification = ? WHERE id = ? AND withdrawn_at IS NULL",
        (now, reason, scan_id, verification_id, reg_id),
    )
    row = c.execute("SELECT registration_id FROM current_registration WHERE singleton = 1").fetchone()
    was_current = row is not None and int(row[0]) == reg_id
    if was_current:
        c.execute("DELETE FROM current_registration WHERE singleton = 1")
    return was_current


@dataclass(frozen=True)
class Supersession:
    """Why a scan may not be registered and made current (docs/safety.md, "Which registration may be
    current"); :meth:`RegistrationStore.supersession`."""

    rule: str
    """``withdrawn`` (a verification withdrew this scan's registration), ``newer-registration`` or
    ``newer-failed-verification`` (a newer scan at the same placement has one)."""
    scan_id: int
    """The newer scan (``withdrawn``: the verification scan that withdrew it)."""
    detail: str
    """What happened, naming the records."""


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

    def withdraw_one(self, reg_id: int, reason: str) -> None:
        """Withdraw registration ``reg_id`` and, if it is current, remove the current pointer."""
        with self._db.transaction() as c:
            c.execute(_Withdraw.UPDATE, (utc_now(), reason, reg_id))
            c.execute(
                "DELETE FROM current_registration WHERE singleton = 1 AND registration_id = ?", (reg_id,)
            )

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

    def withdraw_for_verification(
        self, reg_id: int, reason: str, *, scan_id: int, verification_id: int | None
    ) -> bool:
        """Withdraw ``reg_id``: its verification against scan ``scan_id`` failed (one transaction);
        whether it was current (the pointer is then removed)."""
        with self._db.transaction() as c:
            return withdraw_by_verification(
                c, utc_now(), reg_id, reason, scan_id=scan_id, verification_id=verification_id
            )

    def standing_verification_withdrawal(self) -> RegistrationRecord | None:
        """The registration a failed verification withdrew, while that is still why nothing is current:
        nothing is current, it is the newest withdrawal, and no calibration activation retired it since."""
        if self.current_id() is not None:
            return None
        w = self.latest_withdrawn()
        return w if w is not None and w.withdrawn_by_scan is not None and w.retired_at is None else None

    def supersession(self, scan_id: int, frame_of_reference_uid: str) -> Supersession | None:
        """Whether registering scan ``scan_id`` now would serve a matrix the service already has newer
        evidence against (docs/safety.md, "Which registration may be current"); None: it may.

        Evidence counts while the registration it concerns is not retired: activating a calibration
        retires every registration, and what failed under the old model says nothing of the new one.
        An empty FrameOfReferenceUID names no placement: only the scan's own withdrawal applies."""
        rows = self._db.query(
            "SELECT id, withdrawn_by_scan, withdrawn_by_verification FROM registrations WHERE scan_id = ? "
            "AND withdrawn_by_scan IS NOT NULL AND retired_at IS NULL ORDER BY id DESC LIMIT 1",
            (scan_id,),
        )
        if rows:
            reg_id, by_scan, by_ver = int(rows[0][0]), int(rows[0][1]), rows[0][2]
            what = f"verification {by_ver}" if by_ver is not None else "the verification"
            return Supersession(
                "withdrawn",
                by_scan,
                f"registration {reg_id} of scan {scan_id} was withdrawn by {what} of scan {by_scan}",
            )
        if not frame_of_reference_uid:
            return None
        newer = self._db.query(_Supersede.NEWER, (frame_of_reference_uid, scan_id) * 3)
        if not newer:
            return None
        newer_scan, kind, record_id = int(newer[0][0]), str(newer[0][1]), int(newer[0][2])
        if kind == "registration":
            detail = f"newer scan {newer_scan} at the same placement has accepted registration {record_id}"
            return Supersession("newer-registration", newer_scan, detail)
        what = f"failed verification {record_id}" if kind == "verification" else (
            f"a verification that could not be computed (it withdrew registration {record_id})"
        )  # fmt: skip
        detail = f"newer scan {newer_scan} at the same placement has {what}"
        return Supersession("newer-failed-verification", newer_scan, detail)

    def latest_withdrawn(self) -> RegistrationRecord | None:
        rows = self._db.query(
            "SELECT * FROM registrations WHERE withdrawn_at IS NOT NULL ORDER BY withdrawn_at DESC, id DESC "
            "LIMIT 1"
        )
        return _record(rows[0], self.current_id()) if rows else None

    def latest_retired(self) -> RegistrationRecord | None:
        """The registration a calibration activation retired most recently (None: none ever was)."""
        rows = self._db.query(
            "SELECT * FROM registrations WHERE retired_at IS NOT NULL ORDER BY retired_at DESC, id DESC "
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


class _Supersede:
    """SQL of :meth:`RegistrationStore.supersession`: the newest scan newer than ``?`` at FoR ``?`` with
    an accepted registration (not withdrawn by its own scan's change) or a failed verification of a
    registration not retired since; (scan id, kind, record id), newest scan first."""

    NEWER = (
        "SELECT s.id, 'registration', r.id FROM scans s JOIN registrations r ON r.scan_id = s.id "
        "WHERE s.frame_of_reference_uid = ? AND s.id > ? AND r.status = 'accepted' "
        "AND (r.withdrawn_at IS NULL OR r.withdrawn_by_scan IS NOT NULL) "
        "UNION ALL SELECT s.id, 'verification', v.id FROM scans s JOIN verifications v ON v.scan_id = s.id "
        "JOIN registrations r ON r.id = v.registration_id "
        "WHERE s.frame_of_reference_uid = ? AND s.id > ? AND v.passed = 0 AND v.withdrawn_at IS NULL "
        "AND r.retired_at IS NULL "
        "UNION ALL SELECT s.id, 'uncomputed', r.id FROM scans s "
        "JOIN registrations r ON r.withdrawn_by_scan = s.id "
        "WHERE s.frame_of_reference_uid = ? AND s.id > ? AND r.withdrawn_by_verification IS NULL "
        "AND r.retired_at IS NULL "
        "ORDER BY 1 DESC LIMIT 1"
    )


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
        withdrawn_by_scan=r["withdrawn_by_scan"] if withdrawn else None,
        withdrawn_by_verification=r["withdrawn_by_verification"] if withdrawn else None,
    )
