"""Moving vs still told apart from each link's recorded joint history (issue #5), one test for
every link kind against its mock over loopback or a pty."""

from __future__ import annotations

import asyncio
import math
import sys
import time

import numpy as np
import pytest
from polling import wait_until

from drivers.factory import open_link
from mocks.robot.robot import ScriptedRobot
from mocks.robot.runner import run_mock_controller
from registration.model.stillness import assess_stillness

Q = [math.radians(d) for d in (12.5, -33.25, 101.0, -7.75, 44.125, 170.0)]
KINDS = [
    "simple-message",
    "modbus",
    pytest.param("serial", marks=pytest.mark.skipif(sys.platform == "win32", reason="pty pairs are POSIX")),
]


@pytest.mark.parametrize("kind", KINDS)
def test_moving_vs_still(kind: str) -> None:
    robot = ScriptedRobot(Q)

    async def main() -> None:
        with run_mock_controller(kind, robot) as mock:
            async with open_link(mock.url) as link:
                t0 = time.monotonic()
                robot.move_to([q + 0.05 for q in Q], duration_s=0.5)
                end = robot.motion_end_t_s()
                await wait_until(lambda: link.latest().t_s > end + 0.5, "0.5 s of holding after the move")
                h = link.history(t0 - 0.1)
                t, q = np.array([s.t_s for s in h]), np.array([s.joints_rad for s in h])
                kw = {"window_s": 0.3, "max_deviation_rad": 0.0005, "max_gap_s": 0.1}
                moving = assess_stillness(t, q, window_end_t_s=t0 + 0.4, **kw)
                still = assess_stillness(t, q, window_end_t_s=t[-1], **kw)
                assert not moving.still and "moved" in moving.reason
                assert still.still, still.reason

    asyncio.run(main())


@pytest.mark.parametrize("kind", [k for k in KINDS if getattr(k, "values", (k,))[0] != "modbus"])
def test_controller_in_motion_reaches_the_stillness_verdict(kind: str) -> None:
    """Issue 31 item 8, per link that carries STATUS: a controller reporting in_motion = TRUE with its
    joints standing still gives ``moved`` with the controller's reason; UNKNOWN (−1) never refuses."""
    from dataclasses import replace

    robot = ScriptedRobot(Q)

    async def main() -> None:
        with run_mock_controller(kind, robot) as mock:
            async with open_link(mock.url) as link:
                for reported, verdict in ((1, "moved"), (-1, "still")):
                    robot.controller_status = replace(robot.controller_status, in_motion=reported)
                    t0 = time.monotonic()

                    def reporting(t0: float = t0, reported: int = reported) -> list[float]:
                        """Receive times of the statuses carrying the new value (a status sent before
                        the change may arrive after it: the window starts at the first new one)."""
                        return [s.t_s for s in link.status_history(t0) if s.in_motion == reported]

                    await wait_until(
                        lambda: len(reporting()) >= 2 and link.latest().t_s > reporting()[0] + 0.4,
                        f"statuses reporting in_motion={reported}",
                    )
                    t1 = reporting()[0]
                    h = [s for s in link.history(t1) if s.t_s >= t1]
                    t, q = np.array([s.t_s for s in h]), np.array([s.joints_rad for s in h])
                    moving_t = [s.t_s for s in link.status_history(t1) if s.in_motion == 1]
                    res = assess_stillness(
                        t,
                        q,
                        window_end_t_s=t[-1],
                        window_s=t[-1] - t[0],
                        max_gap_s=0.2,
                        in_motion_t_s=moving_t,
                    )
                    assert res.verdict == verdict, res
                    assert res.max_deviation_rad == 0.0
                    if verdict == "moved":
                        assert "controller reported in_motion at t=" in res.reason

    asyncio.run(main())
