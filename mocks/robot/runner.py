"""Run a mock controller in a background thread with its own event loop.

::

    robot = ScriptedRobot()
    with run_mock_controller("simple-message", robot) as mock:
        link = open_link(mock.url)          # e.g. simple-message://127.0.0.1:40123
        ...
        mock.disconnect(down_s=0.5)         # fault injection, from any thread

``kind`` is ``"simple-message"``, ``"modbus"`` or ``"serial"`` (the URL
schemes).  The context manager starts the server, waits until it listens,
and on exit stops it and joins the thread.
"""

from __future__ import annotations

import asyncio
import threading
import time
from collections.abc import Callable, Coroutine, Iterator
from contextlib import contextmanager
from typing import Any, TypeVar

from mocks.robot.robot import ScriptedRobot

KINDS = ("simple-message", "modbus", "serial")
CALL_TIMEOUT_S = 10.0
"""How long a call into the server thread may take (start, stop, a fault)."""

T = TypeVar("T")


class MockController:
    """Handle on a running mock server (see :func:`run_mock_controller`)."""

    def __init__(self, kind: str, server: Any, loop: asyncio.AbstractEventLoop) -> None:
        self.kind = kind
        self.server = server
        self._loop = loop

    @property
    def url(self) -> str:
        return str(self.server.url)

    # ---- thread bridge -------------------------------------------------------

    def call(self, fn: Callable[[], T]) -> T:
        """Run ``fn()`` on the server's loop and return its result."""

        async def wrapper() -> T:
            return fn()

        return self.run(wrapper())

    def run(self, coro: Coroutine[Any, Any, T], timeout_s: float = CALL_TIMEOUT_S) -> T:
        return asyncio.run_coroutine_threadsafe(coro, self._loop).result(timeout_s)

    def _fault(self, name: str, *args: Any, **kwargs: Any) -> Any:
        fn = getattr(self.server, name, None)
        if fn is None:
            raise NotImplementedError(f"the {self.kind} mock does not support fault {name!r}")
        if asyncio.iscoroutinefunction(fn):
            return self.run(fn(*args, **kwargs), timeout_s=CALL_TIMEOUT_S + float(kwargs.get("down_s", 0)))
        return self.call(lambda: fn(*args, **kwargs))

    # ---- faults --------------------------------------------------------------

    def stall(self) -> None:
        """Stop sending (connection stays open) until :meth:`resume`."""
        self._fault("stall")

    def resume(self) -> None:
        self._fault("resume")

    def disconnect(self, down_s: float = 0.5) -> float:
        """Drop every client and refuse connections for ``down_s``; returns the
        ``time.monotonic()`` instant the mock is back (blocks until then)."""
        self._fault("disconnect", down_s=down_s)
        t = self.server.returned_t_s
        assert t is not None
        return float(t)

    def inject_garbage(self, data: bytes = b"\xde\xad\xbe\xef" * 8) -> None:
        """Write ``data`` into the stream before the next frame."""
        self._fault("inject_raw", data)

    def inject_oversized_prefix(self, length: int = 0x7FFFFFFF) -> None:
        """Write a length prefix of ``length`` bytes (default 2 GiB − 1), then keep streaming."""
        self._fault("inject_raw", length.to_bytes(4, "little", signed=True))

    def inject_nan(self, n_frames: int = 1, joint: int = 0) -> None:
        """NaN in joint ``joint`` of the next ``n_frames`` joint frames."""
        self._fault("inject_nan", n_frames, joint)

    def set_split_frames(self, enabled: bool = True) -> None:
        """Send every byte in its own write."""
        self._fault("set_split_frames", enabled)

    def frames_sent(self) -> int:
        """Joint frames (or Modbus joint reads, or serial joint lines) sent so far."""
        return int(self.call(lambda: self.server.joint_frames_sent))

    def bytes_from_clients(self) -> int:
        return int(self.call(lambda: self.server.bytes_from_clients))


def _make_server(kind: str, robot: ScriptedRobot, host: str, port: int, options: dict[str, Any]) -> Any:
    if kind == "simple-message":
        from mocks.robot.simple_message_server import SimpleMessageServer

        return SimpleMessageServer(robot, host, port, **options)
    if kind == "modbus":
        from mocks.robot.modbus_server import ModbusMockServer

        return ModbusMockServer(robot, host, port, **options)
    if kind == "serial":
        from mocks.robot.serial_mock import SerialMock

        return SerialMock(robot, **options)
    raise ValueError(f"unknown mock controller kind {kind!r}; expected one of {KINDS}")


@contextmanager
def run_mock_controller(
    kind: str, robot: ScriptedRobot, host: str = "127.0.0.1", port: int = 0, **options: Any
) -> Iterator[MockController]:
    """Start a mock controller of ``kind`` serving ``robot``; yields a :class:`MockController`.

    ``options`` go to the server class (e.g. ``period_s``, ``register_map`` for Modbus).
    """
    server = _make_server(kind, robot, host, port, options)
    loop = asyncio.new_event_loop()
    started = threading.Event()
    failure: list[BaseException] = []

    def main() -> None:
        asyncio.set_event_loop(loop)
        try:
            loop.run_until_complete(server.start())
        except BaseException as e:  # report start failures to the caller
            failure.append(e)
            started.set()
            loop.close()
            return
        started.set()
        loop.run_forever()
        try:
            loop.run_until_complete(server.stop())
            pending = [t for t in asyncio.all_tasks(loop) if not t.done()]
            for t in pending:
                t.cancel()
            loop.run_until_complete(asyncio.gather(*pending, return_exceptions=True))
            loop.run_until_complete(loop.shutdown_asyncgens())
        finally:
            loop.close()

    thread = threading.Thread(target=main, name=f"mock-{kind}", daemon=True)
    thread.start()
    if not started.wait(CALL_TIMEOUT_S):
        raise TimeoutError(f"mock {kind} controller did not start within {CALL_TIMEOUT_S} s")
    if failure:
        thread.join(CALL_TIMEOUT_S)
        raise failure[0]
    try:
        yield MockController(kind, server, loop)
    finally:
        loop.call_soon_threadsafe(loop.stop)
        deadline = time.monotonic() + CALL_TIMEOUT_S
        thread.join(max(0.0, deadline - time.monotonic()))
