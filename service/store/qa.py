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

    def check_of(self, verification_id: int) -> QaCheck | None:
        rows = self._db.query("SELECT * FROM qa_checks WHERE verification_id = ?", (verification_id,))
        if not rows:
            return None
        r = rows[0]
        return QaCheck(int(r["verification_id"]), int(r["protocol_id"]), str(r["pose"]))


def _protocol(r: sqlite3.Row) -> QaProtocol:
    poses = tuple(
        QaPose(str(p["name"]), tuple(float(x) for x in p["joints_rad"])) for p in loads(r["poses_json"])
    )
    return QaProtocol(int(r["id"]), str(r["name"]), str(r["description"]), poses, str(r["created_at"]))
