"""Single-use, short-lived tickets for ``GET /events?ticket=`` (browsers' ``EventSource`` cannot
send ``Authorization``).  Minted by the authenticated ``POST /events/ticket``, redeemed by
:class:`service.http.security.SecurityGate`."""

from __future__ import annotations

import secrets
import time

MAX_OUTSTANDING_TICKETS = 1000
"""Tickets minted and not yet used or expired; more are refused (429) — a client loop gone wrong."""


class TicketBook:
    """The outstanding tickets (used on the event loop only)."""

    def __init__(self) -> None:
        self._tickets: dict[str, tuple[float, str]] = {}

    def mint(self, principal: str, ttl_s: float) -> str | None:
        """A new ticket for ``principal``, valid ``ttl_s`` seconds, usable once; None when
        :data:`MAX_OUTSTANDING_TICKETS` are outstanding."""
        now = time.monotonic()
        self._tickets = {k: v for k, v in self._tickets.items() if v[0] > now}
        if len(self._tickets) >= MAX_OUTSTANDING_TICKETS:
            return None
        ticket = secrets.token_urlsafe(24)
        self._tickets[ticket] = (now + ttl_s, principal)
        return ticket

    def redeem(self, ticket: str) -> str | None:
        """The ticket's principal if it is known and unexpired (it is used up either way), else None."""
        entry = self._tickets.pop(ticket, None)
        if entry is None or entry[0] <= time.monotonic():
            return None
        return entry[1]
