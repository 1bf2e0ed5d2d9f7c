"""Whole-process cost of ``oarmreg detect`` vs a minimal pydicom reader (issue #9 item 4: ≤ 1.5×).

Run: ``.venv/bin/python -m benchmarks.bench_detect_process [--repeats 5] [--series DIR]``

Simulates one 512 × 512 × 192 O-arm series once (``python -m service.cli simulate --preset oarm``,
the full-size preset) unless ``--series`` names an existing folder, then runs, alternately and
each as a fresh subprocess (interpreter start and imports count):

* ``python -m service.cli detect DIR`` (load, check, MAR, detection, table), and
* the floor: a minimal script that ``dcmread``s every file of the folder and rescales
  ``pixel_array`` into one float32 numpy volume (:data:`FLOOR_SCRIPT`),

and prints the median wall and CPU (user + sys) time of each and the ratios detect / floor.  Both
run in the same session on the same page-cache-warm files, so the ratio is comparable across machines.

The children run with bytecode caching on (:func:`child_env`), as an installed package runs: pip
compiles the wheel's modules at install, and the floor's pydicom and numpy are compiled in the
venv.  A shell that sets ``PYTHONDONTWRITEBYTECODE`` (this development machine does) would
otherwise make every ``detect`` run compile the project's ~60 modules from source (≈ 0.08 s of
``compile``, measured with cProfile) while the floor compiles nothing.
"""

from __future__ import annotations

import argparse
import os
import resource
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


def child_env() -> dict[str, str]:
    """The environment of the timed children: this one with bytecode caching allowed."""
    env = dict(os.environ)
    env.pop("PYTHONDONTWRITEBYTECODE", None)
    return env


def run_once(cmd: list[str], cwd: Path) -> tuple[float, float]:
    """Wall time and CPU time (user + sys of the child) of one subprocess run in ``cwd`` (it must succeed).

    CPU time is less disturbed than wall time by other jobs on a shared machine, but it sums all
    threads: OpenCV in ``detect`` uses every core, so its CPU time can exceed its wall time.
    """
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    t0 = time.perf_counter()
    subprocess.run(cmd, cwd=cwd, check=True, stdout=subprocess.DEVNULL, env=child_env())
    wall = time.perf_counter() - t0
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    return wall, (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)


def measure(series: Path, repeats: int, baseline: Path | None) -> dict[str, list[tuple[float, float]]]:
    """Interleave the runs (after one untimed warm-up of each); (wall, CPU) times per command label.

    ``baseline`` is another checkout of the project (e.g. the main branch): its ``detect`` runs
    too, from that folder, so "before" and "after" are measured under the same load.
    """
    detect = [sys.executable, "-m", "service.cli", "detect", str(series)]
    runs: dict[str, tuple[list[str], Path]] = {
        "python -m service.cli detect DIR": (detect, _repo_root()),
        "minimal pydicom → float32 volume (floor)": (
            [sys.executable, "-c", FLOOR_SCRIPT, str(series)],
            _repo_root(),
        ),
    }
    if baseline is not None:
        runs[f"detect DIR, code in {baseline}"] = (detect, baseline)
    for cmd, cwd in runs.values():
        run_once(cmd, cwd)
    times: dict[str, list[tuple[float, float]]] = {label: [] for label in runs}
    for _ in range(repeats):
        for label, (cmd, cwd) in runs.items():
            times[label].append(run_once(cmd, cwd))
    return times


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--series", type=Path, default=None, help="an existing series folder to reuse")
    parser.add_argument(
        "--baseline", type=Path, default=None, help="another checkout (e.g. /work/main) to time as 'before'"
    )
    args = parser.parse_args(argv)
    with tempfile.TemporaryDirectory(prefix="bench_detect_process_") as tmp:
        series = args.series
        if series is None:
            series = Path(tmp) / "oarm"
            simulate(series)
        n_files = sum(1 for p in series.iterdir() if p.suffix == ".dcm")
        times = measure(series, args.repeats, args.baseline)
    wall = {label: statistics.median(w for w, _ in ts) for label, ts in times.items()}
    cpu = {label: statistics.median(c for _, c in ts) for label, ts in times.items()}
    detect_label, floor_label = list(times)[:2]
    print_table(
        f"Whole process, median of {args.repeats} fresh subprocesses ({n_files} files, page cache warm)",
        ["command", "wall (s)", "wall / floor", "CPU user+sys (s)", "CPU / floor"],
        [
            [label, wall[label], wall[label] / wall[floor_label], cpu[label], cpu[label] / cpu[floor_label]]
            for label in times
        ],
    )
    ratio = wall[detect_label] / wall[floor_label]
    cpu_ratio = cpu[detect_label] / cpu[floor_label]
    verdict = "ok" if ratio <= RATIO_LIMIT else "OVER"
    sys.stdout.write(
        f"\ndetect / floor = {ratio:.3f} of the median wall times (limit {RATIO_LIMIT}): {verdict}; "
        f"{cpu_ratio:.3f} of the median CPU times (all threads; less disturbed by other jobs)\n"
    )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
