"""A still robot while 12 associations deliver scans: the largest joint receive gap and every scan's
stillness verdict, with the link read on a thread of the service (before, ``robot.link_process =
false``) and in a child process of its own (after, the default).  Issue 19 item 7.

Everything is a real process over loopback: the mock controller (``oarmreg mock robot``, 50 Hz
simple_message, robot still), the service (``oarmreg serve`` with its DICOM C-STORE SCP) and, in
this process, ``--associations`` pynetdicom SCUs that each send one synthetic 512 × 512 CT series of
``--slices`` slices at the same time (the service decodes them as they arrive).  After the last
release the script reads ``GET /status`` (``link.max_receive_gap_s``: the largest time between two
received frames over the last 60 s) and ``GET /scans`` (each scan's verdict).

The bench's config raises ``[dicom] maximum_associations`` to ``--associations`` + 4 (the service's
default is pynetdicom's 10, which refused the 11th and 12th association: only 7–10 of 12 series were
delivered); the load under test is 12 series decoded at once, not the association limit.  Each mode
runs ``--runs`` times (alternating); the summary prints the median largest gap and the verdicts summed.

Run: ``.venv/bin/python -m benchmarks.bench_stillness_load [--associations 12] [--slices 48] [--runs 3]``
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import socket
import statistics
import subprocess
import sys
import tempfile
import threading
import time
from collections import Counter
from pathlib import Path
from typing import Any

import httpx

from benchmarks.bench_dicom_scp import write_series
from benchmarks.common import print_table
from tests.helpers.tokens import make_token

TOKEN = make_token()
WINDOW_S = 2.0
DEADLINE_S = 300.0


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


MOCK_NICE = -10
"""Scheduling boost of the mock controller where allowed (root): it stands for the robot's own controller
on its own hardware.  On a saturated 2-core machine the mock otherwise falls more than a frame period
behind and re-anchors (mocks/robot/simple_message_server.py): frames never sent, which the service
rightly judges ``incomplete``, and the bench would measure the mock, not the service."""


def _boost() -> None:
    with contextlib.suppress(OSError):  # not root: the mock runs at normal priority (the title says so)
        os.nice(MOCK_NICE)


def start_mock() -> tuple[subprocess.Popen[str], str]:
    proc = subprocess.Popen(
        [sys.executable, "-m", "service.cli", "mock", "robot", "--link", "simple-message://127.0.0.1:0"],
        stdout=subprocess.PIPE,
        text=True,
        preexec_fn=_boost,
    )
    assert proc.stdout is not None
    return proc, proc.stdout.readline().strip()


ASSOCIATION_HEADROOM = 4
"""``maximum_associations`` = associations + this, so no association of the load is refused."""


def write_config(
    path: Path,
    root: Path,
    link_url: str,
    dicom_port: int,
    http_port: int,
    in_process: bool,
    maximum_associations: int,
) -> None:
    path.write_text(
        f"""watch_dir = "{root / "watch"}"
data_dir = "{root / "data"}"
api_token = "{TOKEN}"
port = {http_port}

[robot]
link_url = "{link_url}"
link_process = {"false" if in_process else "true"}

[stillness]
window_s = {WINDOW_S}

[dicom]
enabled = true
port = {dicom_port}
maximum_associations = {maximum_associations}
""",
        encoding="utf-8",
    )


def poll(pred: Any, what: str, timeout_s: float = DEADLINE_S) -> Any:
    deadline = time.monotonic() + timeout_s
    tick = threading.Event()
    while time.monotonic() < deadline:
        v = pred()
        if v:
            return v
        tick.wait(0.1)
    raise TimeoutError(what)


def send_series(folder: Path, port: int, errors: list[str], sent: list[Path]) -> None:
    from pydicom.uid import CTImageStorage, ExplicitVRLittleEndian
    from pynetdicom import AE

    from dicomnet.scu import associate

    ae = AE(ae_title="BENCH")
    ae.add_requested_context(CTImageStorage, [ExplicitVRLittleEndian])
    assoc = associate(ae, "127.0.0.1", port, ae_title="OARMREG")
    if not assoc.is_established:
        errors.append(f"association for {folder.name} not established")
        return
    ok = True
    try:
        for p in sorted(folder.glob("*.dcm")):
            st = assoc.send_c_store(p)
            if getattr(st, "Status", None) != 0:
                errors.append(f"{folder.name}/{p.name}: status {getattr(st, 'Status', None)}")
                ok = False
    finally:
        assoc.release()
    if ok:
        sent.append(folder)


def one_run(src: list[Path], in_process: bool, tmp: Path) -> dict[str, Any]:
    root = Path(tempfile.mkdtemp(dir=tmp))
    mock, url = start_mock()
    dicom_port, http_port = free_port(), free_port()
    cfg = root / "oarmreg.toml"
    write_config(cfg, root, url, dicom_port, http_port, in_process, len(src) + ASSOCIATION_HEADROOM)
    log = (root / "serve.log").open("wb")
    serve = subprocess.Popen(
        [sys.executable, "-m", "service.cli", "serve", "--config", str(cfg)],
        stdout=log, stderr=subprocess.STDOUT, env={**os.environ, "OMP_NUM_THREADS": "1"},
    )  # fmt: skip
    base = f"http://127.0.0.1:{http_port}"
    client = httpx.Client(base_url=base, headers={"Authorization": f"Bearer {TOKEN}"}, timeout=60.0)
    try:

        def linked() -> bool:
            try:
                st = client.get("/status").json()["link"]
            except httpx.HTTPError:
                return False
            return bool(st["state"] == "connected" and st["history_s"] > WINDOW_S + 1.0)

        poll(linked, "the service to be up with joint history")
        errors: list[str] = []
        sent: list[Path] = []
        threads = [threading.Thread(target=send_series, args=(f, dicom_port, errors, sent)) for f in src]
        t0 = time.monotonic()
        for t in threads:
            t.start()
        for t in threads:
            t.join()
        send_s = time.monotonic() - t0

        def all_recorded() -> list[dict[str, Any]] | None:
            """Every delivered series judged (not ``receiving``: its verdict and joints are written then)."""
            scans = [s for s in client.get("/scans").json() if s["status"] != "receiving"]
            return scans if len(scans) >= len(sent) else None

        scans = poll(all_recorded, "every series to be recorded")
        link = client.get("/status").json()["link"]
        verdicts = Counter(s["joints"]["verdict"] if s.get("joints") else "none" for s in scans)
        reasons = sorted({s["joints"]["stillness_reason"] for s in scans if s.get("joints")} - {""})
        return {
            "mode": "thread (before)" if in_process else "child process (after)",
            "send_s": send_s,
            "max_receive_gap_s": link["max_receive_gap_s"],
            "verdicts": dict(verdicts),
            "delivered": len(sent),
            "errors": errors[:5],
            "reasons": reasons[:3],
        }
    finally:
        client.close()
        serve.terminate()
        serve.wait(30)
        log.close()
        mock.terminate()
        mock.wait(30)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--associations", type=int, default=12)
    ap.add_argument("--slices", type=int, default=48, help="slices per series (512 x 512 int16)")
    ap.add_argument("--runs", type=int, default=3, help="runs per mode (medians over them)")
    ap.add_argument("--json", action="store_true")
    args = ap.parse_args(argv)
    with tempfile.TemporaryDirectory() as tmp_name:
        tmp = Path(tmp_name)
        src = []
        for i in range(args.associations):
            f = tmp / f"series{i:02d}"
            f.mkdir()
            write_series(f, args.slices)
            src.append(f)
        results = [one_run(src, mode, tmp) for _ in range(args.runs) for mode in (True, False)]
    if args.json:
        sys.stdout.write(json.dumps(results, indent=2) + "\n")
    print_table(
        f"Still robot, {args.associations} associations x {args.slices} slices (512 x 512) at once "
        f"(mock controller nice {MOCK_NICE if os.geteuid() == 0 else 0})",
        ["link reader", "series delivered", "send s", "largest receive gap s", "verdicts", "first reason"],
        [
            (r["mode"], r["delivered"], r["send_s"], r["max_receive_gap_s"], json.dumps(r["verdicts"]),
             (r["reasons"] or [""])[0][:120])
            for r in results
        ],
    )  # fmt: skip
    summary = []
    for mode in ("thread (before)", "child process (after)"):
        rs = [r for r in results if r["mode"] == mode]
        verdicts: Counter[str] = Counter()
        for r in rs:
            verdicts.update(r["verdicts"])
        summary.append((
            mode, len(rs), statistics.median(r["delivered"] for r in rs),
            statistics.median(r["send_s"] for r in rs), statistics.median(r["max_receive_gap_s"] for r in rs),
            max(r["max_receive_gap_s"] for r in rs), json.dumps(dict(verdicts)),
        ))  # fmt: skip
    print_table(
        f"Medians over {args.runs} run(s) per mode",
        ["link reader", "runs", "series delivered", "send s", "largest receive gap s (median)",
         "largest receive gap s (max)", "verdicts (all runs)"],
        summary,
    )  # fmt: skip
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
