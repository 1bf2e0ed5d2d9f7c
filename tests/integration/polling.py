"""Deadline polling for the link tests: wait on a condition, never sleep a fixed time."""

from __future__ import annotations

import asyncio
import time
from collections.abc import Callable

DEADLINE_S = 5.0


async def wait_until(pred: Callable[[], bool], what: str, timeout_s: float = DEADLINE_S) -> None:
    """Poll ``pred`` every 2 ms until it holds; fail naming ``what`` after ``timeout_s``."""
    deadline = time.monotonic() + timeout_s
    while not pred():
        if time.monotonic() > deadline:
            raise AssertionError(f"timed out after {timeout_s} s waiting for {what}")
        await asyncio.sleep(0.002)
