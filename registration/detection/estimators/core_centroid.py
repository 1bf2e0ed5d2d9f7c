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

The weight of a voxel is the default centroid's (:func:`registration.detection.centroid._ball_weights`),
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
from numpy.typing import NDArray

from registration.errors import DetectionError

F64 = NDArray[np.float64]


@dataclass(frozen=True)
class CoreParams:
    """What the core centroid changes from the default centroid (mm, fraction of the clipped contrast).

    Attributes
    ----------
    bloom_mm : float
        The hard ball of the edge path
        (:func:`registration.detection.estimators.core.core_edge_centre`) is the
        nominal radius + this.  1.0 mm measured best of 0.75 / 1.0 / 1.25 / 1.5 / 2.0 / 2.5 on
        the ``wc_rows40`` scans for the unwindowed centroid (mean 0.051 / 0.049 / 0.052 / 0.055 /
        0.061 / 0.072 mm at the default margin; 0.75 mm lost a sphere: too few voxels in the ball).
    window_mm : float
        The windowed ball of :func:`core_centroid` reaches the nominal radius + this (the window
        is 0 there).  On the cached WC hard-sweep scans (mean / max mm, parallel SPR 0.3 1e4 ·
        SPR 0.2 1e3 rod · cone-beam SPR 0.3 1e4, 160 / 120 / 120 spheres), unwindowed 1.0 mm ball
        and 3 re-centrings (before): 0.043 / 0.124 · 0.050 / 0.175 · 0.070 / 0.299; unwindowed,
        converged: 0.043 / 0.124 · 0.050 / 0.175 · 0.067 / 0.198; windowed 1.0 / 1.25 / 1.5 /
        2.0 mm: 0.045 / 0.121 · 0.052 / 0.191 · 0.059 / 0.159; 0.043 / 0.133 · 0.049 / 0.193 ·
        0.060 / 0.164; 0.042 / 0.131 · 0.046 / 0.174 · 0.062 / 0.159; 0.046 / 0.097 ·
        0.046 / 0.135 · 0.067 / 0.151.  1.5 mm has the lowest mean over all 426 WC spheres.
        Re-measured on the same scans simulated with 4 rays per detector pixel and axis
        (``WC_SUBRAYS`` in benchmarks/bench_detection.py; 2 quantised the opaque edge):
        unwindowed 1.0 mm ball, 3 re-centrings 0.042 / 0.119 · 0.049 / 0.171 · 0.065 / 0.261;
        converged 0.042 / 0.119 · 0.049 / 0.171 · 0.064 / 0.156; windowed 1.0 / 1.25 / 1.5 /
        2.0 mm 0.046 / 0.130 · 0.052 / 0.166 · 0.056 / 0.132; 0.043 / 0.127 · 0.048 / 0.177 ·
        0.057 / 0.138; 0.042 / 0.117 · 0.044 / 0.158 · 0.058 / 0.131; 0.045 / 0.100 · 0.043 /
        0.120 · 0.062 / 0.152 (1.5 mm again the lowest mean over the 426 spheres).  The slice
        coordinate from a parabola through the per-slice sums of the unwindowed core weights (as
        ``subvoxel`` does, ``registration.detection.centroid.axial_profile_position``) measured worse on
        these scans (0.051 / 0.134 · 0.057 / 0.157 · 0.060 / 0.181): a streak-bloomed clipped
        plateau's cross-section is not a disc.  A
        Gaussian window (σ 0.8 mm in a 1.5 mm ball: 0.049 / 0.118 · 0.057 / 0.197 · 0.063 /
        0.209) measured worse; restricting the weights to a split core's support (its opened
        metal mask, dilated) too (0.044 / 0.115 · 0.049 / 0.192 · 0.072 / 0.301).  With 745
        instead of 391 views one cone-beam scan errs the same (0.063 / 0.154 against 0.065 /
        0.159 mm): the cone-beam excess is not angular undersampling.
        Re-measured with the averaged margins (``averaged_margin_fractions``) and the cone-beam
        scans re-simulated at the O-arm's 0.65 mm PSF (mocks/oarm/cbct.py
        ``light_spread_fwhm_mm``), sweep (parallel SPR 0.3 · rod · cone-beam) and held-out
        (parallel both · cone-beam) mean / max mm, windows 1.25 / 1.5 / 1.75 / 2.0: 0.041 / 0.124
        · 0.046 / 0.173 · 0.036 / 0.080, held-out 0.042 / 0.134 · 0.038 / 0.127; 0.040 / 0.117 ·
        0.044 / 0.160 · 0.036 / 0.076, held-out 0.040 / 0.119 · 0.036 / 0.123; 0.041 / 0.106 ·
        0.043 / 0.140 · 0.036 / 0.081, held-out 0.040 / 0.097 · 0.036 / 0.125; 0.042 / 0.099 ·
        0.043 / 0.118 · 0.037 / 0.091, held-out 0.041 / 0.092 · 0.036 / 0.112.  1.5 still has the
        lowest pooled sweep mean (0.0399 against 0.0402 mm for 1.75), but the means are within
        0.001 mm of each other and the worst sphere is what a registration cannot average away:
        1.75 lowers the sweep's two largest maxima (0.160 → 0.140, 0.117 → 0.106 mm; the rod
        row's worst sphere sits at the cube's corner between the rod's streak and a neighbour's
        dark band, its clipped plateau a skewed parallelogram) at +0.005 mm on cone-beam's, and
        on the held-out seeds the parallel maximum falls (0.119 → 0.097) while the means stay.
        2.0 lowers the maxima further but raises the means (parallel 0.042, cone-beam 0.037).
    margin_fraction : float
        Voxels count above this fraction of the sphere's contrast (clipped at saturation);
        0.85 measured best of 0.2 / 0.35 / 0.5 / 0.7 / 0.85 for the unwindowed 1.0 mm ball (mean
        0.060 … 0.053 mm at the default ball, 0.049 mm with the 1.0 mm ball).  With the window,
        0.5 / 0.7 / 0.85 / 0.95 are about even (cone-beam mean 0.060 / 0.062 / 0.062 / 0.062 mm,
        max 0.172 / 0.150 / 0.159 / 0.168), so it stays as the margin of the edge path
        (:func:`registration.detection.estimators.core.core_edge_centre`); the windowed core away from an edge
        averages several margins (``averaged_margin_fractions``).
    averaged_margin_fractions : tuple of float
        :func:`core_centroid` runs its windowed, re-centred centroid once at each of these margins
        and averages the converged centres (``margin_fraction`` is the edge path's single margin).
        The centroids at neighbouring levels err alike but not identically (correlation of the
        column error 0.94 between 0.5 and 0.7, 0.67 between 0.5 and 0.95, cone-beam SPR 0.3), so
        the mean cancels part of each level's sampling and streak error.  Mean / max mm on the
        cached hard-sweep WC scans, window 1.5 mm (cone-beam SPR 0.3 · parallel SPR 0.3 · parallel
        SPR 0.2 1e3 rod, 120 / 160 / 120 spheres; the cone-beam scans at the earlier 0.61 mm PSF,
        mocks/oarm/cbct.py ``light_spread_fwhm_mm``) and on held-out seeds (cone-beam · both
        parallel, 120 / 240):
        0.85 alone 0.058 / 0.131 · 0.042 / 0.117 · 0.045 / 0.158, held-out 0.058 / 0.156 ·
        0.042 / 0.107; (0.5, 0.7, 0.85, 0.95) 0.054 / 0.129 · 0.040 / 0.117 · 0.044 / 0.160,
        held-out 0.056 / 0.157 · 0.040 / 0.119; with 0.3 added 0.053 / 0.139 · 0.040 / 0.123 ·
        0.045 / 0.163, held-out 0.056 / 0.157 · 0.040 / 0.142 (the low level follows the rod's
        and the neighbours' blooms in-plane, though it lowers the cone-beam slice error: 0.036 →
        0.027 mm rms, at 0.3 alone).
    max_iterations : int
        Re-centrings of the window at most.  3 (the default centroid's) left the worst cone-beam
        sphere 0.1 mm from where the iteration converges (0.299 → 0.198 mm error); 10 converged
        on every cached WC sphere to < ``tolerance_mm``.
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
