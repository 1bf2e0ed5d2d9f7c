"""Fault suite (issue #13): the real service over loopback, refused input, damaged storage.

Helpers: :func:`raw_http` speaks HTTP/1.1 over a plain socket (to send what httpx would not:
headers without their body, a 10 MB chunked body, a foreign Host), :func:`serve` runs the real
app (uvicorn thread) with the fault-suite settings.
"""

from __future__ import annotations

import socket
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import httpx

from tests.helpers.tokens import make_token

TOKEN = make_token()
AUTH = {"Authorization": f"Bearer {TOKEN}"}
JSON = {"Content-Type": "application/json"}
RAW_TIMEOUT_S = 30.0


def fault_settings(root: Path, link_url: str = "simple-message://127.0.0.1:9", **kw: Any) -> Any:
    from service.settings import load_settings

    return load_settings(
        None,
        {
            "watch_dir": root / "watch",
            "data_dir": root / "data",
            "api_token": TOKEN,
            "robot.link_url": link_url,
            "robot.connect_timeout_s": 2.0,
            "watcher.quiet_period_s": 0.3,
            "watcher.poll_interval_s": 0.2,
            **kw,
        },
    )


@dataclass
class Running:
    base_url: str
    port: int
    client: httpx.Client
    app: Any


@contextmanager
def serve(
    settings: Any, *, start_watcher: bool = False, app_hook: Any = None, **kw: Any
) -> Iterator[Running]:
    """The real app on a free loopback port; ``app_hook(app)`` may add routes before it starts."""
    from service.cli.commands.serve import serve_in_thread
    from service.http.app import create_app

    app = create_app(settings, start_watcher=start_watcher, **kw)
    if app_hook is not None:
        app_hook(app)
    with (
        serve_in_thread(app) as server,
        httpx.Client(base_url=server.base_url, headers=AUTH, timeout=60.0) as client,
    ):
        wait_link_connected(client)
        yield Running(server.base_url, server.port, client, app)


LINK_CONNECT_DEADLINE_S = 30.0
"""How long a test service's robot link (read in a child process) may take to connect."""


def wait_link_connected(client: httpx.Client) -> None:
    """Until the service's robot link is connected.  The link connects from its own process after
    start-up; its connection on the test's mock controller must not open inside the first test
    (the leak guard would count the mock's handler task as that test's)."""
    from tests.integration.polling import poll_until

    poll_until(
        lambda: client.get("/status").json()["link"]["state"] == "connected",
        "the robot link to connect",
        LINK_CONNECT_DEADLINE_S,
    )


@dataclass
class RawResponse:
    status: int
    headers: dict[str, str]
    body: bytes


def read_response(sock: socket.socket) -> RawResponse:
    """One HTTP/1.1 response with a Content-Length body."""
    buf = b""
    while b"\r\n\r\n" not in buf:
        chunk = sock.recv(65536)
        if not chunk:
            raise ConnectionError(f"connection closed before a full response head: {buf!r}")
        buf += chunk
    head, _, rest = buf.partition(b"\r\n\r\n")
    lines = head.decode("latin-1").split("\r\n")
    status = int(lines[0].split()[1])
    headers = {k.strip().lower(): v.strip() for k, _, v in (ln.partition(":") for ln in lines[1:])}
    length = int(headers.get("content-length", "0"))
    while len(rest) < length:
        chunk = sock.recv(65536)
        if not chunk:
            break
        rest += chunk
    return RawResponse(status, headers, rest[:length])


def raw_http(port: int, head: str, body: bytes = b"") -> RawResponse:
    """Send ``head`` (request line + headers, no blank line) and ``body``; read one response."""
    with socket.create_connection(("127.0.0.1", port), timeout=RAW_TIMEOUT_S) as sock:
        sock.sendall(head.encode("latin-1") + b"\r\n\r\n" + body)
        return read_response(sock)


def closed_by_peer(sock: socket.socket) -> bool:
    """True once the server has closed the connection (EOF or reset), waiting up to the timeout."""
    try:
        while True:
            if not sock.recv(65536):
                return True
    except (ConnectionResetError, BrokenPipeError):
        return True
    except TimeoutError:
        return False


Q_STILL = (0.0, 0.0, 1.5707963267948966, 0.0, 0.7853981633974483, 0.0)


@contextmanager
def mock_robot(joints_rad: tuple[float, ...] = Q_STILL) -> Iterator[Any]:
    """A still robot behind the mock simple_message controller (a live link: no reconnect loop)."""
    from mocks.robot.robot import ScriptedRobot
    from mocks.robot.runner import run_mock_controller

    with run_mock_controller("simple-message", ScriptedRobot(joints_rad)) as mock:
        yield mock


REPO_ROOT = Path(__file__).resolve().parents[2]
