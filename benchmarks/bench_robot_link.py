"""Robot link: frame arrival → latest() latency, and the CPU cost of a 50 Hz link.

Latency: the mock controller (its own thread and event loop, same process)
stamps ``time.monotonic()`` right after the last of the three writes of each
JOINT_POSITION frame; a consumer of ``link.stream()`` (woken in the same
callback that updates ``latest()``) stamps the moment it sees the new state.
Frames are matched by their (float32) joint values, so the robot moves.

CPU: the mock runs in a separate process (``oarmreg mock robot``), so this
process's CPU time (user + system, ``time.process_time``) over 10 s is the
link's alone, as a % of one core; measured for simple_message (50 Hz push)
and Modbus (50 Hz poll).

Run: ``.venv/bin/python -m benchmarks.bench_robot_link``  (targets: p99 ≤ 2 ms, ≤ 2 % of a core)
"""

from __future__ import annotations

import asyncio
import subprocess
import sys
import time

import numpy as np

from benchmarks.common import print_table
from drivers.factory import open_link
from mocks.robot.robot import ScriptedRobot
from mocks.robot.runner import run_mock_controller

DURATION_S = 10.0


def _moving_robot() -> ScriptedRobot:
    robot = ScriptedRobot()
    robot.run_script({"steps": [{"move_to_rad": [1.0, 0.5, 2.0, 1.0, 1.2, 2.0], "duration_s": 60.0}]})
    return robot


async def _latency(kind: str, seconds: float) -> list[float]:
    with run_mock_controller(kind, _moving_robot()) as mock:
        link = open_link(mock.url)
        await link.connect()
        seen: dict[tuple[float, ...], float] = {}
        t_end = time.monotonic() + seconds
        async for s in link.stream():
            seen[tuple(float(v) for v in np.asarray(s.joints_rad, dtype=np.float32))] = time.monotonic()
            if time.monotonic() > t_end:
                break
        await link.close()
        sent = mock.call(lambda: list(mock.server.send_log))
    lat = [seen[q] - t for q, t in sent if q in seen]
    return [x * 1000.0 for x in lat if x >= 0]


async def _cpu(url: str) -> float:
    """CPU % of one core used by this process while a link to a mock in another process runs."""
    proc = subprocess.Popen(
        [sys.executable, "-m", "service.cli", "mock", "robot", "--link", url],
        stdout=subprocess.PIPE, text=True,
    )  # fmt: skip
    try:
        assert proc.stdout is not None
        bound = proc.stdout.readline().strip()
        link = open_link(bound)
        await link.connect()
        await asyncio.sleep(1.0)  # warm-up
        c0, w0 = time.process_time(), time.monotonic()
        n0 = link.counters()["frames_accepted"]
        await asyncio.sleep(DURATION_S)
        c1, w1 = time.process_time(), time.monotonic()
        n1 = link.counters()["frames_accepted"]
        await link.close()
    finally:
        proc.terminate()
        proc.wait(10)
    print(f"{url.split(':')[0]}: {n1 - n0} frames in {w1 - w0:.1f} s", file=sys.stderr)
    return 100.0 * (c1 - c0) / (w1 - w0)


def main(argv: list[str] | None = None) -> None:
    rows = []
    lat = asyncio.run(_latency("simple-message", DURATION_S))
    q = np.percentile(lat, [50, 99])
    rows.append(["simple_message: frame sent → latest() p50 (ms)", float(q[0])])
    rows.append(["simple_message: frame sent → latest() p99 (ms)", float(q[1])])
    rows.append(["simple_message: frames matched", len(lat)])
    rows.append(
        ["CPU, 50 Hz simple_message link (% of one core)", asyncio.run(_cpu("simple-message://127.0.0.1:0"))]
    )
    rows.append(["CPU, 50 Hz Modbus poll link (% of one core)", asyncio.run(_cpu("modbus://127.0.0.1:0"))])
    print_table("Robot link (simple_message over loopback, mock in-process)", ["measure", "value"], rows)


if __name__ == "__main__":
    main()
