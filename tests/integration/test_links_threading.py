"""The link's own thread and loop (issue #9): a blocked caller loop leaves no hole in the joint
history, and close() is bounded and leaves no thread or task behind."""

from __future__ import annotations

import asyncio
import contextlib
import gc
import logging
import math
import threading
import time
from collections.abc import Callable

import numpy as np
import pytest
from polling import wait_until

from drivers.base import FRAME_PERIOD_S, BaseLink
from drivers.errors import RobotLinkError
from drivers.factory import open_link
from mocks.robot.robot import ScriptedRobot
from mocks.robot.runner import run_mock_controller
from registration.model.stillness import DEFAULT_MAX_GAP_S, assess_stillness

Q = [math.radians(d) for d in (12.5, -33.25, 101.0, -7.75, 44.125, 170.0)]
BLOCK_S = 1.0
"""How long the fault keeps the caller's event loop from running (s)."""
MAX_GAP_S = DEFAULT_MAX_GAP_S
"""Largest allowed gap between stamps: the stillness gate itself (0.25 s), since a larger gap is what
would make ``/register`` refuse a still robot.  A link sharing the blocked loop shows ≈ BLOCK_S (1 s);
a tighter bound (5 frame periods) measured the machine's scheduler under load, not the link."""
N_CLOSES = 200


def _sleep_block(duration_s: float) -> None:
    time.sleep(duration_s)  # the injected fault (a blocking call on the service loop), not a wait


def _cpu_block(duration_s: float) -> None:
    end = time.monotonic() + duration_s
    while time.monotonic() < end:  # a CPU-bound handler holding the GIL between switches
        sum(i * i for i in range(2000))


def _link_threads() -> list[str]:
    return [t.name for t in threading.enumerate() if t.name.startswith("robot-link")]


@pytest.mark.parametrize(
    ("kind", "block"),
    [("simple-message", _sleep_block), ("modbus", _sleep_block), ("simple-message", _cpu_block)],
    ids=["simple-message-sleep", "modbus-sleep", "simple-message-cpu"],
)
def test_blocked_caller_loop_leaves_no_gap(kind: str, block: Callable[[float], None]) -> None:
    """The caller's loop is blocked for 1 s while the mock streams at 50 Hz.

    Stamps must keep the controller's rhythm (no gap > 5 periods) and, for simple_message,
    each frame's stamp must follow the mock's write within 5 periods.  With a CPU-bound
    block the mock (same process) is itself slowed by the GIL, so there only the per-frame
    latency, which is what the link controls, is asserted.
    """
    cpu = block is _cpu_block

    async def main() -> tuple[list[float], list[float], float, float]:
        with run_mock_controller(kind, ScriptedRobot(Q)) as mock:
            async with open_link(mock.url) as link:
                await wait_until(lambda: len(link.history(0.0)) >= 10, "10 joint frames")
                t_block = time.monotonic()
                block(BLOCK_S)
                t_unblock = time.monotonic()
                await wait_until(lambda: link.latest().t_s > t_unblock + 0.2, "frames after the block")
                sent_t: list[float] = []
                if kind == "simple-message":
                    mock.stall()
                    sent = mock.frames_sent()
                    await wait_until(lambda: link.counters()["frames_accepted"] >= sent, "every frame sent")
                    sent_t = mock.call(lambda: [t for _, t in mock.server.send_log])
                recv_t = [s.t_s for s in link.history(0.0)]
        return recv_t, sent_t, t_block, t_unblock

    recv_t, sent_t, t_block, t_unblock = asyncio.run(main())
    t = np.array(recv_t)
    blocked = (t >= t_block - 0.1) & (t <= t_unblock + 0.1)
    if sent_t:
        latency = t - np.array(sent_t[-len(t) :])
        worst = latency[blocked].max()
        assert worst <= MAX_GAP_S, f"a frame was stamped {worst:.3f} s after its write"
    if cpu:
        return
    gaps = np.diff(t[blocked])
    inside = int(np.count_nonzero((t >= t_block) & (t <= t_unblock)))
    assert gaps.max() <= MAX_GAP_S, f"largest gap {gaps.max():.3f} s"
    # the reader runs on its own thread: a reader blocked with the caller's loop would stamp ~0 frames
    # inside the block; half the 50 Hz rate separates that from a loaded machine's jitter (80 % failed
    # once in CI at 38 of 50 with the Modbus poller, while no gap exceeded MAX_GAP_S)
    assert inside >= 0.5 * (t_unblock - t_block) / FRAME_PERIOD_S, f"{inside} frames while blocked"
    res = assess_stillness(
        t[blocked], np.tile(Q, (int(blocked.sum()), 1)), window_end_t_s=t_unblock,
        window_s=t_unblock - t_block, max_deviation_rad=0.0005, max_gap_s=MAX_GAP_S,
    )  # fmt: skip
    assert res.still, res.reason


@pytest.mark.timeout(240)
@pytest.mark.parametrize("kind", ["simple-message", "modbus"])
def test_close_mid_session_200_times(kind: str) -> None:
    """Close before the transport is up, right after the first frame, and while streaming."""

    async def main() -> None:
        me = asyncio.current_task()
        with run_mock_controller(kind, ScriptedRobot(Q)) as mock:
            for i in range(N_CLOSES):
                link = open_link(mock.url)
                if i % 3 == 0:
                    link.start()
                else:
                    await link.connect()
                if i % 3 == 2:
                    n = link.counters()["frames_accepted"]
                    await wait_until(
                        lambda lk=link, n=n: lk.counters()["frames_accepted"] > n + 1, "streaming"
                    )
                await asyncio.wait_for(link.close(), 2 * link.close_timeout_s)
                assert not link.running, f"close #{i}: the reader thread is still alive"
                assert link.health().state == "down" and link.health().reason == "closed"
                assert _link_threads() == [], f"close #{i}: threads left {_link_threads()}"
                assert asyncio.all_tasks() == {me}, f"close #{i}: tasks left {asyncio.all_tasks()}"

    asyncio.run(main())


class _Stubborn(BaseLink):
    """A session that swallows every cancellation and never checks ``_closing`` (the worst case)."""

    scheme = "stubborn"

    async def _session(self) -> None:
        self._mark_up()
        self._publish_joints(Q)
        while True:
            with contextlib.suppress(asyncio.CancelledError):
                await asyncio.sleep(3600)


def test_close_is_bounded_when_the_session_ignores_cancellation(caplog: pytest.LogCaptureFixture) -> None:
    link = _Stubborn("stubborn://x", close_timeout_s=0.4)

    async def main(link: _Stubborn) -> None:
        await link.connect(timeout_s=5.0)
        await asyncio.wait_for(link.close(), 5.0)  # would hang forever without the bound

    with caplog.at_level(logging.ERROR):
        asyncio.run(main(link))
    assert not link.running and _link_threads() == []
    assert any("did not stop" in r.getMessage() for r in caplog.records)
    # The abandoned reader task is this test's deliberate worst case: drop it with its closed loop
    # so the leak guard judges what the link leaves behind, not the stuck coroutine we built.
    del link
    gc.collect()


def test_connect_then_close_from_another_task_raises_link_error() -> None:
    """A connect() waiting for its first frame ends with a RobotLinkError when the link is closed."""
    link = _Unreachable("unreachable://x")

    async def main() -> None:
        waiting = asyncio.create_task(link.connect(timeout_s=30.0))
        await wait_until(lambda: link.running, "the reader thread")
        await link.close()
        with pytest.raises(RobotLinkError, match="closed while connecting"):
            await waiting

    asyncio.run(main())
    assert _link_threads() == []


class _Unreachable(BaseLink):
    scheme = "unreachable"

    async def _session(self) -> None:
        raise ConnectionRefusedError("refused (test)")


def test_stream_from_the_callers_loop_ends_on_close() -> None:
    async def main() -> None:
        with run_mock_controller("simple-message", ScriptedRobot(Q)) as mock:
            link = open_link(mock.url)
            await link.connect()
            got: list[float] = []

            async def consume() -> None:
                async for s in link.stream():
                    got.append(s.t_s)

            consumer = asyncio.create_task(consume())
            await wait_until(lambda: len(got) >= 5, "5 streamed states")
            await link.close()
            await asyncio.wait_for(consumer, 2.0)  # the stream ended by itself
            assert got == sorted(got) and len(got) >= 5

    asyncio.run(main())


def test_never_connected_health_names_the_error_and_checklist() -> None:
    link = _Unreachable("unreachable://x", backoff_initial_s=0.01, backoff_max_s=0.02)

    async def main() -> None:
        link.start()
        await wait_until(lambda: "refused (test)" in link.health().reason, "the connect error in health")
        h = link.health()
        await link.close()
        assert h.state == "down" and "firewall" in h.reason

    asyncio.run(main())


def test_a_down_link_is_one_warning_then_one_info_when_back(caplog: pytest.LogCaptureFixture) -> None:
    """Issue 34: a controller that is gone was an INFO ConnectionRefusedError every 0.5 s forever.
    Now: one WARNING when the link goes down, the retries counted (DEBUG only), one INFO when back."""
    from urllib.parse import urlsplit

    async def main() -> dict[str, int]:
        with run_mock_controller("simple-message", ScriptedRobot(Q)) as mock:
            url = mock.url
            port = urlsplit(url).port
            link = open_link(url, backoff_initial_s=0.01, backoff_max_s=0.02)
            await link.connect()
        try:  # the controller is gone: many refused reconnects
            await wait_until(lambda: link.counters().get("connect_failures", 0) >= 10, "10 failed reconnects")
            with run_mock_controller("simple-message", ScriptedRobot(Q), port=port or 0):
                await wait_until(lambda: link.health().state == "connected", "reconnected")
                counters = link.counters()
                await link.close()  # before this controller stops: no second outage
            return counters
        finally:
            await link.close()

    with caplog.at_level(logging.DEBUG, logger="drivers.base"):
        counters = asyncio.run(main())
    ours = [r for r in caplog.records if r.name == "drivers.base"]
    warnings = [r.getMessage() for r in ours if r.levelno == logging.WARNING]
    infos = [r.getMessage() for r in ours if r.levelno == logging.INFO]
    assert len(warnings) == 1 and "down" in warnings[0], warnings
    assert not [m for m in infos if "Refused" in m or "refused" in m], infos
    assert sum("connected again" in m for m in infos) == 1, infos
    assert counters["down_events"] == 1 and counters["connect_failures"] >= 10
