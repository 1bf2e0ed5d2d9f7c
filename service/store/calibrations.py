"""The ``calibrations`` table, the ``active_calibration`` pointer and retiring registrations.

A calibration row is written when ``POST /calibrations`` is accepted for work (status ``running``)
or refused at once (``refused`` + reason), and updated once when the worker ends (``done`` with the
figures and the calibrated URDF, or ``refused``).  Activating one is one transaction: the pointer
moves, every accepted registration not yet retired is marked retired (they were computed with the
previous model and rod) and the current-registration pointer is removed (design.md §9: none is
current until the next ``/register``).
"""

from __future__ import annotations

import sqlite3
from dataclasses import dataclass
from typing import Any, Literal, cast

from service.records import JSONDict
from service.store.base import Connection, dumps, loads, utc_now
from service.store.registrations import retire_accepted

CalibrationStatus = Literal["running", "done", "refused"]


@dataclass(frozen=True)
class CalibrationRecord:
    """One calibration session (``id`` 0 until stored).

    ``result`` is :meth:`registration.calibration.solver.CalibrationResult.to_dict` plus ``provenance``
    (None unless ``done``); ``urdf_text`` the calibrated URDF; ``calibration_hash`` the SHA-256 of
    the URDF and ``tool0_from_phantom`` (what a registration's provenance names).
    """

    created_at: str
    status: CalibrationStatus
    scan_ids: tuple[int, ...]
    params: JSONDict
    config_hash: str
    software_version: str
    id: int = 0
    reason: str = ""
    problem_title: str = ""
    frame_of_reference_uid: str = ""
    result: JSONDict | None = None
    urdf_text: str | None = None
    urdf_path: str | None = None
    calibration_hash: str = ""
    finished_at: str | None = None
    duration_s: float | None = None
    is_active: bool = False
    activated_at: str | None = None
    withdrawn_at: str | None = None
    """When a scan it was fitted to changed content (docs/safety.md): never activated again."""
    withdrawn_reason: str = ""


@dataclass(frozen=True)
class Activation:
    """What :meth:`CalibrationStore.activate` changed."""

    calibration_id: int
    previous_calibration_id: int | None
    retired_registration_ids: tuple[int, ...]
    previous_current_registration_id: int | None


class CalibrationStore:
    """Every calibration session, and which one is active."""

    def __init__(self, db: Connection) -> None:
        self._db = db

    def insert(self, r: CalibrationRecord) -> int:
        with self._db.transaction() as c:
            cur = c.execute(
                "INSERT INTO calibrations (created_at, status, reason, problem_title, scan_ids_json, "
                "frame_of_reference_uid, params_json, result_json, urdf_text, urdf_path, calibration_hash, "
                "config_hash, software_version, finished_at, duration_s) "
                "VALUES (?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?)",
                (
                    r.created_at, r.status, r.reason, r.problem_title, dumps(list(r.scan_ids)),
                    r.frame_of_reference_uid, dumps(r.params), dumps(r.result), r.urdf_text, r.urdf_path,
                    r.calibration_hash, r.config_hash, r.software_version, r.finished_at, r.duration_s,
                ),
            )  # fmt: skip
            return int(cur.lastrowid or 0)

    def finish(
        self,
        cal_id: int,
        *,
        status: Literal["done", "refused"],
        duration_s: float,
        reason: str = "",
        problem_title: str = "",
        result: JSONDict | None = None,
        urdf_text: str | None = None,
        urdf_path: str | None = None,
        calibration_hash: str = "",
    ) -> None:
        """End a ``running`` calibration (done with its figures, or refused with the reason)."""
        with self._db.transaction() as c:
            c.execute(
                "UPDATE calibrations SET status = ?, reason = ?, problem_title = ?, result_json = ?, "
                "urdf_text = ?, urdf_path = ?, calibration_hash = ?, finished_at = ?, duration_s = ? "
                "WHERE id = ? AND status = 'running'",
                (
                    status, reason, problem_title, dumps(result), urdf_text, urdf_path, calibration_hash,
                    utc_now(), duration_s, cal_id,
                ),
            )  # fmt: skip

    def refuse_interrupted(self, reason: str) -> list[int]:
        """Mark every ``running`` row refused (the service stopped while it ran); returns their ids."""
        with self._db.transaction() as c:
            ids = [int(r[0]) for r in c.execute("SELECT id FROM calibrations WHERE status = 'running'")]
            c.execute(
                "UPDATE calibrations SET status = 'refused', reason = ?, problem_title = ?, finished_at = ? "
                "WHERE status = 'running'",
                (reason, "Calibration interrupted", utc_now()),
            )
            return ids

    def active_id(self) -> int | None:
        rows = self._db.query("SELECT calibration_id FROM active_calibration WHERE singleton = 1")
        return int(rows[0][0]) if rows else None

    def get(self, cal_id: int) -> CalibrationRecord | None:
        rows = self._db.query("SELECT * FROM calibrations WHERE id = ?", (cal_id,))
        return _record(rows[0], self._active()) if rows else None

    def active(self) -> CalibrationRecord | None:
        a = self.active_id()
        return None if a is None else self.get(a)

    def list(self, limit: int = 100, offset: int = 0) -> list[CalibrationRecord]:
        act = self._active()
        rows = self._db.query("SELECT * FROM calibrations ORDER BY id DESC LIMIT ? OFFSET ?", (limit, offset))
        return [_record(r, act) for r in rows]

    def _active(self) -> tuple[int, str] | None:
        rows = self._db.query("SELECT calibration_id, set_at FROM active_calibration WHERE singleton = 1")
        return (int(rows[0][0]), str(rows[0][1])) if rows else None

    def activate(self, cal_id: int) -> Activation:
        """Make ``cal_id`` (status ``done``) active; retire every accepted registration; none is current.

        Raises
        ------
        ValueError
            ``cal_id`` does not exist or is not ``done``.
        """
        now = utc_now()
        with self._db.transaction() as c:
            row = c.execute(
                "SELECT status, withdrawn_at FROM calibrations WHERE id = ?", (cal_id,)
            ).fetchone()
            state = "missing" if row is None else "withdrawn" if row["withdrawn_at"] else row["status"]
            if state != "done":
                raise ValueError(f"calibration {cal_id} is {state}, not done")
            prev = c.execute("SELECT calibration_id FROM active_calibration WHERE singleton = 1").fetchone()
            cur = c.execute("SELECT registration_id FROM current_registration WHERE singleton = 1").fetchone()
            retired = retire_accepted(c, now, cal_id, also_withdrawn=True)
            c.execute("DELETE FROM current_registration WHERE singleton = 1")
            c.execute(
                "INSERT INTO active_calibration (singleton, calibration_id, set_at) VALUES (1, ?, ?) "
                "ON CONFLICT(singleton) DO UPDATE SET calibration_id = excluded.calibration_id, "
                "set_at = excluded.set_at",
                (cal_id, now),
            )
        return Activation(
            calibration_id=cal_id,
            previous_calibration_id=None if prev is None else int(prev[0]),
            retired_registration_ids=tuple(retired),
            previous_current_registration_id=None if cur is None else int(cur[0]),
        )


def _record(r: sqlite3.Row, active: tuple[int, str] | None) -> CalibrationRecord:
    is_active = active is not None and active[0] == int(r["id"])
    result: Any = loads(r["result_json"])
    return CalibrationRecord(
        id=int(r["id"]),
        created_at=r["created_at"],
        status=cast(CalibrationStatus, r["status"]),
        reason=r["reason"],
        problem_title=r["problem_title"],
        scan_ids=tuple(int(v) for v in loads(r["scan_ids_json"]) or ()),
        frame_of_reference_uid=r["frame_of_reference_uid"],
        params=dict(loads(r["params_json"]) or {}),
        result=None if result is None else dict(result),
        urdf_text=r["urdf_text"],
        urdf_path=r["urdf_path"],
        calibration_hash=r["calibration_hash"],
        config_hash=r["config_hash"],
        software_version=r["software_version"],
        finished_at=r["finished_at"],
        duration_s=r["duration_s"],
        is_active=is_active,
        activated_at=active[1] if is_active and active is not None else None,
        withdrawn_at=r["withdrawn_at"],
        withdrawn_reason=r["withdrawn_reason"],
    )
