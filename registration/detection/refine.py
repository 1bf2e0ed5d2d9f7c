"""Step 4 of the detection: the centre of a sphere near an edge of the imaged region, re-measured.

Near a slab end, the matrix edge or the circular FOV the centroid is pulled inwards: the edge cuts
the sphere, or the bloom halo of a whole sphere close to it.  Along each such boundary the centre
is re-measured with a window symmetric about the estimate that never reaches past the data
(:func:`_symmetric_position`), and a sphere is refused as cut if that centre is less than the
nominal radius inside the edge, or if its clipped plateau runs into the edge
(:func:`registration.detection.fov.plateau_reaches_edge`).
"""

from __future__ import annotations

from typing import Any, Final

import numpy as np
from numpy.typing import NDArray

from registration.arrays import F64
from registration.detection.candidates import Support
from registration.detection.centroid import ball_weights
from registration.detection.fov import DataRegion, boundaries, plateau_reaches_edge
from registration.detection.params import DetectionParams

EDGE_WINDOW_ITERATIONS: Final = 8
"""Re-centrings of the symmetric window near an edge; each halves the remaining offset or better
(measured on spheres 0–2 mm inside the slab end: converged to < 0.01 mm after 5)."""


def _symmetric_position(
    w: F64, t_mm: F64, c_mm: float, edge_mm: float, step_mm: float, r_ball_mm: float
) -> float:
    """Centroid along a direction of the weights inside a window symmetric about the estimate.

    The window ``|t − c| ≤ h`` has ``h = min(r_ball, edge + step/2 − c)``: it never reaches past
    the last sample (which covers up to ``edge + step/2``), so what the edge cut off on one side is
    trimmed from the other and a symmetric blurred ball is located without bias.  Voxels are
    intervals of ``step_mm`` along the direction, counted by the fraction inside the window.
    ``w`` (V,) weights and ``t_mm`` (V,) positions along the direction (mm, edge at ``edge_mm``,
    data at t < edge).  Returns the centre along the direction (mm); beyond the edge if the ball is.
    """
    c = c_mm
    for _ in range(EDGE_WINDOW_ITERATIONS):
        h = min(r_ball_mm, edge_mm + 0.5 * step_mm - c)
        if h <= 0.0:
            return c
        m = w * np.clip((h - np.abs(t_mm - c)) / step_mm + 0.5, 0.0, 1.0)
        total = float(m.sum())
        if total <= 0.0:
            return c
        c = float((m * t_mm).sum()) / total
    return c


def edge_refined_centre(
    vox: NDArray[Any],
    centre_ijk: F64,
    spacing: F64,
    params: DetectionParams,
    fov_radius_mm: float | None,
    support: Support | None = None,
) -> tuple[F64, str | None]:
    """The centre of a sphere near an edge of the imaged region, and why it is cut (or None).

    Near a slab end, matrix edge or the FOV circle the centroid is pulled inwards: a sphere cut by
    the edge (its centre outside, or less than a radius inside) shows only its inner part, and the
    bloom halo of a whole sphere close to it is cut too.  Along each such boundary the centre is
    re-measured with :func:`_symmetric_position`, and the sphere is cut if that centre is less than
    the nominal radius from the edge (the simulator's and the registration's "fully imaged").
    """
    r_ball = params.radius_mm + params.bloom_mm
    centre = centre_ijk.astype(np.float64).copy()
    shape = (vox.shape[0], vox.shape[1], vox.shape[2])
    region = DataRegion(shape, spacing, fov_radius_mm)
    for name, u, edge_mm, step_mm in boundaries(centre, shape, spacing, fov_radius_mm):
        t_c = float(u @ (centre * spacing))
        if edge_mm - t_c > r_ball + step_mm:
            continue
        # In-plane edges only: at the slab ends the same test refused 4 more whole spheres on
        # the 12 partial-FOV sweep scans and no false one (the symmetric window below holds there).
        if u[2] == 0.0 and plateau_reaches_edge(
            vox,
            centre,
            spacing,
            u,
            params.radius_mm,
            r_ball,
            params.background_shell_mm,
            region,
            params.edge_plateau_fraction,
        ):
            return centre, (
                f"cut by the {name}: the sphere's image is still above {params.edge_plateau_fraction:.0%} "
                "of its peak where the image ends (the sphere is cut, or whole but too close to the "
                "edge to be located)"
            )
        bw = ball_weights(vox, centre, spacing, params, support)
        t = sum(float(u[a] * spacing[a]) * bw.ijk[a] for a in range(3))
        w, t_all = np.broadcast_arrays(bw.w, t)
        c = _symmetric_position(w.ravel(), t_all.ravel(), t_c, edge_mm, step_mm, r_ball)
        if edge_mm - c < params.radius_mm:
            return centre, (
                f"cut by the {name}: centre re-measured symmetrically {edge_mm - c:.2f} mm inside "
                f"it < sphere radius {params.radius_mm} mm"
            )
        centre = centre + (c - t_c) * u / spacing
    return centre, None
