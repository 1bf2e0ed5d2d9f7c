"""Shared benchmark helpers: medians, the DICOM I/O floor, tables, peak memory."""

from __future__ import annotations

import statistics
import sys
import time
import tracemalloc
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import numpy as np


def median_time_s(fn: Callable[[], Any], repeats: int = 5, warmup: int = 1) -> tuple[float, list[float]]:
    """Median wall time of ``fn()`` over ``repeats`` runs (after ``warmup`` untimed runs)."""
    for _ in range(warmup):
        fn()
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return statistics.median(times), times


def naive_read_series(folder: Path) -> np.ndarray:
    """The I/O floor: ``dcmread`` every file in the folder, stack ``pixel_array`` (no sorting, no rescale)."""
    import pydicom

    files = sorted(p for p in Path(folder).iterdir() if p.is_file() and p.suffix == ".dcm")
    return np.stack([pydicom.dcmread(p).pixel_array for p in files])


def peak_python_memory_bytes(fn: Callable[[], Any]) -> int:
    """Peak memory traced by tracemalloc (numpy allocations included) while running ``fn``."""
    tracemalloc.start()
    try:
        fn()
        _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    return int(peak)


def print_table(title: str, header: Sequence[str], rows: Sequence[Sequence[Any]]) -> None:
    """Print a GitHub-markdown table (pasteable into the README)."""
    out = sys.stdout
    out.write(f"\n### {title}\n\n")
    out.write("| " + " | ".join(header) + " |\n")
    out.write("|" + "|".join("---" for _ in header) + "|\n")
    for r in rows:
        out.write("| " + " | ".join(_fmt(v) for v in r) + " |\n")
    out.flush()


def _fmt(v: Any) -> str:
    if isinstance(v, float):
        return f"{v:.4g}"
    return str(v)
