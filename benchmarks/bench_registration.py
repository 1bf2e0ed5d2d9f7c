"""Registration speed: correspondence + ICP (+ symmetry and mirror checks) for 64 spheres + 10 spurious.

Issue #4 target: ≤ 20 ms median.  Run: ``python -m benchmarks.bench_registration``.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from benchmarks.common import median_time_s, print_table
from registration.matching.register import register_points
from registration.model import frames
from registration.model.phantom import load_phantom

REPO = Path(__file__).resolve().parents[1]
TARGET_MS = 20.0
REPEATS = 30


def _scene(
    centres_mm: np.ndarray, seed: int, n_spurious: int = 10, n_missing: int = 0
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    robot_from_ph = frames.make_transform(
        Rotation.random(random_state=seed).as_matrix(), [400.0, 50.0, 300.0]
    )
    truth = frames.make_transform(Rotation.random(random_state=seed + 1).as_matrix(), [5.0, -20.0, 80.0])
    robot = frames.apply(robot_from_ph, centres_mm) + rng.normal(0, 0.02, centres_mm.shape)
    image = frames.apply(truth @ robot_from_ph, centres_mm) + rng.normal(0, 0.05, centres_mm.shape)
    image = image[n_missing:]
    spurious = frames.apply(truth @ robot_from_ph, rng.uniform(-50, 50, (n_spurious, 3)))
    image = np.vstack([image, spurious])[rng.permutation(len(image) + n_spurious)]
    return robot, image, truth


def main(argv: list[str] | None = None) -> None:
    phantom = load_phantom(REPO / "configs" / "phantoms" / "bai2018_cube.toml")
    rows = []
    # 1. the fully filled 64-hole grid with an orientation prior 20° off
    robot, image, truth = _scene(phantom.holes_phantom_mm, 1)
    prior = Rotation.from_euler("xyz", [12.0, -10.0, 12.0], degrees=True).as_matrix() @ truth[:3, :3]
    med, _ = median_time_s(lambda: register_points(robot, image, orientation_prior=prior), repeats=REPEATS)
    rows.append(["64-hole grid + prior, 10 spurious", 64, len(image), med * 1e3, TARGET_MS])
    # 2. an asymmetric 64-point set (random, ≥ 6 mm apart) without prior
    rng = np.random.default_rng(7)
    pts: list[np.ndarray] = []
    while len(pts) < 64:
        p = rng.uniform(-1, 1, 3) * [35.0, 35.0, 40.0]
        if all(np.linalg.norm(p - q) > 6.0 for q in pts):
            pts.append(p)
    robot, image, _ = _scene(np.asarray(pts), 2)
    med, _ = median_time_s(lambda: register_points(robot, image), repeats=REPEATS)
    rows.append(["asymmetric 64-point set, 10 spurious", 64, len(image), med * 1e3, TARGET_MS])
    # 3. the default 28-sphere phantom, 3 missing (so the mirrored problem is tried too), 3 spurious,
    #    phantom symmetry twins checked explicitly
    robot, image, _ = _scene(phantom.centres_phantom_mm, 3, n_spurious=3, n_missing=3)
    res = register_points(robot, image, phantom=phantom)
    assert res.mirror_checked
    med, _ = median_time_s(lambda: register_points(robot, image, phantom=phantom), repeats=REPEATS)
    rows.append(["bai2018_cube (28), 3 missing: twins + mirror check", 28, len(image), med * 1e3, TARGET_MS])
    print_table(
        f"Registration: correspondence + ICP + checks (median of {REPEATS})",
        ["case", "spheres", "detections", "median ms", "target ms"],
        rows,
    )


if __name__ == "__main__":
    main()
