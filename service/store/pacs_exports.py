"""The ``pacs_exports`` table: the queue of Spatial Registration objects to archive.

One row per accepted registration.  ``state``: ``pending`` (queued, being sent, or waiting for the
next attempt after a link failure: ``next_attempt_unix_s``), ``sent`` (the PACS answered success
or a warning, ``dimse_status``), ``failed`` (the PACS refused with ``dimse_status``, or the link
kept failing past ``pacs.give_up_after_s``; ``reason`` says which).  A row stays ``pending`` while
it is being sent, so nothing is lost when the service dies mid-send.
"""

from __future__ import annotations

import sqlite3
from dataclasses import dataclass
from typing import Literal, cast

from service.store.base import Connection, utc_now

ExportState = Literal["pending", "sent", "failed"]


@dataclass(frozen=True)
class PacsExport:
    id: int
    registration_id: int
    destination: str
    """``AE@host:port`` of the PACS it is (was) sent to."""
    state: ExportState
    attempts: int
    dimse_status: int | None
    reason: str
    sop_instance_uid: str
    queued_at: str
    updated_at: str
    next_attempt_unix_s: float


class PacsExportStore:
    def __init__(self, db: Connection) -> None:
        self._db = db

    def enqueue(self, registration_id: int, destination: str, now_unix_s: float) -> bool:
        """Queue ``registration_id`` (once: False if it already has a row)."""
        now = utc_now()
        with self._db.transaction() as c:
            cur = c.execute(
                "INSERT OR IGNORE INTO pacs_exports (registration_id, destination, state, queued_at, "
                "updated_at, next_attempt_unix_s) VALUES (?, ?, 'pending', ?, ?, ?)",
                (registration_id, destination, now, now, now_unix_s),
            )
            return cur.rowcount == 1

    def missed(self) -> list[int]:
        """Accepted registrations newer than the newest queued one but not queued (the service
        stopped between accepting and queueing); none before the first export ever queued."""
        rows = self._db.query(
            "SELECT r.id FROM registrations r WHERE r.status = 'accepted' AND r.withdrawn_at IS NULL "
            "AND r.id > (SELECT COALESCE(MAX(registration_id), 1e18) FROM pacs_exports) ORDER BY r.id"
        )
        return [int(r[0]) for r in rows]

    def due(self, now_unix_s: float, limit: int = 10) -> list[PacsExport]:
        """Pending rows whose next attempt is due, oldest first."""
        rows = self._db.query(
            "SELECT * FROM pacs_exports WHERE state = 'pending' AND next_attempt_unix_s <= ? "
            "ORDER BY next_attempt_unix_s, id LIMIT ?",
            (now_unix_s, limit),
        )
        return [_row(r) for r in rows]

    def next_due_unix_s(self) -> float | None:
        rows = self._db.query("SELECT MIN(next_attempt_unix_s) FROM pacs_exports WHERE state = 'pending'")
        return None if not rows or rows[0][0] is None else float(rows[0][0])

    def get(self, registration_id: int) -> PacsExport | None:
        rows = self._db.query("SELECT * FROM pacs_exports WHERE registration_id = ?", (registration_id,))
        return _row(rows[0]) if rows else None

    def update(
        self, registration_id: int, *, state: ExportState, attempts: int, dimse_status: int | None,
        reason: str, sop_instance_uid: str, next_attempt_unix_s: float,
    ) -> None:  # fmt: skip
        with self._db.transaction() as c:
            c.execute(
                "UPDATE pacs_exports SET state = ?, attempts = ?, dimse_status = ?, reason = ?, "
                "sop_instance_uid = ?, updated_at = ?, next_attempt_unix_s = ? WHERE registration_id = ?",
                (state, attempts, dimse_status, reason[:500], sop_instance_uid, utc_now(),
                 next_attempt_unix_s, registration_id),
            )  # fmt: skip

    def requeue(self, registration_id: int, destination: str, now_unix_s: float) -> None:
        """Back to ``pending`` now, attempts reset (the retry endpoint); the row must exist."""
        with self._db.transaction() as c:
            c.execute(
                "UPDATE pacs_exports SET state = 'pending', attempts = 0, dimse_status = NULL, reason = '', "
                "destination = ?, queued_at = ?, updated_at = ?, next_attempt_unix_s = ? "
                "WHERE registration_id = ?",
                (destination, utc_now(), utc_now(), now_unix_s, registration_id),
            )


def _row(r: sqlite3.Row) -> PacsExport:
    return PacsExport(
        id=int(r["id"]),
        registration_id=int(r["registration_id"]),
        destination=str(r["destination"]),
        state=cast(ExportState, r["state"]),
        attempts=int(r["attempts"]),
        dimse_status=None if r["dimse_status"] is None else int(r["dimse_status"]),
        reason=str(r["reason"]),
        sop_instance_uid=str(r["sop_instance_uid"]),
        queued_at=str(r["queued_at"]),
        updated_at=str(r["updated_at"]),
        next_attempt_unix_s=float(r["next_attempt_unix_s"]),
    )
