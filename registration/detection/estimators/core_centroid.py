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

The weight of a voxel is the default centroid's (:func:`registration.detection.centroid.ball_weights`),
``min(HU − background, cap) − margin`` clipped at 0, with a least-squares plane through a shell
outside the ball as background and ``cap`` the clipped contrast, times a window that falls from 1
at the estimate to 0 at the ball's edge (Epanechnikov, ``1 − (d / r_ball)²``), and the estimate
is re-centred until it moves less than a tolerance (a mean shift).  What biases the clipped core
is a streak that saturates on one side of the sphere (the plateau of a corner sphere or one next
to a neighbour runs out 2–4 voxels further on one side);
the window weighs a voxel by how near the sphere's middle it is, so the far end of such a plateau
counts little, and a symmetric plateau is still located without bias.  Measured on the cached
tungsten-carbide hard-sweep scans (``benchmarks/bench_detection.py --hard 40``, 426 spheres,
parallel and cone-beam): see :class:`CoreParams`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from registration.arrays import F64
from registration.errors import DetectionError


@dataclass(frozen=True)
class CoreParams:
    """What the core centroid changes from the default centroid (mm, fraction of the clipped contrast).

    The core of a tungsten-carbide sphere saturates; its centre is the average of windowed,
    re-centred centroids at several contrast margins (neighbouring levels err alike but not
    identically, so the mean cancels part of each one's sampling and streak error).  The defaults
    were chosen on the hard sweep's WC scans and checked on held-out seeds
    (``python -m benchmarks.bench_detection --hard 40`` and ``--seed-offset 1000 --only WC``); the
    figures of every alternative measured are in ``docs/detection-settings.md`` ("core").

    Attributes
    ----------
    bloom_mm : float
        The hard ball of the edge path
        (:func:`registration.detection.estimators.core.core_edge_centre`) is the nominal radius
        + this.
    window_mm : float
        The windowed ball of :func:`core_centroid` reaches the nominal radius + this (the window
        is 0 there); chosen for the lowest worst-sphere error at an even mean.
    margin_fraction : float
        Voxels count above this fraction of the sphere's contrast (clipped at saturation): the
        edge path's single margin.
    averaged_margin_fractions : tuple of float
        :func:`core_centroid` runs its windowed, re-centred centroid once at each of these
        margins and averages the converged centres.
    max_iterations : int
        Re-centrings of the window at most (3, the default centroid's, left the worst cone-beam
        sphere 0.1 mm short of convergence).
    tolerance_mm : float
        Stop re-centring once the estimate moves less than this (well below the 0.01 mm the
        figures are quoted to).
    """

    bloom_mm: float = 1.0
    window_mm: float = 1.75
    margin_fraction: float = 0.85
    averaged_margin_fractions: tuple[float, ...] = (0.5, 0.7, 0.85, 0.95)
    max_iterations: int = 10
    tolerance_mm: float = 1.0e-3

    def __post_init__(self) -> None:
        levels = self.averaged_margin_fractions
        if not levels or not all(0.0 < f < 1.0 for f in (*levels, self.margin_fraction)):
            raise DetectionError(
                f"core margins {self.margin_fraction} / {levels} must be fractions of the clipped "
                "contrast in (0, 1), at least one to average (defaults 0.85 / (0.5, 0.7, 0.85, 0.95))"
            )


@dataclass(frozen=True)
class CoreWeights:
    """Everything :func:`core_centroid` needs: :class:`CoreParams` plus what it shares with the
    default centroid (``registration.detection.DetectionParams``: ``centroid_margin_hu``,
    ``background_shell_mm``, ``LINEAR_BACKGROUND_MIN_VOXELS``)."""

    core: CoreParams
    margin_hu: float
    shell_mm: float
    min_shell_voxels: int


def core_centroid(
    values_hu: F64,
    coords_mm: F64,
    start_mm: F64,
    radius_mm: float,
    saturation_hu: float,
    weights: CoreWeights,
) -> F64 | None:
    """Mean of the windowed, weighted centroids (mm, the axis order of ``coords_mm``) of the core
    of a sphere at each of ``weights.core.averaged_margin_fractions``.

    ``values_hu`` (V,) and ``coords_mm`` (V, 3) are the voxels around the sphere, ``start_mm``
    the first estimate, ``radius_mm`` the nominal radius, ``saturation_hu`` the export's clip
    value (inf if the voxels are not clipped).  None if the ball or the shell is empty or no
    voxel gets a weight at any level (a level with none is left out of the mean).  The voxels
    must hold the whole ball and shell (a sphere near an edge of the imaged region is the
    caller's to keep out).
    """
    r_ball = radius_mm + weights.core.window_mm
    r_shell = r_ball + weights.shell_mm
    centres = [
        c
        for fraction in weights.core.averaged_margin_fractions
        if (
            c := _windowed_centroid(
                values_hu, coords_mm, start_mm, (r_ball, r_shell), saturation_hu, weights, fraction
            )
        )
        is not None
    ]
    return np.mean(centres, axis=0) if centres else None


def _windowed_centroid(
    values_hu: F64,
    coords_mm: F64,
    start_mm: F64,
    ball_shell_mm: tuple[float, float],
    saturation_hu: float,
    weights: CoreWeights,
    margin_fraction: float,
) -> F64 | None:
    """The windowed, weighted centroid of the core at one margin (``margin_fraction`` of the
    sphere's clipped contrast) in a ball and background shell of the given outer radii (mm),
    re-centred until it moves less than the tolerance; the rest as :func:`core_centroid`."""
    r_ball, r_shell = ball_shell_mm
    c = np.asarray(start_mm, dtype=np.float64).copy()
    for _ in range(max(1, weights.core.max_iterations)):
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
        margin = max(weights.margin_hu, margin_fraction * cap)
        window = 1.0 - d2[ball] / r_ball**2
        w = np.clip(np.minimum(signal, cap) - margin, 0.0, None) * window
        total = float(w.sum())
        if total <= 0.0:
            return None
        previous, c = c, (w[:, None] * coords_mm[ball]).sum(axis=0) / total
        if float(np.linalg.norm(c - previous)) < weights.core.tolerance_mm:
            break
    return c
