"""The ``audit_log`` table: who registered, verified, activated or deleted what.

``principal`` names the credential, never the credential itself: ``token:<12 hex of SHA-256>``
(:func:`service.http.security.token_principal`) or ``none-loopback-only``.  ``detail`` holds the
outcome's title or reason as the API gave it (no patient identifiers: the API never carries any).
"""

from __future__ import annotations

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


class AuditStore:
    def __init__(self, db: Connection) -> None:
        self._db = db

    def record(
        self, principal: str, action: AuditAction, target: str, target_id: int | None, outcome: str,
        detail: str = "",
    ) -> int:  # fmt: skip
        """Append one entry; its id."""
        with self._db.transaction() as c:
            cur = c.execute(
                "INSERT INTO audit_log (at, principal, action, target, target_id, outcome, detail) "
                "VALUES (?, ?, ?, ?, ?, ?, ?)",
                (utc_now(), principal, action, target, target_id, outcome, detail[:MAX_DETAIL_CHARS]),
            )
            return int(cur.lastrowid or 0)

    def list(self, limit: int = 100, offset: int = 0) -> list[AuditEntry]:
        """Newest first."""
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
