"""Deadline polling for the tests: wait on a condition, never sleep a fixed time."""

from __future__ import annotations

import asyncio
import threading
import time
from collections.abc import Callable
from typing import Any

DEADLINE_S = 5.0
SERVICE_DEADLINE_S = 60.0
"""How long the service tests wait for a state change (a loaded 2-core CI machine)."""


async def wait_until(pred: Callable[[], bool], what: str, timeout_s: float = DEADLINE_S) -> None:
    """Poll ``pred`` every 2 ms until it holds; fail naming ``what`` after ``timeout_s``."""
    deadline = time.monotonic() + timeout_s
    while not pred():
        if time.monotonic() > deadline:
            raise AssertionError(f"timed out after {timeout_s} s waiting for {what}")
        await asyncio.sleep(0.002)


def poll_until(pred: Callable[[], Any], what: str, timeout_s: float, interval_s: float = 0.05) -> Any:
    """Call ``pred`` until it returns something truthy and return that; fail naming ``what`` after
    ``timeout_s``.  For threads and blocking clients (the service tests); a deadline, never a sleep
    standing in for synchronisation."""
    deadline = time.monotonic() + timeout_s
    tick = threading.Event()
    while True:
        v = pred()
        if v:
            return v
        if time.monotonic() > deadline:
            raise AssertionError(f"timed out after {timeout_s} s waiting for {what}")
        tick.wait(interval_s)


def wait_for(
    pred: Callable[[], Any], what: str, timeout_s: float = SERVICE_DEADLINE_S, interval_s: float = 0.05
) -> Any:
    """:func:`poll_until` with the service tests' deadline: the truthy value ``pred`` returned."""
    return poll_until(pred, what, timeout_s, interval_s)


def wait_robot_still(client: Any, robot: Any, window_s: float, timeout_s: float) -> None:
    """Wait until the mock ``robot`` has been still for ``window_s`` and the service's link
    (``GET /status`` through the httpx ``client``) is connected with that much joint history."""
    end = robot.motion_end_t_s()

    def ok() -> bool:
        st = client.get("/status").json()["link"]
        covered = st["history_s"] > window_s and time.monotonic() > end + window_s
        return bool(st["state"] == "connected" and covered)

    poll_until(ok, "the robot to be still with joint history covering the stillness window", timeout_s)
