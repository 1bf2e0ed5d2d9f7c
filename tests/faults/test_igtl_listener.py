"""Issue #32, the OpenIGTLink listener as a hostile peer meets it: ``oarmreg serve`` in its own
process (what the OR PC runs), real sockets on loopback, ``/health`` over HTTP.

Before: a 64 MiB STATUS with a wrong CRC was read whole and its CRC computed in pure Python on the
event loop (``/health`` stalled for 21.7 s); every peer announcing 64 MiB was buffered whole (RSS
grew with what peers announced); a peer that sent a malformed header stayed connected.  After:
the body size is capped per message type before a byte of the body is read, a started message
must finish within ``igtl.stall_timeout_s``, at most ``igtl.max_clients`` connections are held,
and every refusal closes the socket.  The tests assert outcomes (closed or not, answered within a
liveness deadline, an RSS bound), never fine timings.
"""

from __future__ import annotations

import contextlib
import secrets
import socket
import struct
import threading
import time
from collections.abc import Iterator
from dataclasses import dataclass

import httpx
import psutil
import pytest

from service.navigation.igtl import wire
from tests.faults._service import wait_for
from tests.helpers import http

TOKEN = secrets.token_urlsafe(24)
LIVENESS_S = 3.0
"""``/health`` must answer within this (a liveness probe's deadline, not a latency figure)."""
CLOSE_DEADLINE_S = 10.0
MAX_CLIENTS = 6
STALL_S = 1.0
BIG = 64 * 1024 * 1024


@dataclass
class Serve:
    """The real app (uvicorn thread, as ``oarmreg serve`` runs it) with its OpenIGTLink listener."""

    base_url: str
    igtl_port: int


@pytest.fixture(scope="module")
def serve(tmp_path_factory: pytest.TempPathFactory) -> Iterator[tuple[Serve, int]]:
    from service.cli.commands.serve import serve_in_thread
    from service.http.app import create_app
    from service.settings import load_settings

    root = tmp_path_factory.mktemp("igtl-limits")
    settings = load_settings(None, {
        "watch_dir": root / "watch", "data_dir": root / "data", "api_token": TOKEN,
        "robot.link_url": "simple-message://127.0.0.1:9", "robot.connect_timeout_s": 2.0,
        "igtl.enabled": True, "igtl.port": 0, "igtl.max_clients": MAX_CLIENTS,
        "igtl.stall_timeout_s": STALL_S,
    })  # fmt: skip
    app = create_app(settings, start_watcher=False)
    with serve_in_thread(app) as server:
        client = httpx.Client(base_url=server.base_url, headers={"Authorization": f"Bearer {TOKEN}"})
        with client:
            port = client.get("/status").json()["listeners"]["igtl"]["port"]
        yield Serve(server.base_url, port), port


def counters(proc: Serve) -> dict[str, int]:
    r = http.get(proc.base_url + "/status", headers={"Authorization": f"Bearer {TOKEN}"}, timeout=10.0)
    return dict(r.json()["listeners"]["igtl"]["counters"])


def health_alive(proc: Serve) -> None:
    """``/health`` answers 200 within the liveness deadline, three times in a row."""
    for _ in range(3):
        assert http.get(proc.base_url + "/health", timeout=LIVENESS_S).status_code == 200


def closed_by_server(s: socket.socket, deadline_s: float = CLOSE_DEADLINE_S) -> bool:
    """Read (and throw away the pushes) until EOF or a reset: True; still open at the deadline: False."""
    s.settimeout(0.2)
    end = time.monotonic() + deadline_s
    while time.monotonic() < end:
        try:
            if s.recv(65536) == b"":
                return True
        except TimeoutError:
            continue
        except ConnectionError:
            return True
    return False


@contextlib.contextmanager
def peer(port: int) -> Iterator[socket.socket]:
    s = socket.create_connection(("127.0.0.1", port), timeout=10.0)
    try:
        yield s
    finally:
        s.close()


def header(msg_type: str, body_size: int, *, version: int = 1, crc: int = 0, device: str = "Evil") -> bytes:
    return struct.pack(">H12s20sIIQQ", version, msg_type.encode(), device.encode(), 0, 0, body_size, crc)


def send_quietly(s: socket.socket, data: bytes) -> None:
    """Send what the server may refuse half-way (a reset or a broken pipe is the expected answer)."""
    with contextlib.suppress(OSError):
        s.sendall(data)


def test_a_64_mib_status_with_a_wrong_crc_is_refused_unread_and_health_stays_live(
    serve: tuple[Serve, int],
) -> None:
    proc, port = serve
    body = bytes(BIG)
    with peer(port) as s:
        t = threading.Thread(target=send_quietly, args=(s, header("STATUS", BIG, crc=1) + body))
        t.start()
        t.join(60)
        health_alive(proc)  # before: the CRC of 64 MiB in Python held the loop for ~20 s
        assert closed_by_server(s)
    health_alive(proc)
    assert counters(proc)["oversize"] >= 1


MALFORMED = {
    "version 0": header("STATUS", 30, version=0),
    "version 7": header("STATUS", 30, version=7),
    "BODY_SIZE 2^40": header("STATUS", 1 << 40),
    "GET_ with a 1 MiB body": header("GET_TRANS", 1 << 20),
    "v2 extended header larger than the body": (
        header("STATUS", 12, version=2, crc=wire.crc64(struct.pack(">HHII", 200, 2, 0, 1)))
        + struct.pack(">HHII", 200, 2, 0, 1)
    ),
    "v2 body shorter than its extended header": header("STATUS", 3, version=2, crc=wire.crc64(b"abc"))
    + b"abc",
    "v2 metadata count past the end": (
        header("STATUS", 16, version=2, crc=wire.crc64(struct.pack(">HHIIH2s", 12, 4, 0, 1, 9, b"xx")))
        + struct.pack(">HHIIH2s", 12, 4, 0, 1, 9, b"xx")
    ),
}


def test_a_malformed_header_really_closes_the_socket(serve: tuple[Serve, int]) -> None:
    """Before: 5 of 7 such peers stayed connected and kept receiving pushes."""
    proc, port = serve
    still_open = []
    for name, raw in MALFORMED.items():
        with peer(port) as s:
            send_quietly(s, raw)
            if not closed_by_server(s):
                still_open.append(name)
    assert not still_open, f"still connected after a malformed header: {still_open}"
    health_alive(proc)


def test_peers_announcing_64_mib_are_closed_and_rss_stays_bounded(serve: tuple[Serve, int]) -> None:
    """Before: each peer's announced body was buffered whole (10 peers sending 16 MiB: +160 MiB)."""
    proc, port = serve
    service = psutil.Process()  # the service runs in this process (its uvicorn thread)
    chunk = bytes(16 * 1024 * 1024)
    frames = [header("TRANSFORM", BIG, crc=7) + chunk for _ in range(10)]  # allocated before rss0
    rss0 = service.memory_info().rss
    with contextlib.ExitStack() as stack:
        socks = [stack.enter_context(peer(port)) for _ in range(10)]
        threads = [
            threading.Thread(target=send_quietly, args=(s, frame))
            for s, frame in zip(socks, frames, strict=True)
        ]
        for t in threads:
            t.start()
        for t in threads:
            t.join(60)
        rss1 = service.memory_info().rss
        assert all(closed_by_server(s) for s in socks)
    growth_mib = (rss1 - rss0) / 2**20
    assert growth_mib < 48, f"the service grew {growth_mib:.0f} MiB for 10 peers announcing 64 MiB"
    health_alive(proc)


def test_a_peer_stalling_mid_message_is_dropped_and_a_listener_only_client_is_not(
    serve: tuple[Serve, int],
) -> None:
    proc, port = serve
    with peer(port) as listener, peer(port) as staller:
        staller.sendall(header("STATUS", 30)[:20])  # 20 of the 58 header bytes, then nothing
        assert closed_by_server(staller, STALL_S + CLOSE_DEADLINE_S)
        assert not closed_by_server(listener, STALL_S + 0.5)  # receives pushes, never writes: kept
    assert counters(proc)["stalled"] >= 1


def test_connections_beyond_max_clients_are_closed_at_once_and_counted(
    serve: tuple[Serve, int],
) -> None:
    proc, port = serve
    wait_for(lambda: http.get(proc.base_url + "/health", timeout=LIVENESS_S).status_code == 200, "health")
    before = counters(proc)["refused_full"]
    with contextlib.ExitStack() as stack:
        held = [stack.enter_context(peer(port)) for _ in range(MAX_CLIENTS)]
        for s in held:  # each got its on-connect push: all are in the server's client set
            s.settimeout(10.0)
            assert s.recv(wire.HEADER_SIZE)
        extra = stack.enter_context(peer(port))
        assert closed_by_server(extra)
        assert counters(proc)["refused_full"] == before + 1
        health_alive(proc)
    # a slot frees when a client leaves
    wait_for(
        lambda: (
            http.get(
                proc.base_url + "/status", headers={"Authorization": f"Bearer {TOKEN}"}, timeout=10.0
            ).json()["listeners"]["igtl"]["clients"]
            == 0
        ),
        "the held clients to be gone",
    )
    with peer(port) as s:
        s.settimeout(10.0)
        assert s.recv(wire.HEADER_SIZE)
