"""OpenIGTLink CRC-64 throughput: the old pure-Python table loop, the new crcmod C extension, and
zlib's CRC-32 (C, the same byte-at-a-time table method) as the floor, in the same run (issue #32).

Each row: median over ``--repeats`` runs of one CRC of a random body of that size, MB/s, and the
ratio to the floor's time.  Times are the thread's CPU time (``time.thread_time``), not wall time:
on a shared machine a long run is sliced by the scheduler, and the CPU time is what the event loop
spends; on an idle machine the two agree.  The last column is how long one CRC of that size
holds the event loop with the new code: the listener's default limits are 4 KiB (STATUS),
1 KiB (queries) and 64 KiB (anything else), at most 1 MiB by setting (``service/navigation/igtl/server.py``).
The pure-Python CRC is measured up to 1 MiB (64 MiB would take 10 s or more a run); its 64 MiB
figure is extrapolated from the 1 MiB one.

Run: ``PYTHONPATH=. .venv/bin/python -m benchmarks.bench_igtl_crc``
"""

from __future__ import annotations

import argparse
import os
import statistics
import time
import zlib
from collections.abc import Callable
from typing import Any

from benchmarks.common import print_table
from service.navigation.igtl import wire

SIZES = (1024, 64 * 1024, 1024 * 1024, 64 * 1024 * 1024)
PY_MAX = 1024 * 1024


def median_time_s(fn: Callable[[], Any], repeats: int) -> tuple[float, list[float]]:
    """Median CPU time of ``fn()`` in this thread over ``repeats`` runs (after one untimed run)."""
    fn()
    times = []
    for _ in range(repeats):
        t0 = time.thread_time()
        fn()
        times.append(time.thread_time() - t0)
    return statistics.median(times), times


def _row(size: int, repeats: int, old_per_byte_s: list[float]) -> list[object]:
    """One table row; ``old_per_byte_s`` carries the pure-Python cost per byte to larger sizes."""
    data = os.urandom(size)
    floor_s, _ = median_time_s(lambda: zlib.crc32(data), repeats)
    new_s, _ = median_time_s(lambda: wire.crc64(data), repeats)
    if size <= PY_MAX:
        old_s, _ = median_time_s(lambda: wire.crc64_py(data), max(1, repeats // 2))
        old_per_byte_s[:] = [old_s / size]
        old = f"{old_s * 1e3:.3g} ms ({size / old_s / 1e6:.3g} MB/s, x{old_s / floor_s:.0f})"
    else:
        est_s = size * old_per_byte_s[0]
        old = f"~{est_s:.1f} s (extrapolated)"
    mb_s = size / new_s / 1e6
    return [f"{size / 1024:g} KiB", old, f"{new_s * 1e3:.3g} ms ({mb_s:.0f} MB/s, x{new_s / floor_s:.1f})",
            f"{floor_s * 1e3:.3g} ms", f"{new_s * 1e3:.3g} ms"]  # fmt: skip


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0] if __doc__ else "")
    ap.add_argument("--repeats", type=int, default=7)
    args = ap.parse_args(argv)
    if not wire.native_crc():
        print("crcmod runs without its C extension: the 'new' column would be pure Python too")
        return 1
    check = os.urandom(65537)
    assert wire.crc64(check) == wire.crc64_py(check), "crcmod and the reference CRC disagree"
    per_byte: list[float] = [0.0]
    rows = [_row(size, args.repeats, per_byte) for size in SIZES]  # ascending: 1 MiB before 64 MiB
    print_table(
        "CRC-64 of one body (median; x = time / zlib.crc32 floor)",
        ["body", "old: pure Python", "new: crcmod C", "floor: zlib.crc32", "event loop held (new)"],
        rows,
    )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
