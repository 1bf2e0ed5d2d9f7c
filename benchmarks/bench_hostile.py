"""``/health`` latency and service memory under the hostile mix of issue 32.

Starts ``python -m service.cli serve`` (a process of its own, the DICOM SCP and the OpenIGTLink
server on, the mock robot controller in another process), then, over loopback:

1. idle: ``--probes`` sequential ``GET /health`` on fresh connections (median, p95), RSS, descriptors;
2. the hostile mix: ``--peers`` idle TCP connections to each of the HTTP and OpenIGTLink ports and
   ``--stalled`` OpenIGTLink peers stalled half-way through an 8 MiB STATUS body; once the service
   has taken the burst (its descriptor count still for 3 s; the time it took is printed) the same
   probes, RSS and descriptors, and whether a DICOM association still works (dcmtk ``echoscu``; the
   issue's failure was every association aborted above 1024 descriptors);
3. OpenIGTLink (issue 41 items 1 and 2, :func:`_igtl_probes`): 1 x ``GET_POINT`` and 8 x ``GET_TRANS``
   flooders that never read (processes under ``nice -n 19``, 10 s each): ``/health`` median / max and a
   navigation client's worst ``ToolToImage`` gap; then 32 idle sockets from 127.0.0.5: how many are
   held, whether a client from 127.0.0.6 still receives, what ``/ready`` lists;
4. HTTP slow readers (issue 41 item 3, :func:`_slow_reader_probe`): 300 connections from 127.0.0.44
   pipelining ten GETs of the 1.7 MB Swagger bundle and never reading: ``/health`` answered of
   ``--probes``, median and max.

"Before" is the same run against the code before issue 32: ``--checkout DIR`` runs the service
from another checkout (``git worktree add /tmp/before <commit>``); settings it does not know
(``api.max_connections``, ``api.first_request_timeout_s``) are left out.  A probe that gets no
answer within ``--timeout`` counts as a failure, not a latency.  Bounded: a fixed number of
probes and peers, loopback only.

Run: ``.venv/bin/python -m benchmarks.bench_hostile [--peers 1100] [--stalled 20] [--probes 40]
[--checkout DIR]``.  The process raises its own ``RLIMIT_NOFILE`` for the peers.
"""

from __future__ import annotations

import argparse
import contextlib
import errno
import os
import resource
import secrets
import select
import shutil
import socket
import statistics
import struct
import subprocess
import sys
import tempfile
import time
from collections.abc import Iterator
from pathlib import Path

import httpx

from benchmarks.hostile_clients import IGTL_FLOODER, SLOW_READER

REPO = Path(__file__).resolve().parents[1]
TOKEN = secrets.token_urlsafe(32)  # the token rule (docs/security.md) refuses a patterned one
IGTL_HEADER = struct.Struct(">H12s20sQQQ")
STALLED_ANNOUNCED = 8 * 1024 * 1024
STALLED_SENT = 1024 * 1024
START_TIMEOUT_S = 120.0
CONNECT_TIMEOUT_S = 120.0
"""A connect past a full listen backlog completes on a SYN retry (1, 3, 7 … s later)."""


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def _wait(pred: object, what: str, timeout_s: float) -> None:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if pred():  # type: ignore[operator]
            return
        time.sleep(0.05)  # polling a child process's state: nothing to wait on
    raise TimeoutError(f"{what} not within {timeout_s} s")


@contextlib.contextmanager
def _mock_robot(checkout: Path) -> Iterator[str]:
    mock = subprocess.Popen(
        [sys.executable, "-m", "service.cli", "mock", "robot", "--link", "simple-message://127.0.0.1:0"],
        cwd=checkout, stdout=subprocess.PIPE, text=True, env={**os.environ, "PYTHONPATH": str(checkout)},
    )  # fmt: skip
    try:
        assert mock.stdout is not None
        yield mock.stdout.readline().strip()
    finally:
        mock.terminate()
        mock.wait(30)


@contextlib.contextmanager
def _service(
    checkout: Path, root: Path, link: str
) -> Iterator[tuple[subprocess.Popen[bytes], dict[str, int]]]:
    ports = {"http": _free_port(), "dicom": _free_port(), "igtl": _free_port()}
    new = "max_connections" in (checkout / "service" / "settings.py").read_text()
    lines = [
        f'watch_dir = "{root / "watch"}"', f'data_dir = "{root / "data"}"', f'api_token = "{TOKEN}"',
        f"port = {ports['http']}", "[robot]", f'link_url = "{link}"',
        "[dicom]", "enabled = true", f"port = {ports['dicom']}",
        "[igtl]", "enabled = true", f"port = {ports['igtl']}",
    ]  # fmt: skip
    if new:
        lines += ["[api]", "max_connections = 256", "first_request_timeout_s = 10.0"]
    cfg = root / "oarmreg.toml"
    cfg.write_text("\n".join(lines) + "\n")
    with (root / "serve.log").open("wb") as log:
        proc = subprocess.Popen(
            [sys.executable, "-m", "service.cli", "serve", "--config", str(cfg)],
            cwd=checkout, stdout=log, stderr=subprocess.STDOUT,
            env={**os.environ, "PYTHONPATH": str(checkout)},
        )  # fmt: skip
    try:

        def up() -> bool:
            if proc.poll() is not None:
                raise RuntimeError(
                    f"serve exited {proc.returncode}: {(root / 'serve.log').read_text()[-2000:]}"
                )
            with contextlib.suppress(httpx.HTTPError):
                return httpx.get(f"http://127.0.0.1:{ports['http']}/health", timeout=2.0).status_code == 200
            return False

        _wait(up, "the service", START_TIMEOUT_S)
        yield proc, ports
    finally:
        proc.terminate()
        proc.wait(30)


def _connect_all(port: int, n: int, stack: contextlib.ExitStack) -> list[socket.socket]:
    socks = []
    for _ in range(n):
        s = stack.enter_context(socket.socket())
        s.setblocking(False)
        err = s.connect_ex(("127.0.0.1", port))
        if err not in (0, errno.EINPROGRESS):
            raise OSError(err, os.strerror(err))
        socks.append(s)
    pending = list(socks)
    deadline = time.monotonic() + CONNECT_TIMEOUT_S
    while pending and time.monotonic() < deadline:
        p = select.poll()
        for s in pending:
            p.register(s.fileno(), select.POLLOUT)
        done = {fd for fd, _ in p.poll(1000)}
        pending = [s for s in pending if s.fileno() not in done]
    print(f"  {n - len(pending)} of {n} peers connected to port {port}")
    return socks


def _stall(port: int, n: int, stack: contextlib.ExitStack) -> None:
    head = IGTL_HEADER.pack(1, b"STATUS", b"stall", 0, STALLED_ANNOUNCED, 0)
    for s in _connect_all(port, n, stack):
        with contextlib.suppress(BlockingIOError, ConnectionError):
            s.send(head + b"\0" * STALLED_SENT)


def _settle(pid: int, timeout_s: float) -> tuple[float, int]:
    """Until the service's descriptor count holds still for 3 s (it has accepted the burst or
    dropped what it drops): (seconds taken, descriptors)."""
    t0 = time.monotonic()
    last, since = -1, t0
    while time.monotonic() - t0 < timeout_s:
        n = len(os.listdir(f"/proc/{pid}/fd"))
        if n != last:
            last, since = n, time.monotonic()
        elif time.monotonic() - since >= 3.0:
            break
        time.sleep(0.2)  # sampling a count: nothing to wait on
    return time.monotonic() - t0, last


def _probes(url: str, n: int, timeout_s: float) -> tuple[list[float], int]:
    """``n`` ``GET /health`` on fresh connections: latencies of the 200s (s), failures."""
    lat, failed = [], 0
    for _ in range(n):
        t0 = time.perf_counter()
        try:
            ok = httpx.get(url + "/health", timeout=timeout_s).status_code == 200
        except httpx.HTTPError:
            ok = False
        if ok:
            lat.append(time.perf_counter() - t0)
        else:
            failed += 1
    return lat, failed


def _rss_mb(pid: int) -> float:
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) / 1024
    return float("nan")


def _echo(port: int) -> str:
    echoscu = shutil.which("echoscu")
    if echoscu is None:
        return "echoscu not installed"
    r = subprocess.run([echoscu, "-aec", "OARMREG", "127.0.0.1", str(port)], capture_output=True, timeout=60)
    return "ok" if r.returncode == 0 else f"FAILED ({r.stderr.decode(errors='replace').strip()[-80:]})"


def _row(label: str, pid: int, url: str, a: argparse.Namespace) -> str:
    lat, failed = _probes(url, a.probes, a.timeout)
    med = f"{statistics.median(lat) * 1e3:7.1f}" if lat else "      -"
    p95 = f"{sorted(lat)[int(0.95 * (len(lat) - 1))] * 1e3:7.1f}" if lat else "      -"
    fds = len(os.listdir(f"/proc/{pid}/fd"))
    return f"{label:<8} | {med} | {p95} | {failed:>3}/{a.probes:<3} | {_rss_mb(pid):6.0f} | {fds:>5}"


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0] if __doc__ else None)
    p.add_argument("--peers", type=int, default=1100, help="idle peers on each of HTTP and OpenIGTLink")
    p.add_argument("--igtl-peers", type=int, default=None, help="idle OpenIGTLink peers (default: --peers)")
    p.add_argument("--stalled", type=int, default=20, help="OpenIGTLink peers stalled mid-body")
    p.add_argument("--probes", type=int, default=40, help="GET /health per phase")
    p.add_argument("--timeout", type=float, default=10.0, help="a probe with no answer by then failed, s")
    p.add_argument("--checkout", type=Path, default=REPO, help="run the service from this checkout")
    a = p.parse_args(argv)
    igtl_peers = a.peers if a.igtl_peers is None else a.igtl_peers
    need = a.peers + igtl_peers + a.stalled + 256
    soft, hard = resource.getrlimit(resource.RLIMIT_NOFILE)
    if soft != resource.RLIM_INFINITY and soft < need:
        resource.setrlimit(resource.RLIMIT_NOFILE, (min(need, hard), hard))
    checkout = a.checkout.resolve()
    with (
        tempfile.TemporaryDirectory(prefix="oarmreg-hostile-") as tmp,
        _mock_robot(checkout) as link,
        _service(checkout, Path(tmp), link) as (proc, ports),
    ):
        url = f"http://127.0.0.1:{ports['http']}"
        print(
            f"service from {checkout}: {a.peers} idle peers on HTTP, {igtl_peers} on OpenIGTLink, "
            f"{a.stalled} stalled OpenIGTLink bodies; /health probes time out after {a.timeout:g} s"
        )
        print("phase    | med ms  | p95 ms  | failed  | RSS MB | fds   ")
        print(_row("idle", proc.pid, url, a) + f" | DICOM echo {_echo(ports['dicom'])}")
        with contextlib.ExitStack() as stack:
            _connect_all(ports["http"], a.peers, stack)
            _connect_all(ports["igtl"], igtl_peers, stack)
            _stall(ports["igtl"], a.stalled, stack)
            settle_s, fds = _settle(proc.pid, 120.0)
            print(f"  the service settled in {settle_s:.1f} s at {fds} descriptors")
            print(_row("hostile", proc.pid, url, a) + f" | DICOM echo {_echo(ports['dicom'])}")
        print(_forwarded_probe(url, 3000))
        _igtl_probes(url, ports["igtl"])
        print(_slow_reader_probe(url, ports["http"], 300, a.probes, a.timeout))
    return 0


def _forwarded_probe(url: str, n: int) -> str:
    """Issue 41 item 4: ``n`` wrong tokens from 127.0.0.1 (the proxy uvicorn believes by default), each
    with another ``X-Forwarded-For``: how many were throttled (429) and how many ``auth_throttle`` audit
    rows they wrote.  Before: all 401 at ~4,400/s, one audit row per spoofed address."""
    codes: dict[int, int] = {}
    t0 = time.monotonic()
    with httpx.Client(base_url=url, timeout=10.0) as c:
        for i in range(n):
            fwd = f"10.{(i >> 16) & 255}.{(i >> 8) & 255}.{i & 255}"
            r = c.get("/status", headers={"Authorization": "Bearer " + "x" * 43, "X-Forwarded-For": fwd})
            codes[r.status_code] = codes.get(r.status_code, 0) + 1
        elapsed_s = time.monotonic() - t0
        audit = c.get("/audit", params={"limit": 1000}, headers={"Authorization": f"Bearer {TOKEN}"}).json()
    rows = sum(1 for e in audit if str(e.get("action", "")).startswith("auth_throttle"))
    return (
        f"forwarded-address probe: {n} wrong tokens, rotating X-Forwarded-For, {n / elapsed_s:,.0f}/s: "
        f"{codes.get(401, 0)} answered 401, {codes.get(429, 0)} answered 429; {rows} auth_throttle audit rows"
    )


# ------------------------------------------------------------- OpenIGTLink (issue 41 items 1, 2)


def _igtl_reader(port: int, source: str, arrivals: list[float], stop: list[bool]) -> socket.socket:
    """A navigation client bound to ``source`` reading every message on a thread of its own; appends
    ``time.monotonic()`` of each ``ToolToImage`` to ``arrivals``.  Close the returned socket to end it."""
    import threading

    s = socket.socket()
    s.bind((source, 0))
    s.settimeout(30.0)
    s.connect(("127.0.0.1", port))

    def run() -> None:
        f = s.makefile("rb")
        with contextlib.suppress(OSError, ValueError):
            while not stop:
                head = f.read(IGTL_HEADER.size)
                if len(head) < IGTL_HEADER.size:
                    return
                _, _, dev, _, size, _ = IGTL_HEADER.unpack(head)
                f.read(size)
                if dev.rstrip(b"\0") == b"ToolToImage":
                    arrivals.append(time.monotonic())

    threading.Thread(target=run, name="bench-igtl-reader", daemon=True).start()
    return s


def _igtl_flood_probe(url: str, port: int, kind: str, peers: int, seconds: float, before: str) -> str:
    """``peers`` processes (``nice -n 19``, each on its own loopback address) flood ``kind`` queries
    without reading for ``seconds`` while ``/health`` is probed back to back and a navigation client
    on 127.0.40.1 reads: ``/health`` median / max, the client's worst ``ToolToImage`` gap, drops."""
    import itertools

    arrivals: list[float] = []
    stop: list[bool] = []
    nav = _igtl_reader(port, "127.0.40.1", arrivals, stop)
    _wait(lambda: len(arrivals) >= 2, "the navigation client's first ToolToImage", 30.0)
    procs = [
        subprocess.Popen(
            ["nice", "-n", "19", sys.executable, "-c", IGTL_FLOODER, str(port), f"127.0.41.{10 + i}", kind],
            stdout=subprocess.PIPE,
            text=True,
        )
        for i in range(peers)
    ]
    lat: list[float] = []
    failed = 0
    try:
        for p in procs:
            assert p.stdout is not None
            p.stdout.readline()
        t0 = time.monotonic()
        while time.monotonic() - t0 < seconds:
            p0 = time.monotonic()
            try:
                ok = httpx.get(url + "/health", timeout=30.0).status_code == 200
            except httpx.HTTPError:
                ok = False
            if ok:
                lat.append(time.monotonic() - p0)
            else:
                failed += 1
        t1 = time.monotonic()
    finally:
        for p in procs:
            p.terminate()
        drops = sum(p.communicate(timeout=30)[0].split().count("dropped") for p in procs)
        stop.append(True)
        nav.close()
    times = [t0, *(t for t in arrivals if t0 <= t <= t1), t1]
    gap_ms = max(b - a for a, b in itertools.pairwise(times)) * 1e3
    med = f"{statistics.median(lat) * 1e3:.1f}" if lat else "-"
    top = f"{max(lat) * 1e3:.1f}" if lat else "-"
    return (
        f"igtl flood, {peers} x {kind} never reading (nice 19), {seconds:g} s: /health median {med} ms, "
        f"max {top} ms ({len(lat)} probes, {failed} failed); ToolToImage worst gap {gap_ms:.0f} ms; "
        f"flooders dropped {drops} times  [before the fix: {before}]"
    )


def _igtl_slot_probe(url: str, port: int, idle: int) -> str:
    """``idle`` idle sockets from 127.0.0.5: how many the listener holds; whether a client from
    127.0.0.6 still connects and receives; the problems ``/ready`` lists."""

    def outcome(s: socket.socket) -> bool:
        try:
            return bool(s.recv(IGTL_HEADER.size))
        except OSError:
            return False

    with contextlib.ExitStack() as stack:
        socks = []
        for _ in range(idle):
            s = stack.enter_context(socket.socket())
            s.bind(("127.0.0.5", 0))
            s.settimeout(30.0)
            s.connect(("127.0.0.1", port))
            socks.append(s)
        held = sum(outcome(s) for s in socks)
        with socket.socket() as other:
            other.bind(("127.0.0.6", 0))
            other.settimeout(30.0)
            t0 = time.monotonic()
            other.connect(("127.0.0.1", port))
            got = outcome(other)
            first_ms = (time.monotonic() - t0) * 1e3
        r = httpx.get(url + "/ready", headers={"Authorization": f"Bearer {TOKEN}"}, timeout=30.0)
        types = [str(p["type"]).rsplit(":", 1)[-1] for p in r.json().get("problems", [])]
    other_says = f"received its first message in {first_ms:.0f} ms" if got else "got EOF"
    return (
        f"igtl slots: {idle} idle sockets from 127.0.0.5: {held} held, {idle - held} closed; a client from "
        f"127.0.0.6 {other_says}; /ready {r.status_code} {types}  [before the fix: all {idle} held, "
        "the next client got EOF, /ready 200 with no problem]"
    )


def _slow_reader_probe(url: str, port: int, n: int, probes: int, timeout_s: float) -> str:
    """``n`` connections from 127.0.0.44 (a process of its own, niced), each pipelining ten GETs of
    the 1.7 MB Swagger bundle and never reading; ``/health`` probes from 127.0.0.1 meanwhile."""
    proc = subprocess.Popen(
        ["nice", "-n", "19", sys.executable, "-c", SLOW_READER, str(port), "127.0.0.44", str(n)],
        stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True,
    )  # fmt: skip
    try:
        assert proc.stdout is not None and proc.stdout.readline().strip() == "holding"
        lat, failed = _probes(url, probes, timeout_s)
    finally:
        proc.kill()
        proc.communicate(timeout=30)
    med = f"{statistics.median(lat) * 1e3:.1f} ms" if lat else "-"
    worst = f"{max(lat) * 1e3:.1f} ms" if lat else "-"
    return (
        f"slow readers: {n} connections pipelining 10 x 1.7 MB GETs, never reading: /health "
        f"{probes - failed} of {probes} answered, median {med}, max {worst} (before the write deadline "
        "and the per-address share: 0 of 20)"
    )


def _igtl_probes(url: str, port: int) -> None:
    print(_igtl_flood_probe(url, port, "GET_POINT", 1, 10.0, "/health median 6.4 s, ToolToImage gap 4.5 s"))
    print(_igtl_flood_probe(url, port, "GET_TRANS", 8, 10.0, "/health median 10.8 s, ToolToImage gap 12.2 s"))
    _wait(lambda: _igtl_clients(url) == 0, "the flooders' connections to close", 30.0)
    print(_igtl_slot_probe(url, port, 32))


def _igtl_clients(url: str) -> int:
    r = httpx.get(url + "/status", headers={"Authorization": f"Bearer {TOKEN}"}, timeout=30.0)
    return int(r.json()["listeners"]["igtl"]["clients"])


if __name__ == "__main__":
    raise SystemExit(main())
