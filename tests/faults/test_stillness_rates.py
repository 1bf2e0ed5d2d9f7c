"""Issue 40 item 3, live: three controllers at 50, 250 and 1000 Hz at once while both cores are loaded.

Each mock controller streams simple_message with the VAL3 driver's cadence (1 s after a client
connects, each message in three writes, STATUS every fifth frame); each is read as the service reads
it (:class:`drivers.link_process.ProcessLink`, a child process) and judged by the service's own
:meth:`service.intake.capture.Capture.snapshot`, at the default ``max_gap_s`` (0.25 s) and
deviation limit.  Two busy-loop processes (nice 0) fill both cores for the whole test.

What runs live and what does not: the window here is ``WINDOW_S`` (2 s), not the default 60 s, so
three rates fit in the test-time budget; the default 60 s window is judged on modelled loaded
streams in tests/unit/registration/model/test_stillness_rates.py and measured live by
``python -m benchmarks.bench_stillness`` (docs/validation.md).  Asserted here: every still window is
``still``; a 0.05° move (the controller's ``in_motion`` forced UNKNOWN, so only the joints show it)
is ``moved``; a 0.5 s pause of the controller (connection open, nothing sent late) is
``incomplete`` and says the controller stopped sending; the 1 kHz link holds the whole window.
"""

from __future__ import annotations

import asyncio
import contextlib
import math
import subprocess
import sys
import time
from collections.abc import Iterator
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Any

import pytest

from drivers.link_process import ProcessLink
from mocks.robot.robot import ControllerStatus, ScriptedRobot
from mocks.robot.runner import MockController, run_mock_controller
from service.intake.capture import Capture
from tests.integration.polling import poll_until

RATES_HZ = (50.0, 250.0, 1000.0)
WINDOW_S = 2.0
STILL_JUDGEMENTS = 6
"""Still windows judged per rate, their ends ``STEP_S`` apart in the recorded history."""
STEP_S = 0.25
PAUSE_S = 0.5
MOVE_RAD = math.radians(0.05)
DEADLINE_S = 30.0
LOAD_BOUND_S = 60.0
"""Each load process ends by itself after this long, should the test die before stopping it."""
Q = (0.3, -0.5, 1.6, 0.2, 0.8, -0.1)


@contextlib.contextmanager
def both_cores_loaded() -> Iterator[None]:
    code = f"import time\nend = time.monotonic() + {LOAD_BOUND_S}\nwhile time.monotonic() < end:\n    pass\n"
    procs = [subprocess.Popen([sys.executable, "-c", code]) for _ in range(2)]
    try:
        yield
    finally:
        for p in procs:
            p.terminate()
        for p in procs:
            p.wait(10)


def _settings(root: Path) -> Any:
    from service.settings import load_settings

    return load_settings(
        None, {"watch_dir": root / "w", "data_dir": root / "d", "stillness.window_s": WINDOW_S}
    )


def _pause(mock: MockController, pause_s: float) -> None:
    """The controller sends nothing for ``pause_s`` (the injected fault; its schedule runs on)."""

    async def pause() -> None:
        mock.server.stall()
        await asyncio.sleep(pause_s)
        mock.server.resume()

    mock.run(pause())


def _frames_past(link: ProcessLink, t_s: float) -> bool:
    last = link.latest()
    return last is not None and last.t_s > t_s


def _judged_once_past(link: ProcessLink, cap: Capture, past_t_s: float, end_t_s: float, what: str) -> Any:
    """The window ending at ``end_t_s``, judged once the link has frames past ``past_t_s``."""
    poll_until(lambda: _frames_past(link, past_t_s), what, DEADLINE_S)
    return cap.snapshot(end_t_s, end_t_s)


@pytest.fixture(scope="module")
def live(tmp_path_factory: pytest.TempPathFactory) -> Iterator[dict[str, Any]]:
    root = tmp_path_factory.mktemp("rates")
    robot = ScriptedRobot(Q)
    robot.controller_status = ControllerStatus(in_motion=-1)
    with contextlib.ExitStack() as stack:
        stack.enter_context(both_cores_loaded())
        mocks = {
            r: stack.enter_context(
                run_mock_controller("simple-message", robot, period_s=1.0 / r, start_delay_s=1.0)
            )
            for r in RATES_HZ
        }
        links = {r: ProcessLink(m.url) for r, m in mocks.items()}
        for link in links.values():
            link.start()
        try:
            captures = {r: Capture(link, _settings(root), lambda e: None) for r, link in links.items()}
            need_s = WINDOW_S + STILL_JUDGEMENTS * STEP_S + 1.0
            for r, link in links.items():
                poll_until(
                    lambda link=link: len(h := link.history(0.0)) > 1 and h[-1].t_s - h[0].t_s > need_s,
                    f"{need_s} s of joint history at {r:g} Hz",
                    DEADLINE_S,
                )
            yield {"robot": robot, "mocks": mocks, "links": links, "captures": captures}
        finally:
            for link in links.values():
                asyncio.run(link.close())


def test_still_windows_at_three_rates_under_load_are_still(live: dict[str, Any]) -> None:
    now = time.monotonic()
    for r, cap in live["captures"].items():
        history = live["links"][r].history(0.0)
        assert history[-1].t_s - history[0].t_s > WINDOW_S  # the 1 kHz history holds the window
        for j in range(STILL_JUDGEMENTS):
            end = now - 0.6 - j * STEP_S
            snap = cap.snapshot(end, end)
            assert snap.verdict == "still", (r, j, snap.stillness_reason)
            # the window holds this rate's stream (the rates are 5x and 4x apart); not a throughput
            # figure: a starved mock controller sends late (77 of 100 frames at 50 Hz, load ~5)
            assert snap.n_samples >= 0.5 * r * WINDOW_S, (r, snap.n_samples)


def test_a_move_and_a_pause_at_three_rates_under_load_are_refused(live: dict[str, Any]) -> None:
    robot, links, captures = live["robot"], live["links"], live["captures"]
    robot.move_to([q + (MOVE_RAD if i == 0 else 0.0) for i, q in enumerate(Q)], 0.2)
    moved_end = robot.motion_end_t_s()
    for r, link in links.items():
        snap = _judged_once_past(link, captures[r], moved_end + 0.5, moved_end + 0.3, f"frames ({r:g} Hz)")
        assert snap.verdict == "moved", (r, snap.stillness_reason)
        assert "joint 1" in snap.stillness_reason
    poll_until(
        lambda: all(_frames_past(link, moved_end + 1.2) for link in links.values()), "frames", DEADLINE_S
    )
    paused_at = time.monotonic()
    with ThreadPoolExecutor(len(RATES_HZ)) as pool:
        list(pool.map(lambda m: _pause(m, PAUSE_S), live["mocks"].values()))
    resumed = time.monotonic()
    end = resumed + 0.6
    assert end - WINDOW_S < paused_at - 0.2  # the pause lies inside the window
    for r, link in links.items():
        snap = _judged_once_past(link, captures[r], resumed + 1.7, end, f"frames ({r:g} Hz)")
        assert snap.verdict == "incomplete", (r, snap.stillness_reason)
        assert "the controller stopped sending" in snap.stillness_reason, (r, snap.stillness_reason)
