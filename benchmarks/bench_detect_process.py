"""Whole-process cost of ``oarmreg detect`` vs a minimal pydicom reader (issue #9 item 4: ≤ 1.5×).

Run: ``.venv/bin/python -m benchmarks.bench_detect_process [--repeats 5] [--series DIR]``

Simulates one 512 × 512 × 192 O-arm series once (``python -m service.cli simulate --preset oarm``,
the full-size preset) unless ``--series`` names an existing folder, then runs, alternately and
each as a fresh subprocess (interpreter start and imports count):

* ``python -m service.cli detect DIR`` (load, check, MAR, detection, table), and
* the floor: a minimal script that ``dcmread``s every file of the folder and rescales
  ``pixel_array`` into one float32 numpy volume (:data:`FLOOR_SCRIPT`),

and prints the median wall time of each and the ratio detect / floor.  Both run in the same
session on the same page-cache-warm files, so the ratio is comparable across machines.
"""

from __future__ import annotations

import argparse
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from benchmarks.common import print_table

RATIO_LIMIT = 1.5
"""The ceiling the issue sets for detect / floor."""

FLOOR_SCRIPT = """
import sys
from pathlib import Path

import numpy as np
import pydicom

files = sorted(p for p in Path(sys.argv[1]).iterdir() if p.suffix == ".dcm")
first = pydicom.dcmread(files[0], stop_before_pixels=True)
vol = np.empty((len(files), first.Rows, first.Columns), dtype=np.float32)
for k, p in enumerate(files):
    ds = pydicom.dcmread(p)
    vol[k] = ds.pixel_array
    vol[k] *= float(ds.get("RescaleSlope", 1.0))
    vol[k] += float(ds.get("RescaleIntercept", 0.0))
print(vol.shape, float(vol.mean()))
"""
"""The floor: read the same series with pydicom into a float32 HU volume, nothing else."""


def _repo_root() -> Path:
    return Path(__file__).resolve().parent.parent


def simulate(out: Path) -> None:
    """Write the full-size ``oarm`` preset series into ``out`` (once; takes a minute or two)."""
    subprocess.run(
        [sys.executable, "-m", "service.cli", "simulate", "--out", str(out), "--preset", "oarm"],
        cwd=_repo_root(),
        check=True,
        stdout=subprocess.DEVNULL,
    )


def wall_s(cmd: list[str]) -> float:
    """Wall time of one subprocess run (it must succeed)."""
    t0 = time.perf_counter()
    subprocess.run(cmd, cwd=_repo_root(), check=True, stdout=subprocess.DEVNULL, env=dict(os.environ))
    return time.perf_counter() - t0


def measure(series: Path, repeats: int) -> tuple[list[float], list[float]]:
    """Alternate detect and floor runs (after one untimed warm-up of each); return both time lists."""
    detect = [sys.executable, "-m", "service.cli", "detect", str(series)]
    floor = [sys.executable, "-c", FLOOR_SCRIPT, str(series)]
    wall_s(detect)
    wall_s(floor)
    detect_s, floor_s = [], []
    for _ in range(repeats):
        detect_s.append(wall_s(detect))
        floor_s.append(wall_s(floor))
    return detect_s, floor_s


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--series", type=Path, default=None, help="an existing series folder to reuse")
    args = parser.parse_args(argv)
    with tempfile.TemporaryDirectory(prefix="bench_detect_process_") as tmp:
        series = args.series
        if series is None:
            series = Path(tmp) / "oarm"
            simulate(series)
        n_files = sum(1 for p in series.iterdir() if p.suffix == ".dcm")
        detect_s, floor_s = measure(series, args.repeats)
    d, f = statistics.median(detect_s), statistics.median(floor_s)
    print_table(
        f"Whole process, median of {args.repeats} fresh subprocesses ({n_files} files, page cache warm)",
        ["command", "median (s)", "min (s)", "max (s)"],
        [
            ["python -m service.cli detect DIR", d, min(detect_s), max(detect_s)],
            ["minimal pydicom → float32 volume (floor)", f, min(floor_s), max(floor_s)],
        ],
    )
    verdict = "ok" if d / f <= RATIO_LIMIT else "OVER"
    sys.stdout.write(f"\ndetect / floor = {d / f:.3f} (limit {RATIO_LIMIT}): {verdict}\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
