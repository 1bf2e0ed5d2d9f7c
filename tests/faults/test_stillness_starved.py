"""Issue 19 item 7 (b) at the service level: the link reader starved, a controller that stops sending.

The real service (uvicorn thread) reads the robot link in its child process (the default).  The
child is frozen with SIGSTOP for ``STOP_S`` (0.4 s, > ``stillness.max_gap_s`` 0.25 s) and then
continued, just before a scan arrives in the watch folder, so the stop lies inside the scan's
stillness window (``WINDOW_S`` 2 s before its first file):

* a **streamed** link (simple_message over TCP): the frames sent meanwhile wait in the socket and
  arrive intact and in order; the robot was still and watched, the verdict is ``still`` although the
  receive clock shows a gap over 0.25 s;
* a **polled** link (Modbus): the poller did not run, nobody watched: ``incomplete``, and
  ``POST /register`` answers 409 "Joint history incomplete" (not "Robot moved");
* a controller that **stops sending** (the mock's stall, connection open): frames genuinely missing,
  ``incomplete`` naming the missing frames.

The stop's length is the injected fault, not a synchronisation: every wait polls with a deadline.
"""

from __future__ import annotations

import contextlib
import os
import signal
import threading
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import httpx
import pytest

from tests.faults._service import DEADLINE_S, Q1, TOKEN, Svc, factory_series, overrides, wait_for

WINDOW_S = 2.0
STOP_S = 0.4
"""The injected stall (s): over ``stillness.max_gap_s`` (0.25 s), under ``robot.stale_after_s`` (0.5 s)."""


@contextlib.contextmanager
def _service(root: Path, kind: str) -> Iterator[Svc]:
    from mocks.robot.robot import ScriptedRobot
    from mocks.robot.runner import run_mock_controller
    from registration.model.kinematics import RobotModel
    from registration.model.phantom import load_phantom
    from service.cli.commands.serve import serve_in_thread
    from service.http.app import create_app
    from service.settings import DEFAULT_PHANTOM_FILE, load_settings
    from tests.faults.conftest import wait_link_connected

    robot = ScriptedRobot(Q1)
    with run_mock_controller(kind, robot) as mock:
        settings = load_settings(
            None, overrides(root / "watch", root / "data", mock.url, **{"stillness.window_s": WINDOW_S})
        )
        app = create_app(
            settings, phantom=load_phantom(DEFAULT_PHANTOM_FILE), robot_model=RobotModel.load("tx60")
        )
        with (
            serve_in_thread(app) as server,
            httpx.Client(base_url=server.base_url, headers={"Authorization": f"Bearer {TOKEN}"},
                         timeout=DEADLINE_S) as client,
        ):  # fmt: skip
            wait_link_connected(client)
            yield Svc(client, root / "watch", root / "data", robot, mock, app.state.ctx)


_FAULT_ENDED_T_S: dict[int, float] = {}
"""Per service: when the last injected fault ended (monotonic s); a shared service's next test waits
until it is out of the window, so the tests do not depend on their order."""


def _watched(svc: Svc) -> None:
    wait_for(lambda: svc.client.get("/status").json()["link"]["history_s"] > WINDOW_S + 0.5, "joint history")
    ended = _FAULT_ENDED_T_S.get(id(svc))
    if ended is not None:
        wait_for(lambda: time.monotonic() > ended + WINDOW_S + 0.5, "the last fault out of the window")


def _fault_ended(svc: Svc) -> None:
    _FAULT_ENDED_T_S[id(svc)] = time.monotonic()


def _frozen_link_child(svc: Svc) -> None:
    """SIGSTOP the service's link child for :data:`STOP_S`, then SIGCONT."""
    pid = svc.ctx.robot_link.pid
    assert pid is not None, "the link is not read in a child process"
    os.kill(pid, signal.SIGSTOP)
    try:
        threading.Event().wait(STOP_S)  # the fault's duration
    finally:
        os.kill(pid, signal.SIGCONT)
        _fault_ended(svc)


def _scan_now(svc: Svc, name: str) -> dict[str, Any]:
    factory_series(svc.watch / name)
    return svc.scan_where(lambda s: s["folder"].endswith(name) and s["status"] == "complete", f"scan {name}")


@pytest.fixture(scope="module")
def streamed(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Svc]:
    """One simple_message service for the streamed-link tests (each waits for a full window first)."""
    with _service(tmp_path_factory.mktemp("streamed"), "simple-message") as svc:
        yield svc


def test_a_starved_streamed_link_is_not_a_hole_in_the_history(streamed: Svc) -> None:
    svc = streamed
    _watched(svc)
    _frozen_link_child(svc)
    scan = _scan_now(svc, "after-stop")
    j = scan["joints"]
    gap_s = svc.client.get("/status").json()["link"]["max_receive_gap_s"]
    assert gap_s > 0.25, gap_s  # the receive clock saw the stop (inside the 2 s window) ...
    assert j["verdict"] == "still", j  # ... and the frames it held arrived intact


def test_a_starved_polled_link_and_a_silent_controller_are_incomplete_not_moved(tmp_path: Path) -> None:
    with _service(tmp_path / "modbus", "modbus") as svc:
        _watched(svc)
        _frozen_link_child(svc)
        scan = _scan_now(svc, "after-stop")
        j = scan["joints"]
        assert j["verdict"] == "incomplete" and j["stillness_reason"].startswith(
            "joint history incomplete"
        ), j
        # the stop shows as a gap in the polls, or (when the frozen child's Modbus request timed out
        # meanwhile) as a reconnect inside the window: either way frames may be lost, never "moved"
        assert "gap" in j["stillness_reason"] or "reconnected" in j["stillness_reason"], j
        r = svc.client.post("/register", json={"scan_id": scan["id"]})
        body = r.json()
        assert r.status_code == 409 and body["title"] == "Joint history incomplete", body
        assert body["type"].endswith("joint-history-incomplete"), body


def test_frames_genuinely_missing_are_incomplete(streamed: Svc) -> None:
    svc = streamed
    _watched(svc)
    svc.mock.stall()  # the controller stops sending; the connection stays open
    try:
        threading.Event().wait(STOP_S)  # the fault's duration
    finally:
        svc.mock.resume()
        _fault_ended(svc)
    scan = _scan_now(svc, "after-stall")
    r = svc.client.post("/register", json={"scan_id": scan["id"]})
    assert r.status_code == 409 and r.json()["title"] == "Joint history incomplete", r.text
    j = scan["joints"]
    assert j["verdict"] == "incomplete" and "missing" in j["stillness_reason"], j
