"""Simulator speed (issue #2: full O-arm scan <= 90 s, small preset <= 5 s, demo <= 25 s on 2 cores).

Run: ``.venv/bin/python -m benchmarks.bench_simulator [--quick] [--cbct]`` (``--quick`` skips the full
presets; ``--cbct`` adds the cone-beam presets, issue #11: ``cbct-ci`` <= 60 s including RTK start-up,
``oarm-cbct`` <= 300 s; needs ``pip install 'oarmreg[cbct]'``).
"""

from __future__ import annotations

import sys
import tempfile
import time
from pathlib import Path
from typing import Any

from benchmarks.common import median_time_s, naive_read_series, print_table

REPO = Path(__file__).resolve().parents[1]
BUDGET_S = {
    "small": 5.0,
    "demo": 25.0,
    "oarm": 90.0,
    "small-realistic": 5.0,
    "demo-realistic": 25.0,
    "oarm-realistic": 90.0,
    "cbct-ci": 60.0,
    "oarm-cbct": 300.0,
}
"""Issue #2 / lead brief time budgets."""


def main(argv: list[str] | None = None) -> None:
    from mocks.oarm.cbct import CBCT_PRESET_NAMES, ConeBeamSettings, simulate_cbct
    from mocks.oarm.dicom_export import write_dicom_series
    from mocks.oarm.simulator import AcquisitionSettings, demo_pose, simulate_scan
    from registration.phantom import load_phantom

    args = sys.argv[1:] if argv is None else argv
    phantom = load_phantom(REPO / "configs" / "phantoms" / "bai2018_cube.toml")
    pose = demo_pose()
    presets = [("small", 5), ("demo", 3), ("small-realistic", 3), ("demo-realistic", 3)]
    presets += [] if "--quick" in args else [("oarm", 2), ("oarm-realistic", 2)]
    if "--cbct" in args:
        presets += [("cbct-ci", 1)] + ([] if "--quick" in args else [("oarm-cbct", 1)])
    rows = []
    for name, repeats in presets:
        settings = (ConeBeamSettings if name in CBCT_PRESET_NAMES else AcquisitionSettings).preset(name)
        scans = []

        def run(settings: Any = settings, scans: list = scans) -> None:
            sim = simulate_cbct if isinstance(settings, ConeBeamSettings) else simulate_scan
            scans.append(sim(phantom, pose, settings))

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
                t.get("fbp_s", t.get("fdk_s", 0.0)),
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
