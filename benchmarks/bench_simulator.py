"""Simulator speed (issue #2: full O-arm scan <= 90 s, small preset <= 5 s, demo <= 25 s on 2 cores).

Run: ``.venv/bin/python -m benchmarks.bench_simulator [--quick] [--cbct] [--cbct-png]``.
``--quick`` skips the full presets; ``--cbct`` adds the cone-beam presets (issue #11: ``cbct-ci``
<= 60 s including RTK start-up, ``oarm-cbct`` <= 300 s; the FDK is numpy + OpenCV, RTK is only
timed, cold import, and cross-checks the slice-wise FBP on one slice: max |ΔHU| and centroid
differences); ``--cbct-png`` only redraws ``docs/img/sim_cbct_ci_*.png``.
"""

from __future__ import annotations

import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

from benchmarks.common import median_time_s, naive_read_series, print_table
from registration.arrays import F64

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


def rtk_import_s() -> float | None:
    """Wall time of a cold ``from itk import RTK`` plus its first class, in a fresh interpreter."""
    code = (
        "import time; t = time.perf_counter(); from itk import RTK; "
        "RTK.ThreeDCircularProjectionGeometry.New(); print(time.perf_counter() - t)"
    )
    res = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=False)
    return float(res.stdout.strip().splitlines()[-1]) if res.returncode == 0 else None


def _disc_sinogram(discs: list[tuple[float, float, float, float]], n_views: int, det: F64) -> F64:
    """Parallel-beam line integrals (V, D) of discs (x, y, r mm, μ 1/mm); θ = v·π/V, t = x cos θ + y sin θ."""
    theta = np.arange(n_views) * np.pi / n_views
    sino = np.zeros((n_views, len(det)))
    for x, y, r, mu in discs:
        p = x * np.cos(theta) + y * np.sin(theta)
        sino += mu * 2.0 * np.sqrt(np.clip(r**2 - (det[None, :] - p[:, None]) ** 2, 0.0, None))
    return sino


def fbp_cross_check(window: str = "ramp") -> dict[str, float] | None:
    """The slice-wise simulator's FBP against RTK's FDK in parallel geometry, one 256² slice.

    An analytic sinogram (water disc with two steel-like discs, 0.415 mm bins, 360 views over
    180°) is reconstructed by :func:`mocks.oarm.simulator.fbp` and by RTK (SDD = 0, the views
    mirrored to cover 360°, so RTK's angular weights are uniform); ``hann`` is RTK's
    ``HannCutFrequency`` 1.0 (0.5(1 + cos πi/n) over RTK's n = N/2 + 1 rfft bins; ours 0.5(1 + cos 2πf)).
    """
    try:
        import itk
        from itk import RTK as rtk
    except ImportError:
        return None
    from mocks.oarm.simulator import fbp

    n_views, n_det, px, n = 360, 600, 0.415, 256
    det = ((np.arange(n_det) - (n_det - 1) / 2.0) * px).astype(np.float64)
    discs = [(0.0, 0.0, 45.0, 0.02), (20.3, -10.1, 1.25, 0.6), (-15.2, 25.4, 1.25, 0.6)]
    sino = _disc_sinogram(discs, n_views, det)
    xs = (np.arange(n) - (n - 1) / 2.0) * px
    yy, xx = np.meshgrid(xs, xs, indexing="ij")
    ours = fbp(sino[None].astype(np.float32), px, np.c_[xx.ravel(), yy.ravel()], window)[:, 0].reshape(n, n)
    # RTK: rotation axis y_rtk, u = x cos φ − z_rtk sin φ = x cos φ + y sin φ (z_rtk = −y): t at φ = θ.
    g = rtk.ThreeDCircularProjectionGeometry.New()
    full = np.concatenate([sino, sino[:, ::-1]])  # p(θ + π, t) = p(θ, −t)
    for i in range(2 * n_views):
        g.AddProjection(1000.0, 0.0, i * 180.0 / n_views)
    # Three identical rows: RTK's bilinear back-projector needs a row on either side of v = 0.
    proj = itk.image_from_array(
        np.ascontiguousarray(np.repeat(full[:, None, :], 3, axis=1), dtype=np.float32)
    )
    proj.SetOrigin([float(det[0]), -1.0, 0.0])
    proj.SetSpacing([px, 1.0, 1.0])
    img_t = itk.Image[itk.F, 3]
    src = rtk.ConstantImageSource[img_t].New()
    src.SetOrigin([float(xs[0]), 0.0, float(-xs[-1])])
    src.SetSpacing([px, 1.0, px])
    src.SetSize([n, 1, n])
    fdk = rtk.FDKConeBeamReconstructionFilter[img_t].New()
    fdk.SetInput(0, src.GetOutput())
    fdk.SetInput(1, proj)
    fdk.SetGeometry(g)
    fdk.GetRampFilter().SetHannCutFrequency(1.0 if window == "hann" else 0.0)
    fdk.Update()
    theirs = np.asarray(itk.array_from_image(fdk.GetOutput()))[:, 0, :][::-1, :]  # [z_rtk, x] → [y, x]
    mu_w = 0.02
    hu_ours, hu_theirs = ours / mu_w * 1000.0, theirs / mu_w * 1000.0
    out = {"max_abs_hu": float(np.abs(hu_ours - hu_theirs).max()), "peak_hu": float(hu_theirs.max())}
    for k, (x, y, _, _) in enumerate(discs[1:]):
        m = np.hypot(xx - x, yy - y) < 2.5
        cen = [
            np.array([(np.clip(h - 0.3 * h[m].max(), 0, None)[m] * g_[m]).sum() for g_ in (xx, yy)])
            / np.clip(h - 0.3 * h[m].max(), 0, None)[m].sum()
            for h in (hu_ours, hu_theirs)
        ]
        out[f"sphere{k}_centroid_diff_mm"] = float(np.linalg.norm(cen[0] - cen[1]))
        out[f"sphere{k}_ours_err_mm"] = float(np.linalg.norm(cen[0] - [x, y]))
    return out


def cbct_pictures(out_dir: Path) -> list[Path]:
    """``cbct-ci`` scan of the demo pose (rod on): an axial slice through the most spheres and one
    near the top of the slab (far off the central plane) in a bone window, and a sagittal cut."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from mocks.oarm.cbct import ConeBeamSettings, simulate_cbct
    from mocks.oarm.simulator import SceneExtras, best_slice, demo_pose
    from registration.model.phantom import load_phantom

    phantom = load_phantom(REPO / "configs" / "phantoms" / "bai2018_cube.toml")
    s = ConeBeamSettings.preset("cbct-ci")
    scan = simulate_cbct(phantom, demo_pose(), s, SceneExtras(rod=True))
    k_mid = best_slice(scan)
    k_off = scan.hu.shape[0] - 3
    z = scan.image_from_voxel @ np.array([[0, 0, k, 1.0] for k in (k_mid, k_off)]).T
    paths = []
    for name, img, title in (
        ("sim_cbct_ci_bone_window.png", scan.hu[k_mid], f"axial k={k_mid} (z = {z[2, 0]:.1f} mm)"),
        ("sim_cbct_ci_offplane_bone_window.png", scan.hu[k_off], f"axial k={k_off} (z = {z[2, 1]:.1f} mm)"),
        (
            "sim_cbct_ci_sagittal_bone_window.png",
            scan.hu[:, :, scan.hu.shape[2] // 2],
            "sagittal, centre column",
        ),
    ):
        fig, ax = plt.subplots(figsize=(5, 5), dpi=110)
        aspect = s.slice_spacing_mm / s.pixel_mm if "sagittal" in name else 1.0
        ax.imshow(img, cmap="gray", vmin=-500, vmax=2000, aspect=aspect, interpolation="nearest")
        ax.set_title(f"cbct-ci, {title}\nbone window W 2500 / L 750 HU", fontsize=9)
        ax.axis("off")
        fig.tight_layout()
        paths.append(out_dir / name)
        fig.savefig(paths[-1])
        plt.close(fig)
    return paths


def main(argv: list[str] | None = None) -> None:
    from mocks.oarm.cbct import CBCT_PRESET_NAMES, ConeBeamSettings, simulate_cbct
    from mocks.oarm.dicom_export import write_dicom_series
    from mocks.oarm.simulator import AcquisitionSettings, demo_pose, simulate_scan
    from registration.model.phantom import load_phantom

    args = sys.argv[1:] if argv is None else argv
    if "--cbct-png" in args:
        for path in cbct_pictures(REPO / "docs" / "img"):
            print(path)
        return
    phantom = load_phantom(REPO / "configs" / "phantoms" / "bai2018_cube.toml")
    pose = demo_pose()
    presets = [("small", 5), ("demo", 3), ("small-realistic", 3), ("demo-realistic", 3)]
    presets += [] if "--quick" in args else [("oarm", 2), ("oarm-realistic", 2)]
    if "--cbct" in args:
        presets += [("cbct-ci", 3)] + ([] if "--quick" in args else [("oarm-cbct", 1)])
    rows = []
    for name, repeats in presets:
        settings = (ConeBeamSettings if name in CBCT_PRESET_NAMES else AcquisitionSettings).preset(name)
        scans: list[Any] = []
        cpu: list[float] = []

        def run(settings: Any = settings, scans: list[Any] = scans, cpu: list[float] = cpu) -> None:
            sim = simulate_cbct if isinstance(settings, ConeBeamSettings) else simulate_scan
            c0 = time.process_time()
            scans.append(sim(phantom, pose, settings))
            cpu.append(time.process_time() - c0)

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
                statistics.median(cpu),
                BUDGET_S[name],
                t.get("project_s", 0.0),
                t.get("fbp_s", t.get("fdk_s", 0.0)),
                write_s,
                read_s,
            ]
        )
    print_table(
        "Simulator (median wall time, seconds; cpu_s: process CPU time, all threads, a load-independent"
        " measure of work on a shared machine)",
        [
            "preset",
            "matrix",
            "views",
            "spheres",
            "simulate_s",
            "best_s",
            "cpu_s",
            "budget_s",
            "project_s",
            "fbp_s",
            "write_dicom_s",
            "naive_read_s",
        ],
        rows,
    )
    if "--cbct" in args:
        _report_cbct_extras()


def _report_cbct_extras() -> None:
    """RTK start-up (the numpy FDK does not need it) and the parallel-beam FBP against RTK."""
    imp = rtk_import_s()
    print(f"\nRTK import (cold, fresh interpreter): {'not installed' if imp is None else f'{imp:.1f} s'}")
    rows = []
    for window in ("ramp", "hann"):
        res = fbp_cross_check(window)
        if res is None:
            print("FBP cross-check skipped: itk-rtk not installed (scikit-image is not a dependency)")
            return
        rows.append([window, *res.values()])
        header = ["window", *res.keys()]
    print_table("Parallel-beam FBP (mocks.oarm.simulator.fbp) vs RTK, one 256² slice", header, rows)


if __name__ == "__main__":
    main()
