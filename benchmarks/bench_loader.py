"""Series loading speed and memory vs the naive ``dcmread`` loop (issue #3, "Reading itself should be at
or under the floor of a naive dcmread loop").

Run: ``.venv/bin/python -m benchmarks.bench_loader [--slices 192] [--repeats 7]``

Writes a 512 × 512 × N int16 CT series (noise plus a few bright balls) with the
O-arm simulator's exporter (``mocks.oarm.dicom_export``: realistic header,
InstanceNumber against z) into a temporary folder, twice: signed with
intercept 0 (the direct ``readinto`` path) and unsigned with intercept −1024
(the rescale path).  Then, in one process, it times the median of ``repeats`` runs of

* the I/O floor ``benchmarks.common.naive_read_series`` (``np.stack`` of
  ``dcmread(p).pixel_array``, no sorting, no rescale),
* :func:`registration.dicom.load_series` (sorting, checks, rescale),
* :func:`registration.dicom.list_series` (header-only, the watcher's call),

and the peak traced memory (tracemalloc) of one ``load_series`` against the
volume's int16 size.  The files sit in the page cache after the warm-up run,
so this measures parsing and copying, not the disk.

After the table it prints :data:`BEFORE`, the same table recorded for the reader this package
replaced (``registration/dicom_series.py``: PixelData offsets from pydicom's ``RawDataElement.value_tell``,
``readinto`` the volume), so the ratios to the floor measured in each run can be compared.
"""

from __future__ import annotations

import argparse
import functools
import tempfile
from pathlib import Path
from typing import Final

import numpy as np

from benchmarks.common import median_time_s, naive_read_series, peak_python_memory_bytes, print_table
from registration.dicom import list_series, load_series

COLUMNS: Final = [
    "series",
    "naive dcmread floor (s)",
    "load_series (s)",
    "load / floor",
    "list_series (s)",
    "load peak (MiB)",
    "peak / int16 volume",
]

BEFORE: Final = [
    ["512x512x192 int16, intercept 0", 0.5904, 0.3419, 0.579, 0.2155, 96.38, 1.004],
    ["512x512x192 uint16, intercept -1024", 0.3323, 0.2297, 0.6913, 0.166, 96.94, 1.01],
]
"""``python -m benchmarks.bench_loader --repeats 5`` on the old reader (registration/dicom_series.py at
commit 9daed23), on the 2-core VM shared with other jobs: compare the load / floor ratios, not the seconds."""


def synthetic_hu(n_slices: int, rows: int = 512, columns: int = 512, seed: int = 0) -> np.ndarray:
    """(n, rows, columns) int16 HU: water-ish noise (SD 40 HU) plus eight 3071-HU balls of radius 3 px."""
    rng = np.random.default_rng(seed)
    hu = rng.normal(0.0, 40.0, size=(n_slices, rows, columns)).astype(np.int16)
    k, j, i = np.ogrid[:n_slices, :rows, :columns]
    for _ in range(8):
        ck, cj, ci = rng.uniform(5, n_slices - 5), rng.uniform(20, rows - 20), rng.uniform(20, columns - 20)
        ball = (k - ck) ** 2 + (j - cj) ** 2 + (i - ci) ** 2 <= 9.0
        hu[ball] = 3071
    return hu


def write_case(folder: Path, hu: np.ndarray, *, unsigned: bool) -> None:
    """Write ``hu`` with the O-arm simulator's exporter (realistic header), InstanceNumber against z."""
    from mocks.oarm.dicom_export import write_dicom_series
    from mocks.oarm.simulator import AcquisitionSettings, SimulatedScan

    n, rows, columns = hu.shape
    settings = AcquisitionSettings.preset("oarm", n_slices=n, rows=rows, columns=columns)
    scan = SimulatedScan(
        hu=hu,
        image_from_voxel=settings.image_from_voxel(),
        image_from_phantom=np.eye(4),
        spheres_image_mm=np.zeros((0, 3)),
        sphere_indices=np.zeros(0, dtype=np.int64),
        settings=settings,
    )
    write_dicom_series(scan, folder, reverse_order=True, unsigned=unsigned, write_truth=False)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--slices", type=int, default=192)
    parser.add_argument("--repeats", type=int, default=7)
    args = parser.parse_args(argv)

    hu = synthetic_hu(args.slices)
    volume_bytes = hu.nbytes
    rows = []
    with tempfile.TemporaryDirectory(prefix="bench_loader_") as tmp:
        for label, unsigned in (("int16, intercept 0", False), ("uint16, intercept -1024", True)):
            folder = Path(tmp) / label.split(",")[0]
            write_case(folder, hu, unsigned=unsigned)
            vol = load_series(folder)
            assert np.array_equal(vol.voxels, hu), "loader returned wrong HU"
            floor_s, _ = median_time_s(functools.partial(naive_read_series, folder), repeats=args.repeats)
            load_s, _ = median_time_s(functools.partial(load_series, folder), repeats=args.repeats)
            list_s, _ = median_time_s(functools.partial(list_series, folder), repeats=args.repeats)
            peak = peak_python_memory_bytes(functools.partial(load_series, folder))
            rows.append(
                [
                    f"512x512x{args.slices} {label}",
                    floor_s,
                    load_s,
                    load_s / floor_s,
                    list_s,
                    peak / 2**20,
                    peak / volume_bytes,
                ]
            )
            del vol
    print_table(
        f"Series loading, median of {args.repeats} runs (one process, page cache warm)", COLUMNS, rows
    )
    print_table(
        "Before: registration/dicom_series.py (commit 9daed23), same command, median of 5 runs",
        COLUMNS,
        BEFORE,
    )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
