"""The in-process event bus behind ``GET /events`` (:mod:`service.http.api.events`).

Events are the typed classes of :mod:`service.events`; :meth:`EventBus.publish` takes one, is
callable from any thread, serialises it once (:meth:`service.events.Event.payload`) and hands it to
the SSE subscribers and to the in-process listeners bound to its class (:meth:`EventBus.listen`).

No listener can break the bus: one that raises is logged with the event and counted
(:meth:`EventBus.listener_failures`, on ``GET /status``), the listeners after it still run and the
publisher never sees the exception.  A listener bound with ``safety=True`` carries a safety duty
(telling navigation about a new or refused registration): while its last call failed,
:meth:`EventBus.failing_safety_listeners` names it and ``GET /ready`` answers 503
(:mod:`service.http.health`); its next successful call clears that.
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
from dataclasses import dataclass, replace
from typing import Any, TypeVar

from service.events import EVENT_NAMES, EVENT_TYPES, Event

__all__ = ["EVENT_NAMES", "EventBus", "ListenerFailures", "Published", "Subscriptions"]

log = logging.getLogger(__name__)

KEEPALIVE_S = 15.0
"""Comment interval on idle streams (proxies commonly drop connections idle for 30–60 s)."""
QUEUE_MAX = 256
"""Events buffered per subscriber; a client that falls further behind loses the oldest."""
RECENT_MAX = 100

E = TypeVar("E", bound=Event)
_KNOWN: frozenset[type[Event]] = frozenset(EVENT_TYPES)


@dataclass(frozen=True)
class Published:
    """One published event: its sequence number (the SSE ``id:``), the event, its JSON ``data``."""

    seq: int
    event: Event
    data_json: str


@dataclass(frozen=True)
class ListenerFailures:
    """How often one listener raised on one event class (since the service started)."""

    listener: str
    """The listener's qualified name, e.g. ``IgtlPublisher.on_registration_done``."""
    event: str
    """The event's wire name."""
    safety: bool
    """Bound with ``safety=True``: while ``failing``, the service is not ready."""
    failures: int
    failing: bool
    """Its last call raised (cleared by its next successful call)."""
    last_error: str
    """``Type: message`` of the last exception."""

    def describe(self) -> str:
        state = "its last call failed" if self.failing else "its last call succeeded"
        return (
            f"listener {self.listener} failed {self.failures} time(s) on {self.event} ({state}; last: "
            f"{self.last_error})"
        )


@dataclass(frozen=True)
class _Listener:
    fn: Callable[[Any], None]
    safety: bool
    name: str


class EventBus:
    """Fan-out of service events to SSE subscribers.  :meth:`publish` is callable from any thread."""

    def __init__(self) -> None:
        self._loop: asyncio.AbstractEventLoop | None = None
        self._subs: set[asyncio.Queue[Published | None]] = set()
        self._seq = itertools.count(1)
        self._lock = threading.Lock()
        self._recent: deque[Published] = deque(maxlen=RECENT_MAX)
        self._closed = False
        self._listeners: dict[type[Event], list[_Listener]] = {}
        """Per event class; each callable takes that class (``listen`` keeps the pairing typed)."""
        self._failures: dict[tuple[str, str], ListenerFailures] = {}
        """Per (listener name, event name) that has raised at least once."""

    def listen(self, kind: type[E], fn: Callable[[E], None], *, safety: bool = False) -> None:
        """Call ``fn(event)`` on the publishing thread after each ``kind`` event has gone to the
        subscribers (the in-process reactions: IGTL push, PACS export, auto-register).

        ``safety``: ``fn`` carries a safety duty; while its last call failed the service is not
        ready (see the module docstring)."""
        _check_kind(kind)
        name = getattr(fn, "__qualname__", None) or repr(fn)
        with self._lock:
            self._listeners.setdefault(kind, []).append(_Listener(fn, safety, name))

    def unlisten(self, kind: type[E], fn: Callable[[E], None]) -> None:
        with self._lock:
            bound = self._listeners.get(kind, [])
            for i, one in enumerate(bound):
                if one.fn == fn:
                    del bound[i]
                    return

    def listener_failures(self) -> list[ListenerFailures]:
        """Every listener that has raised, with its count (for ``GET /status``)."""
        with self._lock:
            return list(self._failures.values())

    def failing_safety_listeners(self) -> list[ListenerFailures]:
        """The safety listeners whose last call raised (for ``GET /ready``)."""
        return [f for f in self.listener_failures() if f.safety and f.failing]

    def bind(self, loop: asyncio.AbstractEventLoop) -> None:
        self._loop = loop
        self._closed = False

    def recent(self) -> list[Published]:
        """The last :data:`RECENT_MAX` events, oldest first."""
        with self._lock:
            return list(self._recent)

    def publish(self, event: Event) -> None:
        kind = type(event)
        _check_kind(kind)
        data_json = json.dumps(event.payload())
        with self._lock:
            item = Published(next(self._seq), event, data_json)
            self._recent.append(item)
            listeners = list(self._listeners.get(kind, ()))
        log.info("event %s %s", event.name, data_json[:300])
        self._deliver_on_loop(item)
        for one in listeners:
            self._call(one, item)

    def _call(self, one: _Listener, item: Published) -> None:
        """Run one listener; what it raises is logged and counted, never passed to the publisher."""
        key = (one.name, item.event.name)
        try:
            one.fn(item.event)
        except Exception as e:
            with self._lock:
                was = self._failures.get(key) or ListenerFailures(*key, one.safety, 0, False, "")
                self._failures[key] = replace(
                    was, failures=was.failures + 1, failing=True, last_error=f"{type(e).__name__}: {e}"[:500]
                )
            log.exception(
                "event bus: listener %s failed on event %s #%d %s (%s; the other listeners still run)",
                one.name, item.event.name, item.seq, item.data_json[:300],
                "a SAFETY listener: the service is not ready until it next succeeds"
                if one.safety else "counted on GET /status",
            )  # fmt: skip
            return
        if key in self._failures:  # it failed before: this success ends that
            with self._lock:
                was = self._failures[key]
                self._failures[key] = replace(was, failing=False)
            if was.failing:
                log.warning("event bus: listener %s succeeded again on %s", one.name, item.event.name)

    def _deliver(self, item: Published | None) -> None:
        for q in list(self._subs):
            if q.full():
                with contextlib.suppress(asyncio.QueueEmpty):
                    q.get_nowait()
            q.put_nowait(item)

    def close(self) -> None:
        """End every subscription (called on shutdown, before the server waits for connections)."""
        self._closed = True
        self._deliver_on_loop(None)

    def _deliver_on_loop(self, item: Published | None) -> None:
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

    async def subscribe(self) -> AsyncIterator[Published | None]:
        """Yield events as they come; ``None`` every :data:`KEEPALIVE_S` of silence; ends on :meth:`close`."""
        q: asyncio.Queue[Published | None] = asyncio.Queue(maxsize=QUEUE_MAX)
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


def _check_kind(kind: type[Event]) -> None:
    if kind not in _KNOWN:
        raise TypeError(
            f"{kind.__name__} is not a service event; the events are the classes of service.events "
            f"({', '.join(EVENT_NAMES)})"
        )


class Subscriptions:
    """Listeners bound together and removed together (:meth:`close` is idempotent)."""

    def __init__(self, bus: EventBus) -> None:
        self.bus = bus
        self._bound: list[tuple[type[Event], Callable[[Any], None]]] = []

    def listen(self, kind: type[E], fn: Callable[[E], None], *, safety: bool = False) -> None:
        self.bus.listen(kind, fn, safety=safety)
        self._bound.append((kind, fn))

    def close(self) -> None:
        while self._bound:
            kind, fn = self._bound.pop()
            self.bus.unlisten(kind, fn)
