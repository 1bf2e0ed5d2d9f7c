"""An asyncio event loop on a thread of its own: where a robot link reads its transport.

The link must not share the service's event loop: a large HTTP request body
being parsed or a CPU-bound handler would delay the link's reads, so frames
would be stamped late and the joint history would show gaps that the robot
never had (and the stillness check would refuse a good scan).  On its own
thread the link's loop wakes as soon as the bytes arrive, whatever the
caller's loop is doing.

:class:`LoopThread` owns one loop and one thread.  :meth:`LoopThread.start`
runs a coroutine to completion on it; when that coroutine returns, the thread
cancels whatever tasks are left (a bounded wait), closes the loop and ends.
:meth:`LoopThread.join` awaits that end from another loop without blocking it,
with a timeout.
"""

from __future__ import annotations

import asyncio
import concurrent.futures
import logging
import threading
from collections.abc import Callable, Coroutine
from typing import Any, TypeVar

log = logging.getLogger(__name__)

T = TypeVar("T")

TEARDOWN_TIMEOUT_S = 1.0
"""Default: how long the thread waits for tasks left on its loop after cancelling them (s)."""


class LoopThread:
    """One event loop running on one (daemon) thread.

    Parameters
    ----------
    name : str
        Thread name (shown in leak reports and debuggers).
    teardown_timeout_s : float
        How long the thread waits for tasks left on its loop after cancelling them (s).
    """

    def __init__(self, name: str, *, teardown_timeout_s: float = TEARDOWN_TIMEOUT_S) -> None:
        self.name = name
        self.teardown_timeout_s = teardown_timeout_s
        self._loop: asyncio.AbstractEventLoop | None = None
        self._thread: threading.Thread | None = None
        self._done: concurrent.futures.Future[None] = concurrent.futures.Future()

    @property
    def loop(self) -> asyncio.AbstractEventLoop:
        if self._loop is None:
            raise RuntimeError(f"{self.name}: the loop thread was not started")
        return self._loop

    @property
    def alive(self) -> bool:
        return self._thread is not None and self._thread.is_alive()

    def start(self, main: Coroutine[Any, Any, None]) -> None:
        """Start the thread and run ``main`` on its loop; the thread ends when ``main`` returns."""
        if self._thread is not None:
            main.close()
            raise RuntimeError(f"{self.name}: already started")
        self._loop = asyncio.new_event_loop()
        self._thread = threading.Thread(
            target=self._target, args=(self._loop, main), name=self.name, daemon=True
        )
        self._thread.start()

    def call_soon(self, fn: Callable[..., object], *args: Any) -> bool:
        """Schedule ``fn(*args)`` on the loop from any thread; False if the loop is already closed."""
        loop = self._loop
        if loop is None:
            return False
        try:
            loop.call_soon_threadsafe(fn, *args)
        except RuntimeError:  # the loop closed in the meantime
            return False
        return True

    def submit(self, coro: Coroutine[Any, Any, T]) -> concurrent.futures.Future[T]:
        """Run ``coro`` on the loop (from any other thread); the returned future is thread-safe."""
        return asyncio.run_coroutine_threadsafe(coro, self.loop)

    async def join(self, timeout_s: float) -> bool:
        """Await the end of the thread from another event loop (that loop keeps running).

        Returns True if the thread ended within ``timeout_s``, else False (logged).
        """
        thread = self._thread
        if thread is None:
            return True
        if not self._done.done():
            try:
                await asyncio.wait_for(asyncio.shield(asyncio.wrap_future(self._done)), timeout_s)
            except TimeoutError:
                log.error("%s: thread did not end within %.3g s; abandoning it", self.name, timeout_s)
                return False
        thread.join(timeout_s)  # it has left _target: returns at once
        return not thread.is_alive()

    def _target(self, loop: asyncio.AbstractEventLoop, main: Coroutine[Any, Any, None]) -> None:
        asyncio.set_event_loop(loop)
        try:
            loop.run_until_complete(main)
        except BaseException:
            log.exception("%s: the loop's main coroutine failed", self.name)
        finally:
            try:
                _cancel_leftovers(loop, self.name, self.teardown_timeout_s)
                loop.run_until_complete(loop.shutdown_asyncgens())
            finally:
                asyncio.set_event_loop(None)
                loop.close()
                self._done.set_result(None)


def _cancel_leftovers(loop: asyncio.AbstractEventLoop, name: str, timeout_s: float) -> None:
    tasks = [t for t in asyncio.all_tasks(loop) if not t.done()]
    if not tasks:
        return
    for t in tasks:
        t.cancel()
    _, pending = loop.run_until_complete(asyncio.wait(tasks, timeout=timeout_s))
    if pending:
        log.error("%s: %d task(s) ignored cancellation; dropped with the loop: %s",
                  name, len(pending), [t.get_name() for t in pending])  # fmt: skip
