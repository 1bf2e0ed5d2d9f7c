"""The service's Capture over a real link (issue #9): one reconnect policy, the link's own.

Capture starts the link and watches its health; it never calls ``connect()`` and never
retries.  The link reconnects by itself after the controller drops it.
"""

from __future__ import annotations

import asyncio
import math
import threading
from pathlib import Path
from typing import Any

from polling import wait_until

from drivers.factory import open_link
from mocks.robot.robot import ScriptedRobot
from mocks.robot.runner import run_mock_controller
from service.events import Event, LinkState
from service.intake.capture import Capture

Q = [math.radians(d) for d in (12.5, -33.25, 101.0, -7.75, 44.125, 170.0)]


def _settings(tmp_path: Path) -> Any:
    from service.settings import load_settings

    return load_settings(None, {"watch_dir": tmp_path / "w", "data_dir": tmp_path / "d"})


def test_capture_relies_on_the_links_reconnect_and_leaves_nothing(tmp_path: Path) -> None:
    events: list[Event] = []
    lock = threading.Lock()

    def publish(event: Event) -> None:
        with lock:
            events.append(event)

    def states() -> list[str]:
        with lock:
            return [e.state for e in events if isinstance(e, LinkState)]

    def after_first(state: str, then: str) -> bool:
        seq = states()
        return state in seq and then in seq[seq.index(state) :]

    async def main() -> None:
        with run_mock_controller("simple-message", ScriptedRobot(Q)) as mock:
            link = open_link(mock.url)

            async def no_connect(timeout_s: float = 0.0) -> None:
                raise AssertionError("Capture must not call connect(): the link reconnects by itself")

            link.connect = no_connect  # type: ignore[method-assign]
            cap = Capture(link, _settings(tmp_path), publish)
            await cap.start()
            await wait_until(lambda: "connected" in states(), "a 'connected' event", 10.0)
            back = asyncio.create_task(asyncio.to_thread(mock.disconnect, 0.4))
            await wait_until(lambda: after_first("connected", "down"), "a 'down' event after connecting")
            t_back = await back
            await wait_until(lambda: cap.latest() is not None and cap.latest().t_s > t_back, "frames again")
            await wait_until(lambda: states()[-1] == "connected", "a 'connected' event after the drop")
            await cap.stop()
            assert link.counters()["connects"] >= 2
            assert not link.running
            assert asyncio.all_tasks() == {asyncio.current_task()}

    asyncio.run(main())
    seq = states()
    dropped = seq.index("down", seq.index("connected"))  # the first 'down' after connecting
    assert "connected" in seq[dropped:], seq
