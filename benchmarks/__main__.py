"""Run every benchmark in turn: ``python -m benchmarks`` (``make bench``) from the repository root.

Each ``benchmarks/bench_<area>.py`` also runs alone: ``python -m benchmarks.bench_<area> --help``.
The full run takes about 15 minutes on 2 cores (the detection sweep and the end-to-end sweep
simulate 32 O-arm scans between them).
"""

from __future__ import annotations

import importlib
import sys

MODULES = (
    "benchmarks.bench_simulator",
    "benchmarks.bench_loader",
    "benchmarks.bench_detection",
    "benchmarks.bench_registration",
    "benchmarks.bench_end_to_end",
    "benchmarks.bench_robot_link",
    "benchmarks.bench_stillness",
    "benchmarks.bench_service",
    "benchmarks.bench_or_latency",
)


def main() -> int:
    for name in MODULES:
        sys.stdout.write(f"\n## {name}\n")
        sys.stdout.flush()
        rc = importlib.import_module(name).main([])
        if rc:
            return int(rc)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
