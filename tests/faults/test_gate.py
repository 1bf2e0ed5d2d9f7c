"""Issue #13 items 2, 5, 6, 7 and #32 item 5: the gate in front of the real service (uvicorn on loopback).

Body limit and authentication before the body is read, CSRF (Content-Type) and DNS rebinding
(Host, Origin), docs behind the token, ids in SQLite's range with strict types, 500s that close
their connection without internals, single-use event tickets, the audit log.
"""

from __future__ import annotations

import hashlib
import io
import json
import logging
import secrets
import socket
import threading
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import httpx
import pytest

from tests.faults.conftest import (
    AUTH,
    JSON,
    RAW_TIMEOUT_S,
    TOKEN,
    RawResponse,
    Running,
    closed_by_peer,
    fault_settings,
    mock_robot,
    raw_http,
    read_response,
    serve,
)
from tests.helpers import http

TEN_MB = 10 * 1024 * 1024
SECRET_ROW = "ROW-TEXT-Doe^Jane-must-not-leak"


def _boom_route(app: Any) -> None:
    """A route with a bug (the 500 path): its exception text quotes 'row contents'."""

    async def boom() -> None:
        raise RuntimeError(f"could not decode row {SECRET_ROW}")

    app.add_api_route("/boom", boom, methods=["GET"])


@pytest.fixture(scope="module")
def svc(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Running]:
    root = tmp_path_factory.mktemp("gate")
    with mock_robot() as mock, serve(fault_settings(root, mock.url), app_hook=_boom_route) as s:
        yield s


def assert_problem(r: httpx.Response | Any, status: int) -> dict[str, Any]:
    import json

    code = r.status_code if isinstance(r, httpx.Response) else r.status
    body = r.content if isinstance(r, httpx.Response) else r.body
    headers = r.headers
    assert code == status, body
    assert headers["content-type"].startswith("application/problem+json"), headers
    problem: dict[str, Any] = json.loads(body)
    assert problem["status"] == status and problem["title"] and problem["detail"]
    return problem


# ---- item 2: body limit and auth before the body -------------------------------------------


def test_10mb_without_token_is_refused_from_the_headers(svc: Running) -> None:
    """401 arrives while the 10 MB body is still unsent: the service never read it."""
    head = f"POST /register HTTP/1.1\r\nHost: 127.0.0.1:{svc.port}\r\nContent-Type: application/json\r\n"
    head += f"Content-Length: {TEN_MB}"
    with socket.create_connection(("127.0.0.1", svc.port), timeout=RAW_TIMEOUT_S) as sock:
        sock.sendall(head.encode() + b"\r\n\r\n" + b"{" * 4096)  # a first slice only
        r = read_response(sock)
        assert r.headers.get("connection") == "close"
        assert closed_by_peer(sock)
    assert_problem(r, 401)
    assert r.headers["www-authenticate"].startswith("Bearer")


def test_declared_oversize_body_with_token_is_413(svc: Running) -> None:
    head = f"POST /register HTTP/1.1\r\nHost: 127.0.0.1:{svc.port}\r\nAuthorization: Bearer {TOKEN}\r\n"
    head += f"Content-Type: application/json\r\nContent-Length: {TEN_MB}"
    r = raw_http(svc.port, head)
    assert "max_body_bytes" in assert_problem(r, 413)["detail"]
    assert r.headers.get("connection") == "close"


def test_chunked_oversize_body_is_counted_and_refused(svc: Running) -> None:
    """No Content-Length: the gate counts the streamed bytes and stops at the limit."""
    limit = svc.app.state.ctx.settings.api.max_body_bytes
    head = f"POST /register HTTP/1.1\r\nHost: 127.0.0.1:{svc.port}\r\nAuthorization: Bearer {TOKEN}\r\n"
    head += "Content-Type: application/json\r\nTransfer-Encoding: chunked"
    chunk = b" " * 65536
    body = b"".join(b"%x\r\n%s\r\n" % (len(chunk), chunk) for _ in range(limit // len(chunk) + 2))
    with socket.create_connection(("127.0.0.1", svc.port), timeout=RAW_TIMEOUT_S) as sock:
        sock.sendall(head.encode() + b"\r\n\r\n" + body)  # just over the limit, unterminated
        r = read_response(sock)
    assert_problem(r, 413)


def test_small_chunked_body_is_admitted(svc: Running) -> None:
    head = f"POST /register HTTP/1.1\r\nHost: 127.0.0.1:{svc.port}\r\nAuthorization: Bearer {TOKEN}\r\n"
    head += "Content-Type: application/json\r\nTransfer-Encoding: chunked"
    body = b'{"scan_id": 7}'
    r = raw_http(svc.port, head, b"%x\r\n%s\r\n0\r\n\r\n" % (len(body), body))
    assert "scan 7 does not exist" in assert_problem(r, 404)["detail"]  # parsed, routed, answered


# ---- item 5: CSRF and DNS rebinding ---------------------------------------------------------


def test_cross_site_text_plain_post_is_refused(svc: Running) -> None:
    """The tester's page: bodiless POST /register, text/plain, foreign Origin (no token needed to fail)."""
    r = http.post(
        svc.base_url + "/register", headers={"Content-Type": "text/plain", "Origin": "http://evil.example"}
    )
    assert "api.allowed_origins" in assert_problem(r, 403)["detail"]


@pytest.mark.parametrize(
    "ctype", [None, "text/plain", "application/x-www-form-urlencoded", "multipart/form-data"]
)
def test_mutation_needs_json_content_type(svc: Running, ctype: str | None) -> None:
    headers = {} if ctype is None else {"Content-Type": ctype}
    r = svc.client.post("/register", headers=headers)
    assert "application/json" in assert_problem(r, 415)["detail"]
    r = svc.client.post("/events/ticket", headers=headers)
    assert_problem(r, 415)


def test_bodiless_json_post_is_admitted(svc: Running) -> None:
    r = svc.client.post("/register", headers=JSON)
    assert_problem(r, 409)  # no scan yet: the route ran


@pytest.mark.parametrize(
    "host", ["evil.example", "evil.example:{port}", "127.0.0.1:1", "localhost.evil.example:{port}"]
)
def test_foreign_host_is_refused(svc: Running, host: str) -> None:
    r = svc.client.get("/status", headers={"Host": host.format(port=svc.port)})
    assert "api.allowed_hosts" in assert_problem(r, 400)["detail"]


def test_rebinding_page_cannot_read_health_either(svc: Running) -> None:
    assert_problem(http.get(svc.base_url + "/health", headers={"Host": f"evil.example:{svc.port}"}), 400)


@pytest.mark.parametrize("host", ["127.0.0.1:{port}", "localhost:{port}", "LOCALHOST:{port}"])
def test_own_host_names_are_allowed(svc: Running, host: str) -> None:
    r = svc.client.get("/status", headers={"Host": host.format(port=svc.port)})
    assert r.status_code == 200, r.text


@pytest.mark.parametrize("origin", ["http://evil.example", "null", "http://127.0.0.1:1", "https://localhost"])
def test_foreign_origin_is_refused_even_with_token(svc: Running, origin: str) -> None:
    assert_problem(svc.client.post("/register", headers={**JSON, "Origin": origin}), 403)
    assert_problem(svc.client.get("/status", headers={"Origin": origin}), 403)


def test_same_origin_browser_request_is_allowed(svc: Running) -> None:
    r = svc.client.get("/status", headers={"Origin": f"http://localhost:{svc.port}"})
    assert r.status_code == 200, r.text


# ---- item 6: docs behind the token ----------------------------------------------------------


@pytest.mark.parametrize("path", ["/openapi.json", "/status", "/audit", "/events", "/verifications"])
def test_everything_but_health_needs_the_token(svc: Running, path: str) -> None:
    assert_problem(http.get(svc.base_url + path), 401)
    assert_problem(
        http.get(svc.base_url + path, headers={"Authorization": "Bearer wrong-token-0123456789"}), 401
    )
    assert http.get(svc.base_url + "/health").status_code == 200


def test_docs_with_token(svc: Running) -> None:
    assert svc.client.get("/openapi.json").status_code == 200
    assert svc.client.get("/docs").status_code == 200  # the shell is public (issue #21): no data in it
    assert_problem(svc.client.get("/redoc"), 404)  # removed: /docs is self-hosted, ReDoc is not


def test_docs_can_be_switched_off(tmp_path: Path) -> None:
    with mock_robot() as mock, serve(fault_settings(tmp_path, mock.url, **{"api.docs": False})) as s:
        for path in ("/docs", "/redoc", "/openapi.json", "/static/swagger/swagger-ui-bundle.js"):
            assert_problem(s.client.get(path), 404)


# ---- item 7: ids, strict types, 500s --------------------------------------------------------


@pytest.mark.parametrize(
    "path",
    [
        "/registrations/9223372036854775808",
        "/registrations/99999999999999999999999",
        "/scans/0",
        "/scans/-1",
        "/verifications/9223372036854775808",
        "/verifications/9223372036854775808/histogram.png",
        "/registrations?offset=9223372036854775808",
        "/scans?offset=-1",
        "/audit?limit=0",
    ],
)
def test_out_of_range_ids_are_422(svc: Running, path: str) -> None:
    assert_problem(svc.client.get(path), 422)


def test_largest_id_is_a_plain_404(svc: Running) -> None:
    assert_problem(svc.client.get(f"/registrations/{2**63 - 1}"), 404)


@pytest.mark.parametrize(
    "body",
    [
        {"scan_id": True},
        {"scan_id": "3"},
        {"scan_id": 3.0},
        {"scan_id": 2**63},
        {"scan_id": 0},
        {"targets_image_mm": [[True, 0.0, 0.0]]},
        {"targets_image_mm": [["1", 0.0, 0.0]]},
    ],
)
@pytest.mark.parametrize("route", ["/register", "/verify"])
def test_non_strict_bodies_are_422(svc: Running, body: dict[str, Any], route: str) -> None:
    if route == "/verify" and "targets_image_mm" in body:
        body = {"scan_id": body["targets_image_mm"][0][0]}
    assert_problem(svc.client.post(route, json=body), 422)


def test_old_targets_name_is_a_422_naming_the_new_one(svc: Running) -> None:
    """Issue 31 item 7: ``targets_mm`` meant image-frame points here and robot-frame points in the CLI;
    the API's name is now ``targets_image_mm`` and the old one is refused, naming it."""
    body = assert_problem(svc.client.post("/register", json={"targets_mm": [[1.0, 2.0, 3.0]]}), 422)
    assert "targets_mm was renamed targets_image_mm" in json.dumps(body), body


def test_500_closes_the_connection_cleanly_without_internals(svc: Running) -> None:
    with socket.create_connection(("127.0.0.1", svc.port), timeout=RAW_TIMEOUT_S) as sock:
        head = f"GET /boom HTTP/1.1\r\nHost: 127.0.0.1:{svc.port}\r\nAuthorization: Bearer {TOKEN}"
        sock.sendall(head.encode() + b"\r\n\r\n")
        r = read_response(sock)
        assert r.headers.get("connection") == "close"
        assert closed_by_peer(sock)
    problem = assert_problem(r, 500)
    assert SECRET_ROW not in r.body.decode() and "RuntimeError" not in r.body.decode()
    assert problem["type"].endswith("internal")


def test_keep_alive_client_carries_on_after_a_500(svc: Running) -> None:
    with httpx.Client(base_url=svc.base_url, headers=AUTH) as c:
        for _ in range(3):
            assert_problem(c.get("/boom"), 500)
            assert c.get("/status").status_code == 200  # no reset: the 500 said Connection: close


# ---- event tickets and the audit log --------------------------------------------------------


def _first_sse_line(base_url: str, query: str) -> tuple[int, str]:
    with httpx.Client(base_url=base_url) as c, c.stream("GET", "/events" + query) as r:
        if r.status_code != 200:
            r.read()
            return r.status_code, r.text
        return 200, next(r.iter_lines())


def test_event_ticket_is_single_use(svc: Running) -> None:
    t = svc.client.post("/events/ticket", headers=JSON)
    assert t.status_code == 200, t.text
    ticket = t.json()["ticket"]
    assert t.json()["url"] == f"/events?ticket={ticket}" and t.json()["expires_in_s"] > 0
    assert _first_sse_line(svc.base_url, f"?ticket={ticket}") == (200, ": connected")
    status, text = _first_sse_line(svc.base_url, f"?ticket={ticket}")
    assert status == 401 and "used or expired" in text
    assert _first_sse_line(svc.base_url, "?ticket=made-up")[0] == 401


def test_ticket_is_only_for_events(svc: Running) -> None:
    ticket = svc.client.post("/events/ticket", headers=JSON).json()["ticket"]
    assert_problem(http.get(f"{svc.base_url}/status?ticket={ticket}"), 401)


def test_audit_names_the_token_by_hash_only(svc: Running) -> None:
    r = svc.client.post("/register", json={"scan_id": 123456})
    assert_problem(r, 404)
    entries = svc.client.get("/audit").json()
    mine = next(e for e in entries if e["action"] == "register" and e["outcome"] == "refused")
    assert mine["principal"] == "token:" + hashlib.sha256(TOKEN.encode()).hexdigest()[:12]
    assert mine["detail"] == "Not found"
    assert TOKEN not in svc.client.get("/audit").text


# ---- issue #32 item 5: failed authentications throttled per address; the ticket never logged --
# Different clients are raw sockets bound to other loopback source addresses: 127.0.0.2 guesses,
# 127.0.0.1 (the module's client) and 127.0.0.3 are the others.

GUESSES = 3000
ALLOWED = 10
"""api.auth_failures_before_throttle (the default): wrong tokens answered 401 before 429."""


def _connect(port: int, source: str) -> socket.socket:
    return socket.create_connection(("127.0.0.1", port), timeout=RAW_TIMEOUT_S, source_address=(source, 0))


def _get(port: int, path: str, token: str | None) -> bytes:
    auth = f"Authorization: Bearer {token}\r\n" if token is not None else ""
    return f"GET {path} HTTP/1.1\r\nHost: 127.0.0.1:{port}\r\n{auth}\r\n".encode()


def _pipelined(port: int, source: str, requests: list[bytes]) -> list[RawResponse]:
    """Send ``requests`` back to back on one connection from ``source``; read every response."""
    with _connect(port, source) as sock:
        sender = threading.Thread(target=sock.sendall, args=(b"".join(requests),), daemon=True)
        sender.start()
        try:
            out = [_read_one(sock) for _ in requests]
        finally:
            _pending.pop(sock.fileno(), None)  # file numbers are reused by later sockets
        sender.join(RAW_TIMEOUT_S)
        return out


_pending: dict[int, bytes] = {}


def _read_one(sock: socket.socket) -> RawResponse:
    """One response; bytes already received past it are kept for the next call (pipelining)."""
    buf = _pending.pop(sock.fileno(), b"")
    while b"\r\n\r\n" not in buf:
        chunk = sock.recv(65536)
        if not chunk:
            raise ConnectionError(f"closed before a full response head: {buf[:200]!r}")
        buf += chunk
    head, _, rest = buf.partition(b"\r\n\r\n")
    lines = head.decode("latin-1").split("\r\n")
    headers = {k.strip().lower(): v.strip() for k, _, v in (ln.partition(":") for ln in lines[1:])}
    length = int(headers.get("content-length", "0"))
    while len(rest) < length:
        chunk = sock.recv(65536)
        if not chunk:
            break
        rest += chunk
    _pending[sock.fileno()] = rest[length:]
    return RawResponse(int(lines[0].split()[1]), headers, rest[:length])


def test_guessing_is_throttled_per_address_and_audited(svc: Running) -> None:
    wrong = [_get(svc.port, "/status", secrets.token_urlsafe(32)) for _ in range(GUESSES)]
    answers = _pipelined(svc.port, "127.0.0.2", wrong)
    statuses = [r.status for r in answers]
    assert statuses[:ALLOWED] == [401] * ALLOWED
    assert statuses[ALLOWED:] == [429] * (GUESSES - ALLOWED), sorted(set(statuses[ALLOWED:]))
    waits = {int(r.headers["retry-after"]) for r in answers[ALLOWED:]}
    assert min(waits) >= 1 and max(waits) <= 30, waits
    problem = json.loads(answers[-1].body)
    assert problem["status"] == 429 and "api.auth_failures_before_throttle" in problem["detail"]

    # locked out: a wrong token from that address is 429, the right one still works (issue 41) ...
    right, locked = _pipelined(
        svc.port, "127.0.0.2", [_get(svc.port, "/status", TOKEN), _get(svc.port, "/status", "x" * 30)]
    )
    assert right.status == 200
    assert locked.status == 429 and 1 <= int(locked.headers["retry-after"]) <= 30
    # ... while other addresses are unaffected: the right token works, a wrong one is a plain 401
    assert svc.client.get("/status").status_code == 200  # from 127.0.0.1
    other = _pipelined(
        svc.port, "127.0.0.3", [_get(svc.port, "/status", TOKEN), _get(svc.port, "/status", "x")]
    )
    assert [r.status for r in other] == [200, 401]

    entries = [e for e in svc.client.get("/audit").json() if e["action"] == "auth_throttle"]
    assert [e["principal"] for e in entries] == ["client:127.0.0.2"]  # one entry for the burst
    assert (
        entries[0]["outcome"] == "throttled"
        and f"{ALLOWED + 1} failed authentications" in entries[0]["detail"]
    )


def test_requests_without_authorization_are_not_counted(svc: Running) -> None:
    anonymous = [_get(svc.port, "/status", None) for _ in range(5 * ALLOWED)]
    anonymous += [
        f"GET /status HTTP/1.1\r\nHost: 127.0.0.1:{svc.port}\r\nAuthorization: \r\n\r\n".encode()
    ] * 5
    assert {r.status for r in _pipelined(svc.port, "127.0.0.4", anonymous)} == {401}
    (first_wrong,) = _pipelined(svc.port, "127.0.0.4", [_get(svc.port, "/status", "y" * 30)])
    assert first_wrong.status == 401  # not 429: the 50 header-less requests were not failures


def test_the_event_ticket_never_reaches_the_access_log(svc: Running) -> None:
    access = logging.getLogger("uvicorn.access")
    text = io.StringIO()
    handler = logging.StreamHandler(text)
    handler.setFormatter(logging.Formatter("%(message)s"))
    old_level = access.level
    access.addHandler(handler)
    access.setLevel(logging.INFO)
    try:
        ticket = svc.client.post("/events/ticket", headers=JSON).json()["ticket"]
        with httpx.Client(base_url=svc.base_url) as c, c.stream("GET", f"/events?ticket={ticket}") as r:
            assert r.status_code == 200 and next(r.iter_lines()) == ": connected"
        assert http.get(f"{svc.base_url}/events?ticket={ticket}").status_code == 401  # used up: logged too
        assert svc.client.get("/health", headers=AUTH).status_code == 200  # a line after them
    finally:
        access.removeHandler(handler)
        access.setLevel(old_level)
    log = text.getvalue()
    assert "/health" in log and log.count("/events?ticket=<redacted>") == 2, log
    assert ticket not in log
