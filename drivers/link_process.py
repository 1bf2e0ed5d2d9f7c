"""A robot link read in a child process of its own, so nothing the service does can starve it.

While C-STORE instances were decoded, the in-process reader thread could not get
the GIL for 0.26-0.35 s and the joint history showed receive gaps the robot never had.
:class:`ProcessLink` runs the ordinary link (:func:`drivers.factory.open_link`) in a child Python
process (``python -m drivers.link_process URL``) that does nothing else: it stamps every frame with
``time.monotonic()`` when its bytes arrive (CLOCK_MONOTONIC is system-wide on Linux, so the stamps
are comparable with the parent's clock) and forwards the states, the health, the controller status,
the counters, the transport sessions and its log records over a pipe.  The parent keeps the same
ring buffer and offers the same :class:`drivers.base.RobotLink` interface; a busy parent reads the
pipe late, but the stamps were taken in the child.

The child dies with its parent, so it never keeps the controller's single Feedback connection: it
exits when its stdin reaches end of file (the parent closed it or died: the kernel closes the
parent's end) and, should another process have inherited that end, when its parent process id
changes (checked every :data:`PARENT_CHECK_S`).  ``kill -9`` of the service ends the child within
that time (tests/faults/test_stillness_health.py).  A child that dies on its own is restarted after
``backoff_max_s``; the link is ``down`` meanwhile.

Wire (child → parent, stdout): 4-byte big-endian length + pickle of one tuple; the parent trusts
only its own child.  ``("states", [(joints, t_s, received_at_posix, session), ...])``,
``("statuses", [status_tuple, ...])`` (every controller STATUS, sent before the states read with
it, for the stillness check's ``in_motion``), ``("meta", health_state, reason, status_or_None,
counters, sessions)``, ``("log", level, name, msg)``.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import os
import pickle
import struct
import subprocess
import sys
import threading
import time
from collections.abc import AsyncIterator
from dataclasses import astuple
from datetime import UTC, datetime
from types import TracebackType
from typing import IO, Any, Self

from drivers.base import (
    CONNECT_TIMEOUT_S,
    JointRing,
    JointState,
    LinkHealth,
    LinkSession,
    RobotStatus,
)
from drivers.errors import LinkTimeoutError, RobotLinkError

log = logging.getLogger(__name__)

PARENT_CHECK_S = 0.2
"""How often the child checks that its parent is alive (s): the bound on how long it outlives a
``kill -9`` of the service when its stdin end was inherited elsewhere."""

META_PERIOD_S = 0.05
"""How often the child sends health, status, counters and sessions (s; 2.5 frames at 50 Hz)."""

RESTART_DELAY_S = 0.5
"""Wait before restarting a child that died on its own (s; the links' ``backoff_max_s`` default)."""

CLOSE_TIMEOUT_S = 3.0
"""Upper bound on :meth:`ProcessLink.close` (s): the child's own link close (2 s) plus margin;
then the child is killed."""

_LEN = struct.Struct(">I")


# --------------------------------------------------------------------------- child


class _PipeLog(logging.Handler):
    def __init__(self, send: Any) -> None:
        super().__init__()
        self._send = send

    def emit(self, record: logging.LogRecord) -> None:
        with contextlib.suppress(Exception):
            self._send(("log", record.levelno, record.name, record.getMessage()))


def child_main(url: str, options: dict[str, Any]) -> int:
    """The child: open the link, forward everything to stdout until stdin closes or the parent dies."""
    from drivers.factory import open_link

    out = sys.stdout.buffer
    lock = threading.Lock()
    parent = os.getppid()

    def send(msg: tuple[Any, ...]) -> None:
        data = pickle.dumps(msg, protocol=pickle.HIGHEST_PROTOCOL)
        with lock:
            out.write(_LEN.pack(len(data)) + data)
            out.flush()

    root = logging.getLogger()
    root.handlers[:] = [_PipeLog(send)]
    root.setLevel(logging.INFO)
    stop = threading.Event()

    def watch_stdin() -> None:
        with contextlib.suppress(OSError):
            while sys.stdin.buffer.read(1):
                pass
        stop.set()

    threading.Thread(target=watch_stdin, name="link-process stdin", daemon=True).start()
    link = open_link(url, **options)
    link.start()
    sent = sent_statuses = 0
    next_meta = next_parent = 0.0
    try:
        while not stop.is_set():
            link.wait_appended(sent, META_PERIOD_S)
            statuses, sent_statuses = link.statuses_since(sent_statuses)  # before the states: see above
            if statuses:
                send(("statuses", [astuple(st) for st in statuses]))
            states, sent = link.appended_since(sent)
            if states:
                send(
                    ("states", [(s.joints_rad, s.t_s, s.received_at.timestamp(), s.session) for s in states])
                )
            now = time.monotonic()
            if now >= next_meta:
                next_meta = now + META_PERIOD_S
                h, st = link.health(), link.status()
                send(("meta", h.state, h.reason, None if st is None else astuple(st), link.counters(),
                      [astuple(x) for x in link.sessions()]))  # fmt: skip
            if now >= next_parent:
                next_parent = now + PARENT_CHECK_S
                if os.getppid() != parent:
                    break
    except (BrokenPipeError, OSError):
        pass  # the parent is gone
    finally:
        asyncio.run(link.close())
    return 0


# --------------------------------------------------------------------------- parent


class ProcessLink:
    """A :class:`drivers.base.RobotLink` whose reader runs in a child process (see module doc).

    Parameters
    ----------
    url : str
        Any link URL :func:`drivers.factory.open_link` accepts (validated here, in the parent).
    **options
        Passed to the child's ``open_link``.
    """

    def __init__(self, url: str, **options: Any) -> None:
        from drivers.factory import open_link

        probe = open_link(url, **options)  # validates the URL and options; never started
        self.url = url
        self.streamed = probe.streamed
        self.frame_period_s = probe.frame_period_s
        self.stale_after_s = probe.stale_after_s
        self.close_timeout_s = CLOSE_TIMEOUT_S
        self._options = options
        self.history_s = probe.history_s
        self.joint_resolution_rad = probe.joint_resolution_rad
        """The wire's rounding, as the link in the child states it (the probe is never started)."""
        self._ring: JointRing[JointState] = JointRing(probe.history_s)
        self._lock = threading.Lock()
        self._transport_up = False
        self._reason = "not connected yet (call connect())"
        self._status: RobotStatus | None = None
        self._statuses: JointRing[RobotStatus] = JointRing(probe.history_s)
        self._counters: dict[str, int] = {}
        self._sessions: list[LinkSession] = []
        self._proc: subprocess.Popen[bytes] | None = None
        self._reader: threading.Thread | None = None
        self._closing = threading.Event()
        self._first = threading.Event()
        self.restarts = 0

    # ---- lifecycle -----------------------------------------------------------------------

    def start(self) -> None:
        """Start the child and the thread that reads it (idempotent; returns at once)."""
        if self._reader is not None:
            return
        self._closing.clear()
        self._first.clear()
        self._spawn()
        self._reader = threading.Thread(
            target=self._read_loop, name=f"robot-link-process {self.url}", daemon=True
        )
        self._reader.start()

    async def connect(self, timeout_s: float = CONNECT_TIMEOUT_S) -> None:
        """Start and wait for the first valid joint state (:meth:`drivers.base.BaseLink.connect`)."""
        self.start()
        if not await asyncio.to_thread(self._first.wait, timeout_s):
            reason = self.health().reason
            await self.close()
            raise LinkTimeoutError(f"no valid joint frame from {self.url} within {timeout_s:g} s ({reason})")
        if self._closing.is_set():
            raise RobotLinkError(f"{self.url}: the link was closed while connecting")

    async def close(self) -> None:
        """Close the child's stdin (it closes its link and exits), kill it after
        :data:`CLOSE_TIMEOUT_S`, join the reader thread."""
        self._closing.set()
        self._first.set()
        reader, self._reader = self._reader, None
        await asyncio.to_thread(self._stop_child)
        if reader is not None:
            await asyncio.to_thread(reader.join, self.close_timeout_s)
        with self._lock:
            self._transport_up = False
            self._reason = "closed"

    async def __aenter__(self) -> Self:
        await self.connect()
        return self

    async def __aexit__(
        self, et: type[BaseException] | None, e: BaseException | None, tb: TracebackType | None
    ) -> None:
        await self.close()

    @property
    def running(self) -> bool:
        r = self._reader
        return r is not None and r.is_alive()

    @property
    def pid(self) -> int | None:
        """The child's process id (None when not running)."""
        p = self._proc
        return p.pid if p is not None and p.poll() is None else None

    # ---- accessors (any thread) ------------------------------------------------------------

    def latest(self) -> JointState | None:
        return self._ring.latest()

    def history(self, since_t_s: float) -> list[JointState]:
        return self._ring.since(since_t_s)

    def history_span_s(self, since_t_s: float) -> float:
        return self._ring.span_s(since_t_s)

    def max_receive_gap_s(self, since_t_s: float) -> float | None:
        return self._ring.max_gap_s(since_t_s)

    def wait_past(self, t_s: float, timeout_s: float) -> bool:
        return self._ring.wait_past(t_s, timeout_s)

    def status(self) -> RobotStatus | None:
        with self._lock:
            return self._status

    def status_history(self, since_t_s: float) -> list[RobotStatus]:
        """As :meth:`drivers.base.BaseLink.status_history` (the child's receive stamps)."""
        return self._statuses.since(since_t_s)

    def counters(self) -> dict[str, int]:
        with self._lock:
            return {**self._counters, "process_restarts": self.restarts}

    def sessions(self) -> list[LinkSession]:
        with self._lock:
            return list(self._sessions)

    def health(self, now_t_s: float | None = None) -> LinkHealth:
        """As :meth:`drivers.base.BaseLink.health`; the frame age uses the child's receive stamps."""
        now = time.monotonic() if now_t_s is None else now_t_s
        last = self._ring.latest()
        age = None if last is None else max(0.0, now - last.t_s)
        with self._lock:
            up, reason = self._transport_up, self._reason
        if not up:
            return LinkHealth("down", reason, age)
        if age is None:
            return LinkHealth("stale", "connected, no valid joint frame received yet", None)
        if age > self.stale_after_s:
            return LinkHealth(
                "stale", f"no valid joint frame for {age:.3f} s (> {self.stale_after_s:g} s)", age
            )
        return LinkHealth("connected", "receiving joint frames", age)

    async def stream(self) -> AsyncIterator[JointState]:
        """Every state from now on until :meth:`close` (polled from the ring; for the CLI and tests)."""
        seen = self._ring.total()
        while not self._closing.is_set():
            if not await asyncio.to_thread(self._ring.wait_appended, seen, 0.1):
                continue
            states, seen = self._ring.appended_since(seen)
            for s in states:
                yield s

    # ---- internals -------------------------------------------------------------------------

    def _spawn(self) -> None:
        cmd = [sys.executable, "-m", "drivers.link_process", self.url, repr(self._options)]
        self._proc = subprocess.Popen(cmd, stdin=subprocess.PIPE, stdout=subprocess.PIPE, bufsize=0)
        log.info("robot link %s: reading in child process %d", self.url, self._proc.pid)

    def _stop_child(self) -> None:
        p = self._proc
        if p is None:
            return
        if p.stdin is not None:
            with contextlib.suppress(OSError):
                p.stdin.close()
        try:
            p.wait(self.close_timeout_s)
        except subprocess.TimeoutExpired:
            log.error("robot link %s: child %d did not exit %.3g s after close(); killed",
                      self.url, p.pid, self.close_timeout_s)  # fmt: skip
            p.kill()
            p.wait(self.close_timeout_s)

    def _read_loop(self) -> None:
        while True:
            p = self._proc
            assert p is not None and p.stdout is not None
            self._read_child(p.stdout)
            code = p.wait()
            if p.stdout is not None:
                p.stdout.close()
            with self._lock:
                self._transport_up = False
                self._reason = "closed" if self._closing.is_set() else f"link process exited with code {code}"
            if self._closing.wait(RESTART_DELAY_S):
                return
            log.error("robot link %s: child process exited with code %s; restarting", self.url, code)
            if p.stdin is not None:
                with contextlib.suppress(OSError):
                    p.stdin.close()
            self.restarts += 1
            self._spawn()

    def _read_child(self, pipe: IO[bytes]) -> None:
        while True:
            head = _read_exactly(pipe, _LEN.size)
            if head is None:
                return
            body = _read_exactly(pipe, _LEN.unpack(head)[0])
            if body is None:
                return
            self._dispatch(pickle.loads(body))

    def _dispatch(self, msg: tuple[Any, ...]) -> None:
        kind = msg[0]
        if kind == "states":
            for joints, t_s, posix, session in msg[1]:
                self._ring.append(
                    JointState(tuple(joints), t_s, datetime.fromtimestamp(posix, UTC), self.url, session)
                )
            self._first.set()
        elif kind == "statuses":
            for st in msg[1]:
                self._statuses.append(RobotStatus(*st))
        elif kind == "meta":
            _, state, reason, status, counters, sessions = msg
            with self._lock:
                self._transport_up = state != "down"
                self._reason = reason
                self._status = None if status is None else RobotStatus(*status)
                self._counters = dict(counters)
                self._sessions = [LinkSession(*s) for s in sessions]
        elif kind == "log":
            _, level, name, text = msg
            logging.getLogger(name).log(level, "%s", text)


def _read_exactly(pipe: IO[bytes], n: int) -> bytes | None:
    buf = bytearray()
    while len(buf) < n:
        chunk = pipe.read(n - len(buf))
        if not chunk:
            return None
        buf += chunk
    return bytes(buf)


if __name__ == "__main__":
    import ast

    raise SystemExit(child_main(sys.argv[1], ast.literal_eval(sys.argv[2]) if len(sys.argv) > 2 else {}))
