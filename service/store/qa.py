"""The ``qa_protocols`` and ``qa_checks`` tables.

A QA protocol is a named, fixed set of verification poses (joint angles, rad) so that successive
QA checks of the same cell are comparable; a QA check is a verification taken at one pose of one
protocol.  Protocols are never edited in place (a changed set of poses is a new protocol).
"""

from __future__ import annotations

import sqlite3
from dataclasses import dataclass

from service.store.base import Connection, dumps, loads, utc_now


@dataclass(frozen=True)
class QaPose:
    name: str
    joints_rad: tuple[float, ...]


@dataclass(frozen=True)
class QaProtocol:
    id: int
    name: str
    description: str
    poses: tuple[QaPose, ...]
    created_at: str

    def pose(self, name: str) -> QaPose | None:
        return next((p for p in self.poses if p.name == name), None)


@dataclass(frozen=True)
class QaCheck:
    verification_id: int
    protocol_id: int
    pose: str


class QaStore:
    """QA protocols and the verifications taken under them."""

    def __init__(self, db: Connection) -> None:
        self._db = db

    def find_by_name(self, name: str) -> QaProtocol | None:
        rows = self._db.query("SELECT * FROM qa_protocols WHERE name = ?", (name,))
        return _protocol(rows[0]) if rows else None

    def insert_protocol(self, name: str, description: str, poses: tuple[QaPose, ...]) -> int:
        """Store a new protocol; returns its id (the caller checked that ``name`` is free)."""
        body = [{"name": p.name, "joints_rad": list(p.joints_rad)} for p in poses]
        with self._db.transaction() as c:
            cur = c.execute(
                "INSERT INTO qa_protocols (name, description, poses_json, created_at) VALUES (?, ?, ?, ?)",
                (name, description, dumps(body), utc_now()),
            )
            return int(cur.lastrowid or 0)

    def get_protocol(self, protocol_id: int) -> QaProtocol | None:
        rows = self._db.query("SELECT * FROM qa_protocols WHERE id = ?", (protocol_id,))
        return _protocol(rows[0]) if rows else None

    def list_protocols(self, limit: int = 100, offset: int = 0) -> list[QaProtocol]:
        """Newest first."""
        rows = self._db.query("SELECT * FROM qa_protocols ORDER BY id DESC LIMIT ? OFFSET ?", (limit, offset))
        return [_protocol(r) for r in rows]

    def insert_check(self, check: QaCheck) -> None:
        with self._db.transaction() as c:
            c.execute(
                "INSERT INTO qa_checks (verification_id, protocol_id, pose) VALUES (?, ?, ?)",
                (check.verification_id, check.protocol_id, check.pose),
            )


def _protocol(r: sqlite3.Row) -> QaProtocol:
    poses = tuple(
        QaPose(str(p["name"]), tuple(float(x) for x in p["joints_rad"])) for p in loads(r["poses_json"])
    )
    return QaProtocol(int(r["id"]), str(r["name"]), str(r["description"]), poses, str(r["created_at"]))


# ---- QA trend ----------------------------------------------------------------------------

_CALIBRATION_OF = "json_extract(r.figures_json, '$.provenance.calibration.calibration_id')"
"""The calibration active when a registration was made (its provenance; NULL: the nominal model)."""


@dataclass(frozen=True)
class QaTrendPoint:
    """One QA verification: a verification with a ``qa_checks`` row."""

    verification_id: int
    created_at: str
    protocol_id: int
    protocol_name: str
    pose: str
    mean_mm: float
    max_mm: float
    passed: bool
    registration_id: int
    calibration_id: int | None
    """Active when the registration verified was made (None: the nominal robot model)."""
    withdrawn: bool


@dataclass(frozen=True)
class FrePoint:
    """One accepted registration's FRE."""

    registration_id: int
    created_at: str
    fre_mm: float
    calibration_id: int | None
    face_offset_mm: float | None = None
    """The scan's face offset β (mm; None: not fitted, or stored before it was)."""


def _cal_filter(calibration_id: int | None, nominal: bool) -> tuple[str, tuple[object, ...]]:
    if nominal:
        return f" AND {_CALIBRATION_OF} IS NULL", ()
    if calibration_id is None:
        return "", ()
    return f" AND {_CALIBRATION_OF} = ?", (calibration_id,)


class QaTrendStore:
    """Read-only queries over verifications, qa_checks and registrations for ``GET /qa/trend``."""

    def __init__(self, db: Connection) -> None:
        self._db = db

    def checks(
        self, calibration_id: int | None = None, *, nominal: bool = False, limit: int = 100, offset: int = 0
    ) -> list[QaTrendPoint]:
        """QA verifications, oldest first; ``calibration_id`` narrows to one calibration,
        ``nominal`` to registrations made with the nominal model."""
        where, args = _cal_filter(calibration_id, nominal)
        rows = self._db.query(
            "SELECT v.id, v.created_at, q.protocol_id, p.name AS protocol_name, q.pose, v.mean_mm, "
            f"v.max_mm, v.passed, v.registration_id, {_CALIBRATION_OF} AS calibration_id, "
            "v.withdrawn_at FROM verifications v JOIN qa_checks q ON q.verification_id = v.id "
            "JOIN qa_protocols p ON p.id = q.protocol_id JOIN registrations r ON r.id = v.registration_id "
            f"WHERE 1 = 1{where} ORDER BY v.id LIMIT ? OFFSET ?",
            (*args, limit, offset),
        )
        return [
            QaTrendPoint(
                verification_id=int(x["id"]),
                created_at=str(x["created_at"]),
                protocol_id=int(x["protocol_id"]),
                protocol_name=str(x["protocol_name"]),
                pose=str(x["pose"]),
                mean_mm=float(x["mean_mm"]),
                max_mm=float(x["max_mm"]),
                passed=bool(x["passed"]),
                registration_id=int(x["registration_id"]),
                calibration_id=None if x["calibration_id"] is None else int(x["calibration_id"]),
                withdrawn=x["withdrawn_at"] is not None,
            )
            for x in rows
        ]

    def fre(
        self, calibration_id: int | None = None, *, nominal: bool = False, limit: int = 100, offset: int = 0
    ) -> list[FrePoint]:
        """Accepted registrations' FRE, oldest first (same filter as :meth:`checks`)."""
        where, args = _cal_filter(calibration_id, nominal)
        rows = self._db.query(
            f"SELECT r.id, r.created_at, r.fre_mm, {_CALIBRATION_OF} AS calibration_id, "
            "json_extract(r.figures_json, '$.face_offset_mm') AS face_offset_mm FROM registrations r "
            f"WHERE r.status = 'accepted' AND r.fre_mm IS NOT NULL{where} ORDER BY r.id LIMIT ? OFFSET ?",
            (*args, limit, offset),
        )
        return [
            FrePoint(
                int(x["id"]),
                str(x["created_at"]),
                float(x["fre_mm"]),
                None if x["calibration_id"] is None else int(x["calibration_id"]),
                None if x["face_offset_mm"] is None else float(x["face_offset_mm"]),
            )
            for x in rows
        ]

    def last_means(self, calibration_id: int | None, n: int) -> list[float]:
        """The mean error (mm) of the last ``n`` QA checks made under ``calibration_id`` (None:
        the nominal model), withdrawn ones left out; oldest first."""
        where, args = _cal_filter(calibration_id, calibration_id is None)
        rows = self._db.query(
            "SELECT v.mean_mm FROM verifications v JOIN qa_checks q ON q.verification_id = v.id "
            f"JOIN registrations r ON r.id = v.registration_id WHERE v.withdrawn_at IS NULL{where} "
            "ORDER BY v.id DESC LIMIT ?",
            (*args, n),
        )
        return [float(x["mean_mm"]) for x in reversed(rows)]
