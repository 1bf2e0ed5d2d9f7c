"""Helpers of the fault suite (h-hardfs half): the real service over loopback, in-process or as a
subprocess (``python -m service.cli serve --config ...``), SSE reading, deadline polls.  No sleeps:
every wait polls with a deadline or reads server-sent events."""

from __future__ import annotations

import contextlib
import json
import os
import signal
import socket
import subprocess
import sys
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import httpx
import numpy as np
import pytest

from tests.helpers import http
from tests.helpers.tokens import make_token
from tests.integration.fast_service import fast_overrides
from tests.integration.polling import wait_for, wait_robot_still

REPO = Path(__file__).resolve().parents[2]
TOKEN = make_token()
WINDOW_S = 0.6
DEADLINE_S = 60.0
Q1 = (0.0, 0.0, np.pi / 2, 0.0, np.pi / 4, 0.0)


def overrides(watch: Path, data: Path, link_url: str, **kw: Any) -> dict[str, Any]:
    return fast_overrides(watch, data, link_url, TOKEN, WINDOW_S, **kw)


@dataclass
class Svc:
    """A running service and what the tests need of it."""

    client: httpx.Client
    watch: Path
    data: Path
    robot: Any = None
    mock: Any = None
    ctx: Any = None
    n: int = 0

    def scans(self) -> list[dict[str, Any]]:
        r = self.client.get("/scans")
        r.raise_for_status()
        return list(r.json())

    def scan_where(self, pred: Callable[[dict[str, Any]], bool], what: str) -> dict[str, Any]:
        return wait_for(lambda: next((s for s in self.scans() if pred(s)), None), what)  # type: ignore[no-any-return]

    def wait_still(self) -> None:
        """Until the robot has been still, and watched, for the service's own stillness window."""
        window_s = self.ctx.settings.stillness.window_s if self.ctx is not None else WINDOW_S
        wait_robot_still(self.client, self.robot, window_s, DEADLINE_S)


@contextlib.contextmanager
def in_process_service(root: Path, phantom: Any, model: Any, **kw: Any) -> Iterator[Svc]:
    """Mock simple-message controller + the app under uvicorn in a thread, robot still at Q1."""
    from mocks.robot.robot import ScriptedRobot
    from mocks.robot.runner import run_mock_controller
    from service.cli.commands.serve import serve_in_thread
    from service.http.app import create_app
    from service.settings import load_settings

    watch, data = root / "watch", root / "data"
    robot = ScriptedRobot(Q1)
    with run_mock_controller("simple-message", robot) as mock:
        settings = load_settings(None, overrides(watch, data, mock.url, **kw))
        app = create_app(settings, phantom=phantom, robot_model=model)
        with (
            serve_in_thread(app) as server,
            httpx.Client(
                base_url=server.base_url, headers={"Authorization": f"Bearer {TOKEN}"}, timeout=60.0
            ) as client,
        ):
            from tests.faults.conftest import wait_link_connected

            wait_link_connected(client)
            yield Svc(client, watch, data, robot, mock, app.state.ctx)


class Events:
    """Server-sent events of ``GET /events`` read on the caller's thread, until a wanted one arrives."""

    def __init__(self, svc: Svc) -> None:
        self.svc = svc
        self.seen: list[tuple[str, dict[str, Any]]] = []
        self._cm = svc.client.stream("GET", "/events", timeout=httpx.Timeout(DEADLINE_S))
        self._lines: Iterator[str] | None = None

    def __enter__(self) -> Events:
        stream = self._cm.__enter__()
        assert stream.headers["content-type"].startswith("text/event-stream")
        self._lines = stream.iter_lines()
        assert next(self._lines).startswith(": connected")
        if self.svc.ctx is not None:  # subscribed before the caller acts (the generator runs on)
            wait_for(lambda: self.svc.ctx.bus.n_subscribers > 0, "the SSE subscription")
        return self

    def __exit__(self, *exc: object) -> None:
        self._cm.__exit__(None, None, None)

    def wait(self, name: str, pred: Callable[[dict[str, Any]], bool] = lambda d: True) -> dict[str, Any]:
        """The first event ``name`` whose data ``pred`` accepts, already seen or still to come (events
        published together may arrive in either order)."""
        assert self._lines is not None
        for seen_name, seen_data in self.seen:
            if seen_name == name and pred(seen_data):
                return seen_data
        event = None
        deadline = time.monotonic() + DEADLINE_S  # keep-alive comments would reset a read timeout
        for line in self._lines:
            if time.monotonic() > deadline:
                pytest.fail(f"timed out waiting for event {name}; seen {[e for e, _ in self.seen]}")
            if line.startswith("event: "):
                event = line[7:]
            elif line.startswith("data: ") and event:
                data = json.loads(line[6:])
                self.seen.append((event, data))
                if event == name and pred(data):
                    return data  # type: ignore[no-any-return]
        pytest.fail(f"event stream ended before {name}; seen {[e for e, _ in self.seen]}")


def factory_series(folder: Path, n: int = 6, **kw: Any) -> list[Path]:
    """A small valid CT series (``tests/helpers/dicom_factory``), 8 x 8 pixels."""
    from tests.helpers.dicom_factory import ramp_volume, write_series

    return list(write_series(folder, ramp_volume(n, 8, 8), **kw))


def free_port() -> int:
    s = socket.socket()
    s.bind(("127.0.0.1", 0))
    port = int(s.getsockname()[1])
    s.close()
    return port


@dataclass
class ServeProcess:
    """``python -m service.cli serve --config FILE`` as a child process (what the OR PC runs)."""

    config: Path
    port: int
    log: Path
    proc: subprocess.Popen[bytes] | None = None
    starts: int = 0
    kills: int = 0
    env: dict[str, str] = field(default_factory=dict)

    @property
    def base_url(self) -> str:
        return f"http://127.0.0.1:{self.port}"

    def start(self, timeout_s: float = DEADLINE_S) -> None:
        with self.log.open("ab") as out:
            self.proc = subprocess.Popen(
                [sys.executable, "-m", "service.cli", "serve", "--config", str(self.config)],
                cwd=REPO,
                stdout=out,
                stderr=subprocess.STDOUT,
                env={**os.environ, **self.env},
            )
        self.starts += 1

        def up() -> bool:
            assert self.proc is not None
            if self.proc.poll() is not None:
                pytest.fail(f"serve exited with {self.proc.returncode}; log:\n{self.log.read_text()[-3000:]}")
            try:
                return http.get(self.base_url + "/health", timeout=2.0).status_code == 200
            except httpx.HTTPError:
                return False

        wait_for(up, "the service to answer /health", timeout_s)

    def kill9(self) -> None:
        assert self.proc is not None
        self.proc.send_signal(signal.SIGKILL)
        self.proc.wait(30)
        self.kills += 1
        self.proc = None

    def stop(self) -> None:
        if self.proc is not None:
            self.proc.terminate()
            try:
                self.proc.wait(30)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait(30)
            self.proc = None


@dataclass
class ForkedServe:
    """Restarts of ``serve`` forked from :mod:`_zygote` (same code path, without the 4 s of imports)."""

    config: Path
    port: int
    log: Path
    zygote: subprocess.Popen[str] | None = None
    pid: int | None = None
    starts: int = 0
    kills: int = 0

    @property
    def base_url(self) -> str:
        return f"http://127.0.0.1:{self.port}"

    def _ask(self, line: str) -> str:
        assert self.zygote is not None and self.zygote.stdin is not None and self.zygote.stdout is not None
        self.zygote.stdin.write(line + "\n")
        self.zygote.stdin.flush()
        return self.zygote.stdout.readline().strip()

    def open(self) -> None:
        with self.log.open("ab") as out:
            self.zygote = subprocess.Popen(
                [sys.executable, str(Path(__file__).with_name("_zygote.py")), str(self.config)],
                cwd=REPO,
                stdin=subprocess.PIPE,
                stdout=subprocess.PIPE,
                stderr=out,
                text=True,
                env={
                    **os.environ,
                    "OPENBLAS_NUM_THREADS": "1",
                    "OMP_NUM_THREADS": "1",
                    "PYTHONPATH": str(REPO),
                },
            )
        assert self.zygote.stdout is not None
        assert self.zygote.stdout.readline().strip() == "ready", self.log.read_text()[-3000:]

    def start(self, timeout_s: float = DEADLINE_S) -> None:
        self.pid = int(self._ask("spawn"))
        self.starts += 1

        def up() -> bool:
            try:
                return http.get(self.base_url + "/health", timeout=2.0).status_code == 200
            except httpx.HTTPError:
                return False

        wait_for(up, "the forked service to answer /health", timeout_s)

    def kill9(self) -> None:
        assert self.pid is not None
        os.kill(self.pid, signal.SIGKILL)
        assert self._ask(f"reap {self.pid}") == "reaped"
        self.kills += 1
        self.pid = None

    def close(self) -> None:
        if self.pid is not None:
            os.kill(self.pid, signal.SIGTERM)
            self._ask(f"reap {self.pid}")
            self.pid = None
        if self.zygote is not None:
            assert self.zygote.stdin is not None
            self.zygote.stdin.write("quit\n")
            self.zygote.stdin.close()
            self.zygote.wait(30)
            if self.zygote.stdout is not None:
                self.zygote.stdout.close()
            self.zygote = None


def write_config(path: Path, settings: dict[str, Any]) -> None:
    """A TOML config from dotted keys (the subset the suite needs: str, int, float, bool)."""
    tables: dict[str, dict[str, Any]] = {}
    top: dict[str, Any] = {}
    for key, value in settings.items():
        head, _, tail = key.rpartition(".")
        (tables.setdefault(head, {}) if head else top)[tail] = value

    def fmt(v: Any) -> str:
        if isinstance(v, bool):
            return "true" if v else "false"
        if isinstance(v, int | float):
            return repr(v)
        return json.dumps(str(v))

    lines = [f"{k} = {fmt(v)}" for k, v in top.items()]
    for name, kv in tables.items():
        lines += ["", f"[{name}]", *(f"{k} = {fmt(v)}" for k, v in kv.items())]
    path.write_text("\n".join(lines) + "\n", encoding="utf-8")


@contextlib.contextmanager
def mock_controller_process(link: str = "simple-message://127.0.0.1:0") -> Iterator[str]:
    """``oarmreg mock robot --link LINK`` (robot still) in a process of its own; yields its URL."""
    mock = subprocess.Popen(
        [sys.executable, "-m", "service.cli", "mock", "robot", "--link", link],
        cwd=REPO,
        stdout=subprocess.PIPE,
        text=True,
    )
    try:
        assert mock.stdout is not None
        url = mock.stdout.readline().strip()
        assert url.startswith(link.split("://", 1)[0] + "://"), url
        yield url
    finally:
        mock.terminate()
        mock.wait(30)
        if mock.stdout is not None:
            mock.stdout.close()


@contextlib.contextmanager
def served(cfg: Path, port: int) -> Iterator[tuple[ServeProcess, httpx.Client]]:
    """``serve --config cfg`` on ``port`` (log beside ``cfg``) and a client carrying the token;
    stopped on exit."""
    serve = ServeProcess(cfg, port, cfg.with_name("serve.log"))
    serve.start()
    try:
        with httpx.Client(
            base_url=serve.base_url, headers={"Authorization": f"Bearer {TOKEN}"}, timeout=DEADLINE_S
        ) as client:
            yield serve, client
    finally:
        serve.stop()
