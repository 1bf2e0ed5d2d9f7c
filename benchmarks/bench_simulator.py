"""Simulator speed (issue #2: full O-arm scan <= 90 s, small preset <= 5 s, demo <= 25 s on 2 cores).

Run: ``.venv/bin/python -m benchmarks.bench_simulator [--quick]`` (``--quick`` skips the full preset).
"""

from __future__ import annotations

import sys
import tempfile
import time
from pathlib import Path

from benchmarks.common import median_time_s, naive_read_series, print_table

REPO = Path(__file__).resolve().parents[1]
BUDGET_S = {"small": 5.0, "demo": 25.0, "oarm": 90.0}
"""Issue #2 / lead brief time budgets."""


def main(argv: list[str] | None = None) -> None:
    from mocks.oarm.dicom_export import write_dicom_series
    from mocks.oarm.simulator import AcquisitionSettings, demo_pose, simulate_scan
    from registration.phantom import load_phantom

    args = sys.argv[1:] if argv is None else argv
    phantom = load_phantom(REPO / "configs" / "phantoms" / "bai2018_cube.toml")
    pose = demo_pose()
    presets = [("small", 5), ("demo", 3)] + ([] if "--quick" in args else [("oarm", 2)])
    rows = []
    for name, repeats in presets:
        settings = AcquisitionSettings.preset(name)
        scans = []

        def run(settings: AcquisitionSettings = settings, scans: list = scans) -> None:
            scans.append(simulate_scan(phantom, pose, settings))

        med, times = median_time_s(run, repeats=repeats, warmup=0)
        scan = scans[-1]
        with tempfile.TemporaryDirectory() as tmp:
            t0 = time.perf_counter()
            write_dicom_series(scan, Path(tmp))
            write_s = time.perf_counter() - t0
            t0 = time.perf_counter()
            naive_read_series(Path(tmp))
            read_s = time.perf_counter() - t0
        shape = "x".join(str(v) for v in (settings.columns, settings.rows, settings.n_slices))
        t = scan.timings_s
        rows.append(
            [
                name,
                shape,
                settings.n_views,
                len(scan.sphere_indices),
                med,
                min(times),
                BUDGET_S[name],
                t.get("project_s", 0.0),
                t.get("fbp_s", 0.0),
                write_s,
                read_s,
            ]
        )
    print_table(
        "Simulator (median wall time, seconds)",
        [
            "preset",
            "matrix",
            "views",
            "spheres",
            "simulate_s",
            "best_s",
            "budget_s",
            "project_s",
            "fbp_s",
            "write_dicom_s",
            "naive_read_s",
        ],
        rows,
    )


if __name__ == "__main__":
    main()
