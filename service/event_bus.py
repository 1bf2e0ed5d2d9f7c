"""The in-process event bus behind ``GET /events`` (:mod:`service.api.events`).

Event names: :data:`EVENT_NAMES` (an unknown name is a ``ValueError``).  :meth:`EventBus.publish`
is callable from any thread.
"""

from __future__ import annotations

import asyncio
import contextlib
import itertools
import json
import logging
import threading
from collections import deque
from collections.abc import AsyncIterator, Callable
from typing import Any

log = logging.getLogger(__name__)

KEEPALIVE_S = 15.0
"""Comment interval on idle streams (proxies commonly drop connections idle for 30–60 s)."""
QUEUE_MAX = 256
"""Events buffered per subscriber; a client that falls further behind loses the oldest."""
RECENT_MAX = 100

EVENT_NAMES: tuple[str, ...] = (
    # scans (service.intake, service.scan_lifecycle, service.retention)
    "scan_arrived",
    "scan_invalid",
    "scan_reopened",  # late slices of a recorded series
    "scan_replaced",  # an instance of a judged series replaced with different bytes, or removed
    "scan_files_deleted",  # the retention policy deleted a scan's folder
    # registrations and verifications (service.orchestrator)
    "registration_done",
    "registration_refused",
    "registration_withdrawn",  # its scan was reopened: incomplete when registered (design §9)
    "derived_withdrawn",  # verifications / calibrations made from a scan whose content changed
    "verification_done",
    # the robot link (service.capture)
    "link_state",
    # operating-room interfaces (service.or_integration)
    "dicom_association_released",
    "dicom_association_aborted",
    "dicom_refused",
    "igtl_client_connected",
    "igtl_client_disconnected",
    "igtl_client_header_version",  # it sent header version 2: answered in version 2 from now on
    # calibration sessions (service.calibration_jobs); registration_retired says none is current
    # any more (push channels INVALID until the next /register)
    "calibration_started",
    "calibration_progress",
    "calibration_done",
    "calibration_refused",
    "calibration_activated",
    "calibration_deactivated",  # the active calibration was withdrawn: the nominal model again
    "registration_retired",
    # archiving a registration's SRO to the PACS (service.pacs)
    "pacs_export_sent",
    "pacs_export_failed",
)
"""Every event :meth:`EventBus.publish` accepts (one tuple; a new event is added here)."""


class EventBus:
    """Fan-out of service events to SSE subscribers.  :meth:`publish` is callable from any thread."""

    def __init__(self) -> None:
        self._loop: asyncio.AbstractEventLoop | None = None
        self._subs: set[asyncio.Queue[tuple[int, str, dict[str, Any]] | None]] = set()
        self._seq = itertools.count(1)
        self._lock = threading.Lock()
        self._recent: deque[tuple[int, str, dict[str, Any]]] = deque(maxlen=RECENT_MAX)
        self._closed = False
        self._listeners: dict[str, list[Callable[[dict[str, Any]], None]]] = {}

    def listen(self, event: str, fn: Callable[[dict[str, Any]], None]) -> None:
        """Call ``fn(data)`` on the publishing thread after each ``event`` has gone to the subscribers
        (the in-process reactions: IGTL push, PACS export, auto-register)."""
        if event not in EVENT_NAMES:
            raise ValueError(f"unknown event {event!r}; known: {EVENT_NAMES}")
        with self._lock:
            self._listeners.setdefault(event, []).append(fn)

    def unlisten(self, event: str, fn: Callable[[dict[str, Any]], None]) -> None:
        with self._lock:
            fns = self._listeners.get(event, [])
            if fn in fns:
                fns.remove(fn)

    def bind(self, loop: asyncio.AbstractEventLoop) -> None:
        self._loop = loop
        self._closed = False

    def recent(self) -> list[tuple[int, str, dict[str, Any]]]:
        with self._lock:
            return list(self._recent)

    def publish(self, event: str, data: dict[str, Any]) -> None:
        if event not in EVENT_NAMES:
            raise ValueError(f"unknown event {event!r}; known: {EVENT_NAMES}")
        with self._lock:
            item = (next(self._seq), event, data)
            self._recent.append(item)
            listeners = list(self._listeners.get(event, ()))
        log.info("event %s %s", event, json.dumps(data)[:300])
        self._deliver_on_loop(item)
        for fn in listeners:
            fn(data)

    def _deliver(self, item: tuple[int, str, dict[str, Any]] | None) -> None:
        for q in list(self._subs):
            if q.full():
                with contextlib.suppress(asyncio.QueueEmpty):
                    q.get_nowait()
            q.put_nowait(item)

    def close(self) -> None:
        """End every subscription (called on shutdown, before the server waits for connections)."""
        self._closed = True
        self._deliver_on_loop(None)

    def _deliver_on_loop(self, item: tuple[int, str, dict[str, Any]] | None) -> None:
        """Deliver ``item`` on the server's loop, from that loop or from any other thread."""
        loop = self._loop
        if loop is None or loop.is_closed():
            return
        try:
            running = asyncio.get_running_loop()
        except RuntimeError:
            running = None
        if running is loop:
            self._deliver(item)
        else:
            with contextlib.suppress(RuntimeError):  # loop closing
                loop.call_soon_threadsafe(self._deliver, item)

    async def subscribe(self) -> AsyncIterator[tuple[int, str, dict[str, Any]] | None]:
        """Yield events as they come; ``None`` every :data:`KEEPALIVE_S` of silence; ends on :meth:`close`."""
        q: asyncio.Queue[tuple[int, str, dict[str, Any]] | None] = asyncio.Queue(maxsize=QUEUE_MAX)
        self._subs.add(q)
        try:
            while not self._closed:
                try:
                    item = await asyncio.wait_for(q.get(), KEEPALIVE_S)
                except TimeoutError:
                    yield None
                    continue
                if item is None:
                    return
                yield item
        finally:
            self._subs.discard(q)

    @property
    def n_subscribers(self) -> int:
        return len(self._subs)
