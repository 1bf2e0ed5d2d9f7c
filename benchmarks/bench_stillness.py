"""Still scans judged under a CPU load that fills both cores, at 50, 250 and 1000 Hz (issue 40 item 3).

Three mock controllers (simple_message, the VAL3 driver's cadence: streaming 1 s after a client
connects, each message in three writes, STATUS every fifth frame), each in a process of its own
(``nice -10`` where allowed, ``--mock-nice``: it stands for the controller's own hardware), serve
one still robot.  Each is read as the service reads it (:class:`drivers.link_process.ProcessLink`,
a child process at nice 0) while ``stress-ng --cpu 2`` (or two Python busy loops) at nice 0 fills
both cores.  After ``--record-s`` of history, ``--judgements`` windows of the default
``stillness.window_s`` (60 s) whose ends are spread over the last ``record − window`` seconds are
judged by the service's own :meth:`service.intake.capture.Capture.snapshot` with default
settings.  The windows overlap
(they come from one recording per rate): they are not independent scans.

The same samples are also judged by the rule before issue 40 (the frame count over the window
against the median receive interval, ``missing × period > max_gap_s``), for comparison.  A second
table gives the history's memory at 1 kHz for the full ``history_s`` and the cost of one append,
against ``deque.append`` (the floor) measured in the same run.

Run: ``.venv/bin/python -m benchmarks.bench_stillness [--record-s 115] [--judgements 20] [--mock-nice 0]``
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import os
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
import tracemalloc
from collections import deque
from collections.abc import Iterator
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import numpy as np

from benchmarks.common import print_table

RATES_HZ = (50.0, 250.0, 1000.0)
MOCK_NICE = -10
"""The mock controllers' scheduling boost where allowed (root): a controller runs on its own
hardware; unboosted on a saturated 2-core machine the mock itself falls behind (see
benchmarks/bench_stillness_load.py), and the bench would measure the mock, not the judge."""

_MOCK = """
import sys
from mocks.robot.robot import ScriptedRobot
from mocks.robot.runner import run_mock_controller
robot = ScriptedRobot((0.3, -0.5, 1.6, 0.2, 0.8, -0.1))
with run_mock_controller("simple-message", robot, period_s=1.0 / {rate}, start_delay_s=1.0) as mock:
    print(mock.url, flush=True)
    sys.stdin.read()
"""


@contextlib.contextmanager
def mock_controller(rate_hz: float, nice: int) -> Iterator[str]:
    """A mock controller at ``rate_hz`` in a process of its own at ``nice`` (where allowed); yields its
    URL (it ends on stdin EOF)."""

    def boost() -> None:
        with contextlib.suppress(OSError):
            os.nice(nice)

    proc = subprocess.Popen(
        [sys.executable, "-c", _MOCK.format(rate=rate_hz)],
        stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True, preexec_fn=boost,
    )  # fmt: skip
    try:
        assert proc.stdout is not None
        yield proc.stdout.readline().strip()
    finally:
        assert proc.stdin is not None
        proc.stdin.close()
        try:
            proc.wait(10)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait(10)


@contextlib.contextmanager
def cpu_load(bound_s: float) -> Iterator[str]:
    """Both cores busy at nice 0 for at most ``bound_s``; yields what makes the load."""
    if shutil.which("stress-ng"):
        cmds = [["stress-ng", "--cpu", "2", "--timeout", f"{int(bound_s)}s", "--quiet"]]
        what = "stress-ng --cpu 2"
    else:
        code = f"import time\nend = time.monotonic() + {bound_s}\nwhile time.monotonic() < end:\n    pass\n"
        cmds = [[sys.executable, "-c", code]] * 2
        what = "2 Python busy loops"
    procs = [subprocess.Popen(c) for c in cmds]
    try:
        yield what
    finally:
        for p in procs:
            p.terminate()
        for p in procs:
            p.wait(10)


def median_rule_refused(
    t: np.ndarray, session_t: np.ndarray, start: float, end: float, max_gap_s: float
) -> bool:
    """The rule before issue 40: frames in the window against the median receive interval."""
    period = float(np.median(np.diff(session_t)))
    n = int(np.count_nonzero((t >= start) & (t <= end)))
    missing = (end - start) / period - n
    return bool(missing * period > max_gap_s)


PAUSE_S = 0.5
"""A controller pause cut into each judged window of the recording (nothing sent, nothing late)."""


def pause_caught(t_all: np.ndarray, end: float, st: Any) -> tuple[bool, bool]:
    """The same window with :data:`PAUSE_S` of frames removed from its middle: refused by the judge
    (as Capture calls it), and by the median rule?"""
    from registration.model.stillness import assess_stillness, stream_period_s

    mid = end - st.window_s / 2
    t = t_all[(t_all < mid) | (t_all >= mid + PAUSE_S)]
    session = t[(t >= end - 60.0) & (t <= end)]
    q = np.zeros((t.size, 6))
    res = assess_stillness(
        t, q, window_end_t_s=end, window_s=st.window_s, max_deviation_rad=st.max_deviation_rad,
        max_gap_s=st.max_gap_s, period_s=stream_period_s(session),
    )  # fmt: skip
    return res.verdict == "incomplete", median_rule_refused(t, session, end - st.window_s, end, st.max_gap_s)


def judge_rate(cap: Any, link: Any, n: int, settings: Any) -> dict[str, Any]:
    """``n`` still windows of the default length spread over the recorded history."""
    st = settings.stillness
    hist = link.history(0.0)
    t_all = np.array([s.t_s for s in hist])
    first, last = float(t_all[0]), float(t_all[-1])
    ends = np.linspace(first + st.window_s + 1.0, last - 1.0, n)
    new_refused: list[str] = []
    old_refused = paused_caught = paused_caught_old = 0
    for end in ends:
        caught_new, caught_old = pause_caught(t_all, float(end), st)
        paused_caught += caught_new
        paused_caught_old += caught_old
        snap = cap.snapshot(float(end), float(end))
        if snap.verdict != "still":
            new_refused.append(snap.stillness_reason)
        session = t_all[(t_all >= end - 60.0) & (t_all <= end)]
        old_refused += median_rule_refused(t_all, session, end - st.window_s, float(end), st.max_gap_s)
    gaps = np.diff(t_all)
    return {
        "frames": int(t_all.size),
        "span_s": last - first,
        "median_interval_ms": float(np.median(gaps)) * 1e3,
        "long_run_period_ms": (last - first) / (t_all.size - 1) * 1e3,
        "zero_intervals": float(np.mean(gaps < 1e-6)),
        "max_gap_s": float(gaps.max()),
        "judged": len(ends),
        "refused": len(new_refused),
        "refused_median_rule": old_refused,
        "pause_caught": paused_caught,
        "pause_caught_median_rule": paused_caught_old,
        "first_reason": (new_refused or [""])[0],
    }


def history_cost(rate_hz: float = 1000.0) -> tuple[float, float, float]:
    """(MB held by a full history at ``rate_hz``, median µs per append, the deque.append floor in µs)."""
    from drivers.base import HISTORY_S, JointRing, JointState

    now = datetime.now(UTC)
    n = int(HISTORY_S * rate_hz)
    tracemalloc.start()
    before = tracemalloc.get_traced_memory()[0]
    ring: JointRing[JointState] = JointRing(HISTORY_S)
    for k in range(n):  # each state made as the link makes one per frame (its joints tuple, its stamps)
        q = tuple(0.1 * j + k * 1e-9 for j in range(6))
        ring.append(
            JointState(q, k / rate_hz, datetime.fromtimestamp(k / rate_hz, UTC), "simple-message://x", 1)
        )
    held = tracemalloc.get_traced_memory()[0] - before
    tracemalloc.stop()
    # per-frame cost: a state built as the link builds it, appended to a full ring, vs deque.append
    per, floor = [], []
    extra = [JointState((0.1,) * 6, HISTORY_S + k / rate_hz, now, "x", 1) for k in range(20000)]
    plain: deque[JointState] = deque(maxlen=n)
    for _ in range(5):
        t0 = time.perf_counter()
        for s in extra:
            ring.append(s)
        per.append((time.perf_counter() - t0) / len(extra) * 1e6)
        t0 = time.perf_counter()
        for s in extra:
            plain.append(s)
        floor.append((time.perf_counter() - t0) / len(extra) * 1e6)
    return held / 1e6, statistics.median(per), statistics.median(floor)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--record-s", type=float, default=115.0, help="history recorded per rate (s, ≤ 120)")
    ap.add_argument("--judgements", type=int, default=20, help="still windows judged per rate")
    ap.add_argument(
        "--mock-nice", type=int, default=MOCK_NICE,
        help="the mock controllers' nice value (0: they compete with the load like the link does)",
    )  # fmt: skip
    args = ap.parse_args(argv)
    from drivers.link_process import ProcessLink
    from service.intake.capture import Capture
    from service.settings import load_settings

    rows: list[tuple[Any, ...]] = []
    with tempfile.TemporaryDirectory() as tmp, contextlib.ExitStack() as stack:
        settings = load_settings(None, {"watch_dir": Path(tmp) / "w", "data_dir": Path(tmp) / "d"})
        what = stack.enter_context(cpu_load(args.record_s + 60.0))
        urls = {r: stack.enter_context(mock_controller(r, args.mock_nice)) for r in RATES_HZ}
        links = {r: ProcessLink(u) for r, u in urls.items()}
        for link in links.values():
            link.start()
        try:
            deadline = time.monotonic() + args.record_s + 30.0
            while time.monotonic() < deadline:
                spans = [
                    (h[-1].t_s - h[0].t_s) if len(h := lk.history(0.0)) > 1 else 0.0 for lk in links.values()
                ]
                if min(spans) >= args.record_s:
                    break
                time.sleep(1.0)  # a bench, not a test: how long to record
            results = {
                r: judge_rate(Capture(link, settings, lambda e: None), link, args.judgements, settings)
                for r, link in links.items()
            }
        finally:
            for link in links.values():
                asyncio.run(link.close())
    for r, res in results.items():
        rows.append((
            f"{r:g} Hz", res["frames"], res["span_s"], res["median_interval_ms"], res["long_run_period_ms"],
            res["zero_intervals"], res["max_gap_s"], res["judged"], res["refused"],
            res["refused_median_rule"], f"{res['pause_caught']} / {res['pause_caught_median_rule']}",
            res["first_reason"][:100],
        ))  # fmt: skip
    boosted = os.geteuid() == 0
    print_table(
        f"Still robot, default settings (window {settings.stillness.window_s:g} s, max_gap_s "
        f"{settings.stillness.max_gap_s:g} s), load: {what} at nice 0, mock controllers nice "
        f"{args.mock_nice if boosted else 0}",
        ["rate", "frames", "recorded s", "median interval ms", "long-run period ms", "share of 0-s intervals",
         "largest receive gap s", "windows judged", "refused", "refused by the median rule (before)",
         f"{PAUSE_S:g} s pause cut in: refused by the judge / by the median rule", "first refusal"],
        rows,
    )  # fmt: skip
    mb, per_us, floor_us = history_cost()
    print_table(
        "Joint history at 1 kHz for the full history_s (120 s), no load",
        ["MB held (120 000 states)", "µs per append (median of 5)", "deque.append floor µs", "ratio"],
        [(mb, per_us, floor_us, per_us / floor_us)],
    )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
