"""What the HTTP door keeps beside the service's parts (``app.state.http``).

The service's parts and their state are the runtime's :class:`service.runtime.context.ServiceContext`;
what only HTTP needs lives here, built with the app and kept across restarts of its lifespan: the
event tickets, the server's connection counters and the encoded current registration.
"""

from __future__ import annotations

from dataclasses import dataclass, field

from service.http.limits import HttpLimitCounters
from service.http.tickets import TicketBook
from service.records import RegistrationRecord


@dataclass
class HttpState:
    """``app.state.http``: set by :func:`service.http.app.create_app`; ``limits`` by ``serve``."""

    tickets: TicketBook = field(default_factory=TicketBook)
    """Single-use tickets for GET /events?ticket= (service.http.security)."""
    limits: HttpLimitCounters | None = None
    """The HTTP connection bounds' counters (``service.http.limits``; None when not served by ``serve``)."""
    _current: tuple[RegistrationRecord, bytes] | None = None

    def current_registration_json(self, cur: RegistrationRecord | None) -> bytes | None:
        """``cur`` (the current registration) as JSON bytes, encoded once per registration."""
        if cur is None:
            return None
        cached = self._current
        if cached is None or cached[0] is not cur:
            from service.http.api.models import registration_out

            cached = (cur, registration_out(cur).model_dump_json().encode())
            self._current = cached
        return cached[1]
