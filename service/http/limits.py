"""Bounded HTTP connections for uvicorn: a connection cap and a request-header deadline.

uvicorn's own bounds do not hold a flood of idle peers: ``timeout_keep_alive`` only starts after a
response (a connection that never sends a byte stays open for ever), and ``limit_concurrency``
answers 503 to *everyone* once full, ``/health`` included.  :func:`bounded_protocol` makes an
``HttpToolsProtocol`` subclass (uvicorn's ``Config(http=...)`` takes a protocol class) that adds:

* **a request-header deadline** (``api.first_request_timeout_s``): a connection must complete a
  request header within this long of opening, and of its previous response; otherwise it is
  closed (the peer sees EOF, no response).  A peer that trickles a header byte by byte is closed
  the same way.
* **a connection cap** (``api.max_connections``): one connection over the cap closes the *oldest
  idle* one (no request in progress: never sent a complete header, or between keep-alive requests)
  and the newcomer is served, so ``/health`` and the page keep answering while idle peers are
  held.  Connections with a request in progress (an SSE stream among them) are never dropped; when
  every connection is busy the newcomer is closed instead.
* **a share per peer address** (``api.max_connections_per_address``): a new connection from an
  address already holding its share closes that address's oldest idle connection, or itself when
  all of them are busy, so one host cannot hold every slot and lock another out.
* **a write deadline** (``api.write_timeout_s``): a connection whose peer stops reading (the
  transport paused writing: its buffer is full) and does not resume within this long is aborted,
  so a slow reader pipelining large responses cannot hold its slot for ever.  A streaming response
  (``/events``) stays open as long as its peer reads.

Every drop is counted (:class:`HttpLimitCounters`, on the protocol class); drops are logged as one
WARNING per :data:`LOG_EVERY_S` with the counts, not one line per peer.
"""

from __future__ import annotations

import asyncio
import logging
from dataclasses import dataclass
from typing import Any, ClassVar

from uvicorn.protocols.http.httptools_impl import HttpToolsProtocol, RequestResponseCycle

log = logging.getLogger(__name__)

LOG_EVERY_S = 30.0
"""At most one WARNING about dropped HTTP connections per this many seconds (a flood is one line)."""


@dataclass
class HttpLimitCounters:
    """Connections dropped by the bounds, since start-up."""

    header_timeouts: int = 0
    """Closed for not completing a request header within ``api.first_request_timeout_s``."""
    idle_evicted: int = 0
    """Oldest idle connections closed to admit a newer one (``api.max_connections``)."""
    refused_busy: int = 0
    """New connections closed because every held connection had a request in progress."""
    address_share: int = 0
    """Connections closed because their address held ``api.max_connections_per_address``."""
    write_timeouts: int = 0
    """Connections aborted because their peer read nothing for ``api.write_timeout_s``."""
    last_address: str = ""
    """The address of the latest connection closed for its share or a write deadline."""
    last_drop_at: float = -1e18
    """Monotonic time of that drop (``/ready`` names the problem for a while after it)."""
    logged_at: float = -1e18
    logged_total: int = 0

    @property
    def total(self) -> int:
        return sum(self.as_dict().values())

    def as_dict(self) -> dict[str, int]:
        return {
            "header_timeouts": self.header_timeouts,
            "idle_evicted": self.idle_evicted,
            "refused_busy": self.refused_busy,
            "address_share": self.address_share,
            "write_timeouts": self.write_timeouts,
        }


class BoundedHttpProtocol(HttpToolsProtocol):
    """uvicorn's httptools protocol with a request-header deadline and a connection cap (see the
    module docstring).  Use :func:`bounded_protocol` to get a subclass with the limits set."""

    max_connections: ClassVar[int] = 256
    max_connections_per_address: ClassVar[int] = 64
    first_request_timeout_s: ClassVar[float] = 10.0
    write_timeout_s: ClassVar[float] = 10.0
    counters: ClassVar[HttpLimitCounters] = HttpLimitCounters()

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        self._header_deadline: asyncio.TimerHandle | None = None
        self._write_deadline: asyncio.TimerHandle | None = None
        self._cycles: list[RequestResponseCycle] = []
        """Requests not answered yet: the running one and those pipelined behind it (uvicorn marks
        only the newest disconnected when the connection is lost; the running one then wrote on a
        closed transport, an unhandled error per connection)."""
        self.opened_at = 0.0

    def _host(self) -> str:
        client = getattr(self, "client", None)
        return str(client[0]) if isinstance(client, tuple) and client else ""

    # ---- the write deadline --------------------------------------------------------------

    def pause_writing(self) -> None:
        super().pause_writing()
        if self._write_deadline is None:
            self._write_deadline = self.loop.call_later(self.write_timeout_s, self._write_timeout)

    def resume_writing(self) -> None:
        self._cancel_write_deadline()
        super().resume_writing()

    def _cancel_write_deadline(self) -> None:
        if self._write_deadline is not None:
            self._write_deadline.cancel()
            self._write_deadline = None

    def _write_timeout(self) -> None:
        self._write_deadline = None
        if not self.transport.is_closing():
            self.counters.write_timeouts += 1
            self._note_address(self)
            self._drop(self, "its peer read nothing for api.write_timeout_s", abort=True)

    # ---- the deadline --------------------------------------------------------------------

    def _arm_header_deadline(self) -> None:
        self._cancel_header_deadline()
        self._header_deadline = self.loop.call_later(self.first_request_timeout_s, self._header_timeout)

    def _cancel_header_deadline(self) -> None:
        if self._header_deadline is not None:
            self._header_deadline.cancel()
            self._header_deadline = None

    def _header_timeout(self) -> None:
        self._header_deadline = None
        if not self.transport.is_closing():
            self.counters.header_timeouts += 1
            self._drop(self, "no complete request header within api.first_request_timeout_s")

    # ---- the cap -------------------------------------------------------------------------

    def is_idle(self) -> bool:
        """No request in progress (none started, or the last one answered)."""
        return not self.pipeline and (self.cycle is None or self.cycle.response_complete)

    def _over_address_share(self) -> None:
        """This connection's address holds more than its share: close its oldest idle one, else this."""
        host = self._host()
        mine = [c for c in self.connections if isinstance(c, BoundedHttpProtocol) and c._host() == host]
        if len(mine) <= self.max_connections_per_address:
            return
        idle = [c for c in mine if c is not self and c.is_idle()]
        victim = min(idle, key=lambda c: c.opened_at) if idle else self
        self.counters.address_share += 1
        self._note_address(victim)
        self._drop(victim, "its address holds api.max_connections_per_address")

    def _note_address(self, conn: BoundedHttpProtocol) -> None:
        self.counters.last_address, self.counters.last_drop_at = conn._host(), self.loop.time()

    def _make_room(self) -> None:
        """Over ``max_connections``: close the oldest idle connection, else this new one."""
        victim: BoundedHttpProtocol | None = None
        for c in self.connections:
            if (
                c is not self
                and isinstance(c, BoundedHttpProtocol)
                and c.is_idle()
                and (victim is None or c.opened_at < victim.opened_at)
            ):
                victim = c
        if victim is None:
            self.counters.refused_busy += 1
            self._drop(self, "every connection has a request in progress (api.max_connections)")
        else:
            self.counters.idle_evicted += 1
            self._drop(victim, "oldest idle connection closed for a new one (api.max_connections)")

    def _drop(self, conn: BoundedHttpProtocol, why: str, abort: bool = False) -> None:
        conn._cancel_header_deadline()
        conn._cancel_write_deadline()
        self.connections.discard(conn)  # counted out now; connection_lost discards it again
        if abort:  # close() would wait to flush what the peer does not read
            conn.transport.abort()
        else:
            conn.transport.close()
        log.debug("HTTP %s: %s", conn.client, why)
        c = self.counters
        now = self.loop.time()
        if now - c.logged_at >= LOG_EVERY_S:
            log.warning(
                "HTTP: %d connection(s) dropped since the last report (header deadline %d, idle evicted %d, "
                "refused busy %d, address share %d, write deadline %d since start-up; latest from %s: %s)",
                c.total - c.logged_total, c.header_timeouts, c.idle_evicted, c.refused_busy, c.address_share,
                c.write_timeouts, conn._host() or "?", why,
            )  # fmt: skip
            c.logged_at, c.logged_total = now, c.total

    # ---- uvicorn's protocol hooks ----------------------------------------------------------

    def connection_made(self, transport: asyncio.Transport) -> None:  # type: ignore[override]
        super().connection_made(transport)
        self.opened_at = self.loop.time()
        self._arm_header_deadline()
        self._over_address_share()
        if not self.transport.is_closing() and len(self.connections) > self.max_connections:
            self._make_room()

    def connection_lost(self, exc: Exception | None) -> None:
        self._cancel_header_deadline()
        self._cancel_write_deadline()
        for cycle in self._cycles:  # before super() resumes writing: a waiting send returns at once
            if not cycle.response_complete:
                cycle.disconnected = True
        self._cycles.clear()
        super().connection_lost(exc)

    def on_headers_complete(self) -> None:
        self._cancel_header_deadline()
        super().on_headers_complete()
        self._cycles = [c for c in self._cycles if not c.response_complete]
        if self.cycle is not None:
            self._cycles.append(self.cycle)

    def on_response_complete(self) -> None:
        super().on_response_complete()
        if not self.transport.is_closing() and self.is_idle():
            self._arm_header_deadline()


def bounded_protocol(
    max_connections: int,
    first_request_timeout_s: float,
    max_connections_per_address: int | None = None,
    write_timeout_s: float = 10.0,
) -> type[BoundedHttpProtocol]:
    """A :class:`BoundedHttpProtocol` subclass with these limits and its own counters (one per server)."""
    share = max_connections if max_connections_per_address is None else max_connections_per_address
    return type(
        "BoundedHttpProtocolWithLimits",
        (BoundedHttpProtocol,),
        {
            "max_connections": max_connections,
            "max_connections_per_address": min(share, max_connections),
            "first_request_timeout_s": first_request_timeout_s,
            "write_timeout_s": write_timeout_s,
            "counters": HttpLimitCounters(),
        },
    )
