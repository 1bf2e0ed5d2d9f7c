"""Centre of an opaque sphere from its saturated core (the ``core`` detection method).

A tungsten-carbide sphere of 2.5 mm (μ ≈ 12 /mm at 70 keV) stops every ray through its middle:
its projections saturate at the photon-starvation / scatter floor, the reconstruction peaks far
above the 12-bit export's 3071 HU, and what remains below the clip is the far tail of the
point-spread function, shaped by the reconstruction's streaks and aliasing rather than by the
sphere's edge.  Measured on the simulator's ``wc_rows40`` scans (parallel beam, SPR 0.2–0.3,
benchmarks/bench_detection.py): the default centroid's ball (radius + 1.5 mm bloom, voxels above
half the clipped contrast) errs 0.060 mm mean over 306 spheres, the same error with no other
sphere in the slice (8 isolated spheres: 0.045 mm in-plane) and with a monochromatic beam (so
neither neighbouring-sphere streaks nor beam hardening are the cause).  Restricting the weights
to the saturated core (voxels above 85 % of the clipped contrast, inside radius + 1.0 mm) halves
the weight of that tail: 0.049 mm.  For steel and titanium, whose edge is not in the tail, the same
restriction measures worse (0.034 → 0.041 mm), so the method is chosen by sphere material
(:data:`registration.detection.METHOD_FOR_MATERIAL`), not by default.

The centroid is the same as the default one (:func:`registration.detection._ball_weights`): the
weight of a voxel is ``min(HU − background, cap) − margin`` clipped at 0, with a least-squares
plane through a shell outside the ball as background and ``cap`` the clipped contrast.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

F64 = NDArray[np.float64]


@dataclass(frozen=True)
class CoreParams:
    """What the core centroid changes from the default centroid (mm, fraction of the clipped contrast).

    Attributes
    ----------
    bloom_mm : float
        The ball is the nominal radius + this.  1.0 mm measured best of 0.75 / 1.0 / 1.25 / 1.5 /
        2.0 / 2.5 on the ``wc_rows40`` scans (mean 0.051 / 0.049 / 0.052 / 0.055 / 0.061 /
        0.072 mm at the default margin; 0.75 mm lost a sphere: too few voxels in the ball).
    margin_fraction : float
        Voxels count above this fraction of the sphere's contrast (clipped at saturation);
        0.85 measured best of 0.2 / 0.35 / 0.5 / 0.7 / 0.85 (mean 0.060 … 0.053 mm at the
        default ball, 0.049 mm with the 1.0 mm ball).
    """

    bloom_mm: float = 1.0
    margin_fraction: float = 0.85


@dataclass(frozen=True)
class CoreWeights:
    """Everything :func:`core_centroid` needs: :class:`CoreParams` plus what it shares with the
    default centroid (``registration.detection.DetectionParams``: ``centroid_margin_hu``,
    ``background_shell_mm``, ``centroid_iterations``, ``LINEAR_BACKGROUND_MIN_VOXELS``)."""

    core: CoreParams
    margin_hu: float
    shell_mm: float
    iterations: int
    min_shell_voxels: int


def core_centroid(
    values_hu: F64,
    coords_mm: F64,
    start_mm: F64,
    radius_mm: float,
    saturation_hu: float,
    weights: CoreWeights,
) -> F64 | None:
    """Weighted centroid (mm, the axis order of ``coords_mm``) of the core of a sphere.

    ``values_hu`` (V,) and ``coords_mm`` (V, 3) are the voxels around the sphere, ``start_mm``
    the first estimate, ``radius_mm`` the nominal radius, ``saturation_hu`` the export's clip
    value (inf if the voxels are not clipped).  None if the ball or the shell is empty or no
    voxel gets a weight.  The voxels must hold the whole ball and shell (a sphere near an edge
    of the imaged region is the caller's to keep out).
    """
    r_ball = radius_mm + weights.core.bloom_mm
    r_shell = r_ball + weights.shell_mm
    c = np.asarray(start_mm, dtype=np.float64).copy()
    for _ in range(max(1, weights.iterations)):
        off = coords_mm - c
        d2 = np.einsum("ij,ij->i", off, off)
        ball = d2 <= r_ball**2
        shell = (d2 > r_ball**2) & (d2 <= r_shell**2)
        if not ball.any() or not shell.any():
            return None
        if int(shell.sum()) > weights.min_shell_voxels:
            a = np.c_[np.ones(int(shell.sum())), off[shell]]
            coef = np.linalg.lstsq(a, values_hu[shell], rcond=None)[0]
            bg = coef[0] + off[ball] @ coef[1:]
        else:
            bg = np.full(int(ball.sum()), float(np.median(values_hu[shell])))
        signal = values_hu[ball] - bg
        cap = saturation_hu - float(bg.max()) if math.isfinite(saturation_hu) else float(signal.max())
        margin = max(weights.margin_hu, weights.core.margin_fraction * cap)
        w = np.clip(np.minimum(signal, cap) - margin, 0.0, None)
        total = float(w.sum())
        if total <= 0.0:
            return None
        c = (w[:, None] * coords_mm[ball]).sum(axis=0) / total
    return c
