"""Fault suite, issue 41 items 4, 5 and 7: a local peer can neither dodge nor aim the auth throttle,
nor lock the right token out; weak hand-made tokens are refused; a disguised ticket is redacted.

One real service (``python -m service.cli serve``, a process of its own); every hostile or
legitimate client is a process of its own too (:func:`client_run`), bound to its own loopback
address (127.0.0.0/8 is all loopback on Linux), so each test uses addresses no other test uses
and the tests run in any order.  Every wait polls with a deadline; nothing sleeps.
"""

from __future__ import annotations

import json
import socket
import struct
import subprocess
import sys
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import httpx
import pytest

from tests.faults._service import (
    DEADLINE_S,
    REPO,
    TOKEN,
    ServeProcess,
    free_port,
    served,
    wait_for,
    write_config,
)

AUDIT_ROWS_PER_MINUTE = 3
"""``api.auth_throttle_audit_rows_per_minute`` of the test service (default 20; 3 shows the cap)."""
FAILURES_BEFORE_THROTTLE = 10
"""``api.auth_failures_before_throttle`` (the default)."""
WRONG = "Bearer " + "x" * 43
PROXY_LIKE = "127.0.0.1"
"""The address uvicorn believes as a proxy by default (``FORWARDED_ALLOW_IPS``: 127.0.0.1, ::1): any
local process.  The forwarded-header tests send from it; its right token still works (item 5)."""

CLIENT = r"""
import json, sys, httpx
spec = json.loads(sys.argv[1])
out = []
for source, n, token, forwarded, path in spec["runs"]:
    transport = httpx.HTTPTransport(local_address=source)
    with httpx.Client(base_url=spec["base"], transport=transport, timeout=30.0) as c:
        for i in range(n):
            headers = {"Authorization": token}
            if forwarded:
                headers["X-Forwarded-For"] = forwarded.format(i=i)
            out.append(c.get(path, headers=headers).status_code)
print(json.dumps(out))
"""


def client_run(base: str, runs: list[tuple[str, int, str, str, str]]) -> list[int]:
    """Status codes of ``runs`` (source address, count, Authorization, X-Forwarded-For template or "",
    path), sent by a client process of its own, in order."""
    r = subprocess.run(
        [sys.executable, "-c", CLIENT, json.dumps({"base": base, "runs": runs})],
        cwd=REPO, capture_output=True, text=True, timeout=DEADLINE_S,
    )  # fmt: skip
    assert r.returncode == 0, r.stderr[-2000:]
    return list(json.loads(r.stdout))


def _supported(kw: dict[str, Any]) -> dict[str, Any]:
    """``kw`` minus the ``[api]`` settings this checkout does not know (so the module also runs against
    the code before issue 41, where each test must fail on its assertion)."""
    from service.settings import ApiSettings, DatabaseSettings

    known = {"api.": ApiSettings.model_fields, "database.": DatabaseSettings.model_fields}
    return {
        k: v
        for k, v in kw.items()
        if not any(k.startswith(p) and k[len(p) :] not in f for p, f in known.items())
    }


BUSY_TIMEOUT_S = 0.5
"""``database.busy_timeout_s`` of the test service (default 10 s; main waits its 10 s for each write)."""
LOCKER = r"""
import sqlite3, sys
c = sqlite3.connect(sys.argv[1], isolation_level=None)
c.execute("BEGIN EXCLUSIVE")
print("locked", flush=True)
sys.stdin.readline()
c.execute("ROLLBACK")
"""


@dataclass
class Auth:
    serve: ServeProcess
    client: httpx.Client
    db_path: Path
    igtl_port: int

    @property
    def base(self) -> str:
        return self.serve.base_url

    def audit(self, action: str) -> list[dict[str, Any]]:
        rows = self.client.get("/audit", params={"limit": 1000}).json()
        return [r for r in rows if r["action"] == action]


@pytest.fixture(scope="module")
def auth(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Auth]:
    root = tmp_path_factory.mktemp("auth")
    cfg, port, igtl_port = root / "oarmreg.toml", free_port(), free_port()
    write_config(cfg, _supported({
        "watch_dir": str(root / "watch"), "data_dir": str(root / "data"), "api_token": TOKEN,
        "port": port, "robot.link_url": f"simple-message://127.0.0.1:{free_port()}",
        "robot.connect_timeout_s": 1.0,
        "api.auth_throttle_audit_rows_per_minute": AUDIT_ROWS_PER_MINUTE,
        "database.busy_timeout_s": BUSY_TIMEOUT_S,
        "igtl.enabled": True, "igtl.port": igtl_port,
    }))  # fmt: skip
    with served(cfg, port) as (serve, client):
        yield Auth(serve, client, root / "data" / "oarmreg.sqlite3", igtl_port)


# ---------------------------------------------------------------------------- item 4


def test_item4_rotating_x_forwarded_for_does_not_dodge_the_throttle(auth: Auth) -> None:
    """Wrong tokens from one socket address, each with another ``X-Forwarded-For``: the throttle keys
    on the socket (before: all 3,000 answered 401, uvicorn believing loopback as a proxy)."""
    codes = client_run(
        auth.base, [(PROXY_LIKE, FAILURES_BEFORE_THROTTLE + 5, WRONG, "10.9.{i}.1", "/status")]
    )
    assert codes.count(401) <= FAILURES_BEFORE_THROTTLE, codes  # fewer if another test failed here first
    assert codes[FAILURES_BEFORE_THROTTLE:] == [429] * 5, codes


def test_item4_a_spoofed_address_cannot_lock_its_owner_out(auth: Auth) -> None:
    """A peer spoofing ``X-Forwarded-For: 127.0.41.3`` is throttled itself; the real 127.0.41.3 is not."""
    spoofer = client_run(
        auth.base, [(PROXY_LIKE, FAILURES_BEFORE_THROTTLE + 2, WRONG, "127.0.41.3", "/status")]
    )
    assert spoofer[-1] == 429, spoofer
    owner = client_run(
        auth.base,
        [("127.0.41.3", 1, WRONG, "", "/status"), ("127.0.41.3", 1, f"Bearer {TOKEN}", "", "/status")],
    )
    assert owner == [401, 200], owner


def test_item4_throttle_audit_rows_are_capped_with_one_summary_row(auth: Auth) -> None:
    """Six addresses each past the allowance write at most ``api.auth_throttle_audit_rows_per_minute``
    rows and one ``auth_throttle_summary`` (before: one row per address, 1,004 rows in 5 s)."""
    sources = [f"127.0.42.{k}" for k in range(1, 7)]
    codes = client_run(auth.base, [(s, FAILURES_BEFORE_THROTTLE + 1, WRONG, "", "/status") for s in sources])
    assert codes.count(429) == len(sources), codes
    rows = auth.audit("auth_throttle")
    ours = [r for r in rows if r["principal"] in {f"client:{s}" for s in sources}]
    assert len(rows) <= AUDIT_ROWS_PER_MINUTE, rows  # within the minute the module runs in
    assert len(ours) < len(sources), ours
    summaries = auth.audit("auth_throttle_summary")
    assert len(summaries) == 1, summaries
    assert "api.auth_throttle_audit_rows_per_minute" in summaries[0]["detail"]


# ---------------------------------------------------------------------------- item 5


def test_item5_the_right_token_works_while_its_address_is_throttled(auth: Auth) -> None:
    """A guesser on 127.0.43.1 is throttled; the navigation UI on the same address, polling with the
    right token, is answered 200 each time, and the guesser's next wrong token still 429."""
    guesser = client_run(auth.base, [("127.0.43.1", FAILURES_BEFORE_THROTTLE + 2, WRONG, "", "/status")])
    assert guesser[-1] == 429, guesser
    ui = client_run(auth.base, [("127.0.43.1", 5, f"Bearer {TOKEN}", "", "/registration/current"),
                                ("127.0.43.1", 1, WRONG, "", "/status")])  # fmt: skip
    assert all(c != 429 and c != 401 for c in ui[:5]), ui
    assert ui[5] == 429, ui


# ---------------------------------------------------------------------------- item 7


@pytest.mark.parametrize("weak", ["Xk9#mQ2!" * 3])
def test_item7_serve_refuses_a_repeated_hand_made_token(tmp_path: Path, weak: str) -> None:
    """``serve`` exits 3 naming the rule (the other weak tokens of the issue: tests/unit)."""
    cfg = tmp_path / "oarmreg.toml"
    write_config(cfg, {"watch_dir": str(tmp_path / "w"), "data_dir": str(tmp_path / "d"), "api_token": weak,
                       "port": free_port()})  # fmt: skip
    r = subprocess.run([sys.executable, "-m", "service.cli", "serve", "--config", str(cfg)],
                       cwd=REPO, capture_output=True, text=True, timeout=DEADLINE_S)  # fmt: skip
    assert r.returncode == 3, r.stderr[-2000:]
    assert "oarmreg token" in r.stderr + r.stdout


def test_item7_a_percent_encoded_ticket_is_redacted_in_the_log(auth: Auth) -> None:
    """``GET /events?%74icket=T`` is redeemed as ``?ticket=`` (the gate decodes the name) and the
    access log shows ``<redacted>``, never ``T`` (before: logged as sent)."""
    ticket = auth.client.post("/events/ticket", headers={"Content-Type": "application/json"}).json()["ticket"]
    with (
        httpx.Client(base_url=auth.base, timeout=DEADLINE_S) as anon,
        anon.stream("GET", f"/events?%74icket={ticket}") as stream,
    ):
        assert stream.status_code == 200
        wait_for(lambda: "%74icket=<redacted>" in auth.serve.log.read_text(), "the access log line")
    assert ticket not in auth.serve.log.read_text()


def test_item7_a_database_locked_by_another_process_is_503_and_the_audit_row_kept(auth: Auth) -> None:
    """Another process holds the database (``BEGIN EXCLUSIVE``): ``POST /qa/protocols`` is answered 503
    with ``Retry-After`` after ``database.busy_timeout_s`` (before: 500 after 20 s, its audit row
    lost); once released, the refusal's audit row is in the log."""
    assert auth.db_path.is_file(), sorted(p.name for p in auth.db_path.parent.iterdir())
    locker = subprocess.Popen([sys.executable, "-c", LOCKER, str(auth.db_path)], stdin=subprocess.PIPE,
                              stdout=subprocess.PIPE, text=True)  # fmt: skip
    try:
        assert locker.stdout is not None and locker.stdout.readline().strip() == "locked"
        body = {"name": "locked-out", "poses": [{"name": "p1", "joints_rad": [0, 0, 1.5, 0, 0.7, 0]}]}
        r = auth.client.post("/qa/protocols", json=body, timeout=60.0)
        assert r.status_code == 503, r.text
        assert int(r.headers["retry-after"]) >= 1
        assert r.json()["title"] == "Database busy"
    finally:
        assert locker.stdin is not None
        locker.stdin.write("\n")
        locker.stdin.close()
        locker.wait(30)
    rows = [e for e in auth.audit("qa_protocol_create") if e["outcome"] == "refused"]
    assert rows and rows[0]["detail"] == "Database busy", rows


IGTL_HEADER = struct.Struct(">H12s20sQQQ")


def test_item7_a_query_for_a_non_ascii_device_is_answered_with_a_status_and_logged(auth: Auth) -> None:
    """``GET_TRANS`` for device ``"été"`` (UTF-8 bytes): a STATUS NOT_FOUND comes back and the log names
    it escaped (before: the connection dropped, unanswered and unlogged)."""
    head = IGTL_HEADER.pack(1, b"GET_TRANS", "été".encode(), 0, 0, 0)  # empty body: CRC 0
    with socket.create_connection(("127.0.0.1", auth.igtl_port), timeout=DEADLINE_S) as s:
        s.sendall(head)
        f = s.makefile("rb")
        while True:  # the server may push its devices first
            raw = f.read(IGTL_HEADER.size)
            assert len(raw) == IGTL_HEADER.size, "connection closed without an answer"
            _, typ, _, _, size, _ = IGTL_HEADER.unpack(raw)
            body = f.read(size)
            if typ.rstrip(b"\0") == b"STATUS" and b"NOT_FOUND" in body:  # not the pushed "no registration"
                break
    assert b"printable ASCII" in body, body
    wait_for(lambda: "not a printable ASCII name" in auth.serve.log.read_text(), "the log line")
    line = next(x for x in auth.serve.log.read_text().splitlines() if "not a printable ASCII name" in x)
    assert "\\ufffd" in line or "\\x" in line, line
