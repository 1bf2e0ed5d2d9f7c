"""The ``paper`` estimator: Bai 2018 (doi:10.1088/1742-6596/1016/1/012006, §2.2).

The in-plane centre is the mean of the slice circles' centres, the slice coordinate the
Pythagorean depth with the radius fitted to the circles' radii (r_i² + z_i² = c + 2·z0·z_i).
The circles are the measurement, so MAR runs on every slice patch first.  Measured less accurate
than the 3-D estimators on the raw volume (``benchmarks/bench_detection.py``); kept as the
published reference.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from registration.arrays import F64
from registration.detection.cross_check import SliceCircle
from registration.detection.estimators.base import MeasuredSphere


@dataclass(frozen=True, eq=False)
class PaperCircles:
    """What ``paper`` measures from: the slice circles, their fitted radius (mm), the slice spacing (mm)."""

    circles: list[SliceCircle]
    radius_fit_mm: float
    dz_mm: float


def _paper_depth(circles: list[SliceCircle], radius_mm: float, dz_mm: float) -> float:
    """Pythagorean depth (Bai 2018 §2.2): per slice two depths z_i ± √(R² − r_i²); the radius trend picks one.

    Slices before the largest circle (in k) have the centre above them, slices
    after it below; at the largest circle the larger neighbour says which way.
    Returns the centre's k (continuous slice index), the average over slices.
    """
    cs = sorted(circles, key=lambda c: c.k)
    radii = np.array([c.r_mm for c in cs])
    m = int(np.argmax(radii))
    zs = []
    for n, c in enumerate(cs):
        d = math.sqrt(max(radius_mm * radius_mm - c.r_mm * c.r_mm, 0.0)) / dz_mm
        if n < m:
            sign = 1.0
        elif n > m:
            sign = -1.0
        else:
            below = radii[n - 1] if n > 0 else -math.inf
            above = radii[n + 1] if n + 1 < len(cs) else -math.inf
            sign = 1.0 if above > below else -1.0
        zs.append(c.k + sign * d)
    return float(np.mean(zs))


class PaperEstimator:
    """``prepare``: the circles and their radius; ``estimate``: the circles' mean and Pythagorean depth."""

    circles_are_the_measurement = True

    def prepare(self, sphere: MeasuredSphere) -> PaperCircles:
        return PaperCircles(sphere.circles, sphere.radius_fit_mm, sphere.dz_mm)

    def estimate(self, prepared: PaperCircles) -> tuple[F64 | None, str]:
        """Bai 2018: in-plane mean of the circle centres, depth by Pythagoras with the fitted radius."""
        circles, radius_mm = prepared.circles, prepared.radius_fit_mm
        if len({c.k for c in circles}) < 2 or not math.isfinite(radius_mm) or radius_mm <= 0:
            return None, (
                f"paper method: {len(circles)} circle slice(s), the per-slice radii do not fit a sphere "
                "(r_i² + z_i² = c + 2·z0·z_i needs ≥ 2 slices); try --method subvoxel"
            )
        k_c = _paper_depth(circles, radius_mm, prepared.dz_mm)
        return np.array([np.mean([c.i for c in circles]), np.mean([c.j for c in circles]), k_c]), ""


ESTIMATOR = PaperEstimator()
