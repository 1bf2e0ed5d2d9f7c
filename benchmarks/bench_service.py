"""Service benchmarks (issue #6).

1. ``POST /register`` on a 512 × 512 × 192 scan (simulator preset ``oarm``) against the I/O
   floor (``naive_read_series`` on the same folder, same run).  Target: ≤ 1.3 × floor + 0.1 s.
   Measured twice: with the volume the watcher already loaded (the production path: the
   watcher loads each series when it completes) and cold (cache cleared: load + MAR + detect +
   register).
2. ``GET /registration/current`` latency with 50 concurrent clients running in a SECOND process
   on loopback (bounded: 40 requests per client and 60 s).  Target: p99 ≤ 20 ms.

Run: ``.venv/bin/python -m benchmarks.bench_service [--preset oarm] [--repeats 3]``.
"""

from __future__ import annotations

import argparse
import asyncio
import json
import random
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path
from typing import Any

import numpy as np

from benchmarks.common import median_time_s, naive_read_series, print_table
from tests.helpers.tokens import make_token

N_CLIENTS = 50
REQUESTS_PER_CLIENT = 100
POLL_PERIOD_S = 0.1
"""Paced mode: each client polls at 20 Hz (a navigation UI refresh), 1000 requests/s offered in total."""
LOAD_TIME_LIMIT_S = 60.0
TOKEN = make_token()


# ---- load client (runs in the second process) -----------------------------------------------


async def _get(reader: asyncio.StreamReader, writer: asyncio.StreamWriter, request: bytes) -> int:
    """One keep-alive HTTP/1.1 GET on an open connection; returns the status code."""
    writer.write(request)
    await writer.drain()
    head = await reader.readuntil(b"\r\n\r\n")
    status = int(head.split(b" ", 2)[1])
    length = 0
    for line in head.split(b"\r\n"):
        if line.lower().startswith(b"content-length:"):
            length = int(line.split(b":", 1)[1])
    await reader.readexactly(length)
    return status


async def _load(
    url: str, token: str, n_clients: int, n_requests: int, limit_s: float, period_s: float = 0.0
) -> dict[str, Any]:
    """``n_clients`` keep-alive connections, each sending ``n_requests`` GETs, back to back
    (``period_s`` = 0: saturation) or one every ``period_s`` (a UI polling at 1/period_s Hz).

    A minimal asyncio HTTP/1.1 client (no httpx): with 50 concurrent requests, httpx's own
    overhead in the load process dominated the measurement (≈ 140 req/s against an empty app).
    """
    from urllib.parse import urlsplit

    u = urlsplit(url)
    host, port = u.hostname or "127.0.0.1", int(u.port or 80)
    request = (
        f"GET /registration/current HTTP/1.1\r\nHost: {host}:{port}\r\n"
        f"Authorization: Bearer {token}\r\nAccept: application/json\r\n\r\n"
    ).encode()
    latencies: list[float] = []
    errors = 0
    deadline = time.monotonic() + limit_s

    async def client() -> None:
        nonlocal errors
        reader, writer = await asyncio.open_connection(host, port)
        try:
            await _get(reader, writer, request)  # warm-up
            await started.wait()
            # polling clients start at random phases, as independent UIs would (phase-locked clients
            # would measure a 50-request burst every period instead)
            next_t = time.monotonic() + (phase.uniform(0.0, period_s) if period_s > 0 else 0.0)
            for _ in range(n_requests):
                if time.monotonic() > deadline:
                    return
                if period_s > 0:
                    next_t += period_s
                    await asyncio.sleep(max(0.0, next_t - time.monotonic()))
                t0 = time.perf_counter()
                status = await _get(reader, writer, request)
                latencies.append(time.perf_counter() - t0)
                if status != 200:
                    errors += 1
        finally:
            writer.close()

    started = asyncio.Event()
    phase = random.Random(0)
    tasks = [asyncio.create_task(client()) for _ in range(n_clients)]
    await asyncio.sleep(0.5)  # every connection open and warmed up
    t0 = time.perf_counter()
    started.set()
    await asyncio.gather(*tasks)
    wall = time.perf_counter() - t0
    lat = np.asarray(latencies)
    return {
        "n": len(latencies),
        "errors": errors,
        "wall_s": wall,
        "p50_ms": float(np.percentile(lat, 50) * 1e3),
        "p99_ms": float(np.percentile(lat, 99) * 1e3),
        "max_ms": float(lat.max() * 1e3),
        "rps": len(latencies) / wall,
    }


def _load_client_main(argv: list[str]) -> int:
    url, token, period_s = argv[0], argv[1], float(argv[2])
    res = asyncio.run(_load(url, token, N_CLIENTS, REQUESTS_PER_CLIENT, LOAD_TIME_LIMIT_S, period_s))
    sys.stdout.write(json.dumps(res) + "\n")
    return 0


# ---- benchmark ------------------------------------------------------------------------------


def _run_load_client(base_url: str, period_s: float) -> dict[str, Any]:
    proc = subprocess.run(
        [sys.executable, "-m", "benchmarks.bench_service", "--load-client", base_url, TOKEN, str(period_s)],
        capture_output=True,
        text=True,
        timeout=LOAD_TIME_LIMIT_S + 60,
        cwd=Path(__file__).resolve().parents[1],
    )
    if proc.returncode != 0:
        sys.stderr.write(proc.stderr)
        raise RuntimeError("load client failed")
    return json.loads(proc.stdout.strip().splitlines()[-1])  # type: ignore[no-any-return]


def _wait(pred: Any, timeout_s: float, what: str) -> Any:
    ev = threading.Event()
    end = time.monotonic() + timeout_s
    while time.monotonic() < end:
        v = pred()
        if v:
            return v
        ev.wait(0.05)
    raise TimeoutError(what)


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    if argv and argv[0] == "--load-client":
        return _load_client_main(argv[1:])
    ap = argparse.ArgumentParser()
    ap.add_argument("--preset", default="oarm")
    ap.add_argument("--repeats", type=int, default=3)
    args = ap.parse_args(argv)

    import httpx

    from mocks.oarm.dicom_export import write_dicom_series
    from mocks.oarm.simulator import AcquisitionSettings, demo_pose, simulate_scan
    from mocks.robot.robot import HOME_RAD, ScriptedRobot
    from mocks.robot.runner import run_mock_controller
    from service.cli.commands.serve import serve_in_thread
    from service.http.app import create_app
    from service.settings import load_settings

    with tempfile.TemporaryDirectory(prefix="bench-service-") as tmp:
        root = Path(tmp)
        watch, data, staging = root / "watch", root / "data", root / "staging"
        robot = ScriptedRobot(HOME_RAD)
        with run_mock_controller("simple-message", robot) as mock:
            settings = load_settings(
                None,
                {
                    "watch_dir": watch,
                    "data_dir": data,
                    "api_token": TOKEN,
                    "robot.link_url": mock.url,
                    "stillness.window_s": 1.0,
                    "watcher.quiet_period_s": 0.5,
                    "watcher.poll_interval_s": 0.2,
                },
            )
            app = create_app(settings)
            inputs = app.state.inputs  # the running parts (app.state.ctx) exist once it serves
            t0p = settings.robot.tool0_from_phantom.matrix()
            from registration.model.frames import invert

            image_from_robot = demo_pose() @ invert(inputs.robot_model.robot_from_tool0(HOME_RAD) @ t0p)
            image_from_phantom = image_from_robot @ inputs.robot_model.robot_from_tool0(HOME_RAD) @ t0p
            acq = AcquisitionSettings.preset(args.preset)
            sys.stderr.write(f"simulating a {acq.columns}x{acq.rows}x{acq.n_slices} scan ...\n")
            scan = simulate_scan(inputs.phantom, image_from_phantom, acq)
            exp = write_dicom_series(scan, staging, write_truth=False)
            floor_s, _ = median_time_s(lambda: naive_read_series(staging), repeats=args.repeats)
            with (
                serve_in_thread(app) as server,
                httpx.Client(
                    base_url=server.base_url, headers={"Authorization": f"Bearer {TOKEN}"}, timeout=300
                ) as c,
            ):
                _wait(lambda: c.get("/status").json()["link"]["history_s"] > 1.0, 30, "link history")
                staging.rename(watch / "scan")
                scan_row = _wait(
                    lambda: next(
                        (s for s in c.get("/scans").json() if s["series_uid"] == exp.series_uid), None
                    ),
                    120,
                    "scan recorded",
                )
                body = {"scan_id": scan_row["id"]}

                last_timings: dict[str, Any] = {}

                def post() -> None:
                    r = c.post("/register", json=body)
                    r.raise_for_status()
                    last_timings.clear()
                    last_timings.update(r.json().get("timings_s", {}))

                warm_s, _ = median_time_s(post, repeats=args.repeats, warmup=1)

                def post_cold() -> None:
                    app.state.ctx.orchestrator.volumes.discard(scan_row["series_uid"])
                    post()

                cold_s, _ = median_time_s(post_cold, repeats=args.repeats, warmup=0)
                cold_timings = dict(last_timings)
                last = c.post("/register", json=body).json()
                loads = {p: _run_load_client(server.base_url, p) for p in (0.0, POLL_PERIOD_S)}

    target = 1.3 * floor_s + 0.1
    print_table(
        f"POST /register, {acq.columns}×{acq.rows}×{acq.n_slices} scan (median of {args.repeats})",
        ["measurement", "time (s)", "vs target 1.3 × floor + 0.1 s"],
        [
            ["I/O floor: naive_read_series", floor_s, ""],
            ["POST /register (volume loaded by the watcher)", warm_s, f"{warm_s / target:.2f} × target"],
            [
                "POST /register cold (load + MAR + detect + register)",
                cold_s,
                f"{cold_s / target:.2f} × target",
            ],
        ],
    )
    t = last.get("timings_s", {})
    print_table(
        "Server-side timings of the last warm and the last cold POST /register (s)",
        ["step", "warm (s)", "cold (s)"],
        [[k, float(v), float(cold_timings.get(k, float("nan")))] for k, v in t.items()],
    )
    print_table(
        f"GET /registration/current, {N_CLIENTS} concurrent keep-alive clients in a second "
        f"process (loopback)",
        ["clients", "mode", "requests", "errors", "p50 (ms)", "p99 (ms)", "max (ms)", "req/s", "target p99"],
        [
            [N_CLIENTS, "back to back" if p == 0 else f"each polls at {1 / p:g} Hz", ld["n"], ld["errors"],
             ld["p50_ms"], ld["p99_ms"], ld["max_ms"], ld["rps"], "≤ 20 ms"]
            for p, ld in loads.items()
        ],
    )  # fmt: skip
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
