"""Spheres at the edge of the field of view: which are reported, and how well, by their margin.

Run ``python -m benchmarks.bench_fov_edge [--seeds 2] [--cache-dir DIR]``.

The hard sweep's partial-FOV scans (``benchmarks/bench_detection.py``) put few spheres near the FOV
circle by chance.  Here the phantom of each partial-FOV condition (steel, tungsten carbide; the
same parallel-beam settings) is posed so that its outermost sphere in the slab sits at a chosen
margin from the circle (surface inside it by the margin; negative: cut by it), for margins from
−1.0 to +1.5 mm.  Every sphere within 2 mm of the circle and a slice-spacing away from the slab
ends is scored: reported (a detection within 1 mm) or not, and the reported centre's error.  A
sphere with a negative margin is cut (not fully imaged) and must never be reported; a whole
sphere close to the circle may be refused when its clipped plateau runs into it
(``DetectionParams.edge_plateau_fraction``).  All scans are this project's own simulator's.
"""

from __future__ import annotations

import argparse
import itertools
import pickle
from pathlib import Path
from typing import Any, Final

import numpy as np

from benchmarks.bench_detection import HARD_CONDITIONS, MATCH_MM, hard_pose, hard_scene, hard_settings
from benchmarks.common import print_table

MARGINS_MM: Final = (-1.0, -0.6, -0.3, -0.15, -0.05, 0.05, 0.15, 0.3, 0.5, 0.7, 1.0, 1.5)
"""Margin of the outermost sphere's surface inside the FOV circle (mm) per scan."""

BINS_MM: Final = (-2.0, -0.5, -0.2, 0.0, 0.2, 0.4, 0.7, 1.0, 2.0)
"""Edges of the margin bins of the table (mm)."""

CONDITIONS: Final = ("steel partial x40", "WC partial x45")


def edge_pose(cond: dict[str, Any], seed: int, margin_mm: float) -> np.ndarray:
    """``hard_pose`` shifted in-plane so the outermost slab sphere's surface is ``margin_mm``
    inside the FOV circle (image = scanner axes for the axial orientation of these scans)."""
    from registration.model import frames

    phantom, ex = hard_scene(cond)
    s = hard_settings(cond, seed)
    pose = hard_pose(cond, seed)
    c = frames.apply(pose, ex.actual_centres_phantom_mm(phantom))
    half_z = (s.n_slices - 1) / 2.0 * s.slice_spacing_mm
    in_slab = np.abs(c[:, 2]) + phantom.sphere_radius_mm + s.slice_spacing_mm <= half_z
    rho = np.hypot(c[:, 0], c[:, 1])
    n = int(np.argmax(np.where(in_slab, rho, -np.inf)))
    direction = np.array([c[n, 0], c[n, 1], 0.0]) / rho[n]
    shift = (s.fov_radius_mm - phantom.sphere_radius_mm - margin_mm) - rho[n]
    out = pose.copy()
    out[:3, 3] += shift * direction
    return out


def _scan(cond: dict[str, Any], seed: int, margin_mm: float, cache_dir: Path | None) -> tuple[Any, Any]:
    from mocks.oarm.simulator import simulate_scan

    key = "".join(ch if ch.isalnum() else "_" for ch in cond["name"])
    path = None if cache_dir is None else cache_dir / f"fov_{key}_{seed}_{margin_mm:+.2f}.pkl"
    if path is not None and path.is_file():
        with path.open("rb") as f:
            return tuple(pickle.load(f))  # type: ignore[return-value]
    phantom, ex = hard_scene(cond)
    scan = simulate_scan(phantom, edge_pose(cond, seed, margin_mm), hard_settings(cond, seed), ex)
    if path is not None:
        path.parent.mkdir(parents=True, exist_ok=True)
        with path.open("wb") as f:
            pickle.dump((phantom, scan), f)
    return phantom, scan


def score(phantom: Any, scan: Any) -> list[tuple[float, float | None]]:
    """(margin mm, error mm of the reported centre or None) of every sphere near the circle."""
    from mocks.oarm.simulator import scan_to_volume
    from registration.detection import detect_spheres, params_for_spheres
    from registration.model import frames

    s = scan.settings
    res = detect_spheres(
        scan_to_volume(scan), params_for_spheres(scan.sphere_material, phantom.sphere_diameter_mm)
    )
    c = frames.apply(scan.image_from_phantom, scan.extras.actual_centres_phantom_mm(phantom))
    half_z = (s.n_slices - 1) / 2.0 * s.slice_spacing_mm
    margin = s.fov_radius_mm - np.hypot(c[:, 0], c[:, 1]) - phantom.sphere_radius_mm
    in_slab = np.abs(c[:, 2]) + phantom.sphere_radius_mm + s.slice_spacing_mm <= half_z
    near = (np.abs(margin) <= 2.0) & in_slab
    out: list[tuple[float, float | None]] = []
    for n in np.flatnonzero(near):
        d = np.linalg.norm(res.centres_image_mm - c[n], axis=1) if len(res.centres_image_mm) else np.zeros(0)
        hit = len(d) > 0 and float(d.min()) < MATCH_MM
        out.append((float(margin[n]), float(d.min()) if hit else None))
    return out


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, default=2, help="poses per margin and condition")
    ap.add_argument("--cache-dir", type=Path, default=None, help="pickle the scans here and reuse them")
    args = ap.parse_args(argv)
    conds = [c for c in HARD_CONDITIONS if c["name"] in CONDITIONS]
    for cond in conds:
        rows: list[tuple[float, float | None]] = []
        for seed in range(args.seeds):
            for m in MARGINS_MM:
                rows.extend(score(*_scan(cond, 500 + seed, m, args.cache_dir)))
        table = []
        for lo, hi in itertools.pairwise(BINS_MM):
            sel = [e for m, e in rows if lo <= m < hi]
            errs = [e for e in sel if e is not None]
            table.append(
                [
                    f"[{lo:+.1f}, {hi:+.1f})",
                    len(sel),
                    len(errs),
                    float(np.mean(errs)) if errs else float("nan"),
                    float(np.max(errs)) if errs else float("nan"),
                ]
            )
        print_table(
            f"{cond['name']}: spheres by surface margin inside the FOV circle ({args.seeds} poses × "
            f"{len(MARGINS_MM)} margins)",
            ["margin mm", "spheres", "reported", "error mean mm", "max"],
            table,
        )


if __name__ == "__main__":
    main()
