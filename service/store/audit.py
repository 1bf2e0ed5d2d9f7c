"""The ``audit_log`` table: who registered, verified, activated or deleted what.

``principal`` names the credential, never the credential itself: ``token:<12 hex of SHA-256>``
(:func:`service.http.security.token_principal`) or ``none-loopback-only``.  ``detail`` holds the
outcome's title or reason as the API gave it (no patient identifiers: the API never carries any).
"""

from __future__ import annotations

import contextlib
import threading
from collections import deque
from dataclasses import dataclass
from typing import Literal

from service.store.base import Connection, utc_now

AuditAction = Literal[
    "register",
    "verify",
    "activate",
    "delete",
    "pacs_export",
    "qa_protocol_create",
    "auth_throttle",
    "auth_throttle_summary",
]
MAX_DETAIL_CHARS = 500


@dataclass(frozen=True)
class AuditEntry:
    id: int
    at: str
    principal: str
    action: str
    target: str
    target_id: int | None
    outcome: str
    detail: str


MAX_DEFERRED = 1000
"""Audit rows held in memory while the database cannot be written (oldest dropped, and counted)."""
_INSERT = (
    "INSERT INTO audit_log (at, principal, action, target, target_id, outcome, detail) "
    "VALUES (?, ?, ?, ?, ?, ?, ?)"
)


class AuditStore:
    """The audit log.  A row that cannot be written because the database is busy or read-only
    (:class:`~service.errors.DatabaseBusyError`) is kept in memory (at most :data:`MAX_DEFERRED`) with
    its original time and written before the next one."""

    def __init__(self, db: Connection) -> None:
        self._db = db
        self._deferred: deque[tuple[object, ...]] = deque(maxlen=MAX_DEFERRED)
        self._lock = threading.Lock()

    def record(
        self, principal: str, action: AuditAction, target: str, target_id: int | None, outcome: str,
        detail: str = "",
    ) -> int:  # fmt: skip
        """Append one entry (after any deferred ones); its id.  Raises what the write raised; a
        :class:`~service.errors.DatabaseBusyError` keeps the row deferred."""
        row = (utc_now(), principal, action, target, target_id, outcome, detail[:MAX_DETAIL_CHARS])
        with self._lock:
            self._deferred.append(row)
            return self._flush()

    def defer(
        self, principal: str, action: AuditAction, target: str, target_id: int | None, outcome: str,
        detail: str = "",
    ) -> None:  # fmt: skip
        """Keep one entry in memory without touching the database (it is busy: written by the next
        :meth:`record` or :meth:`flush`)."""
        with self._lock:
            self._deferred.append(
                (utc_now(), principal, action, target, target_id, outcome, detail[:MAX_DETAIL_CHARS])
            )

    def flush(self) -> None:
        """Write the deferred entries, if any (raises as :meth:`record`)."""
        with self._lock:
            if self._deferred:
                self._flush()

    def _flush(self) -> int:
        from service.errors import DatabaseBusyError

        rows = list(self._deferred)
        try:
            with self._db.transaction() as c:
                last = 0
                for r in rows:
                    last = int(c.execute(_INSERT, r).lastrowid or 0)
        except DatabaseBusyError:
            raise  # the rows stay deferred
        except BaseException:
            self._deferred.pop()  # this row fails for its own reason; the earlier ones stay
            raise
        self._deferred.clear()
        return last

    def list(self, limit: int = 100, offset: int = 0) -> list[AuditEntry]:
        """Newest first (deferred entries written first, when the database takes them)."""
        with contextlib.suppress(Exception):
            self.flush()
        rows = self._db.query(
            "SELECT id, at, principal, action, target, target_id, outcome, detail FROM audit_log "
            "ORDER BY id DESC LIMIT ? OFFSET ?",
            (limit, offset),
        )
        return [
            AuditEntry(
                id=int(r[0]),
                at=str(r[1]),
                principal=str(r[2]),
                action=str(r[3]),
                target=str(r[4]),
                target_id=None if r[5] is None else int(r[5]),
                outcome=str(r[6]),
                detail=str(r[7]),
            )
            for r in rows
        ]
