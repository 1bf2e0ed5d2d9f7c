"""Gated, trimmed ICP between labelled robot spheres and unlabelled image detections.

Besl & McKay 1992, "A method for registration of 3-D shapes"
(doi:10.1109/34.121791): alternate nearest-neighbour correspondence and a
closed-form least-squares rigid fit (here Kabsch/Umeyama with the determinant
fix, :func:`registration.matching.rigid.fit_rigid`) until the transform stops changing.

Changes from the textbook loop, all from research/registration-ecosystem.md §1.7:

* **Gate schedule.**  A pair counts only if the detection lies within the gate.
  The gate starts at about half the hole pitch (7.5 mm for the 15 mm grid: a
  sphere can never be paired with its neighbour's hole) and shrinks to
  ``gate_sigma_factor`` × the robust RMS residual (1.126 × median) of the current fit (at most halving
  per iteration, never below ``gate_floor_mm``).  A fixed tight gate fails when
  the initial error exceeds it; no gate lets spurious blobs drag the fit
  (TRE 2.8 mm median in the research's Open3D trial).
* **Trimming.**  Pairs beyond the shrunk gate are outliers and leave the fit.
* **Mutual uniqueness.**  A detection claimed by several robot spheres keeps
  only the closest one.
* **Convergence.**  Stop when the gate no longer shrinks, the pair set is
  unchanged and no robot sphere moved by more than ``tol_mm``; otherwise after
  ``max_iterations``.  The returned transform is the least-squares fit on the
  final pairs.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from typing import Final

import numpy as np
from numpy.typing import NDArray
from scipy.spatial import cKDTree

from registration.arrays import F64
from registration.matching.rigid import fit_rigid_unchecked

log = logging.getLogger(__name__)

I64 = NDArray[np.int64]

GATE_START_MM: Final = 7.5
"""Half the 15 mm hole pitch (Bai 2018 §2.1): a sphere can never pair with a neighbouring hole."""

GATE_SIGMA_FACTOR: Final = 3.0
"""Final gate = 3 × robust RMS residual (≈ 5σ per axis: a genuine pair is trimmed with p ≈ 1e-5)."""

GATE_FLOOR_MM: Final = 0.3
"""Smallest gate: ≈ 3 × the simulated FRE (σ ≈ 0.05 mm per axis per space) so sub-voxel
detection jitter is never trimmed; spurious blobs further than this from a sphere cannot pair."""

ROBUST_RMS_PER_MEDIAN: Final = 1.7321 / 1.5382
"""RMS / median of the Maxwell (χ, 3 dof) distribution: √3 σ over 1.5382 σ."""

MIN_PAIRS: Final = 3
"""A rigid fit needs 3 non-collinear pairs; with fewer the loop stops (the caller refuses it)."""

GATE_MIN_KEEP_FRACTION: Final = 0.5
"""The gate shrinks by at most this factor per iteration (7.5 mm → 0.3 mm in ~5 steps), so pairs
that are right but still far from the start pose are not cut off before the pose has moved."""

MAX_ITERATIONS: Final = 50
"""Besl & McKay converge in a handful of steps here; 50 is a safety bound (VTK's default)."""

TOL_MM: Final = 1e-7
"""Convergence: no robot sphere moved by more than this between two fits (mm)."""


@dataclass(frozen=True, eq=False)
class IcpResult:
    """Outcome of :func:`icp`.

    Attributes
    ----------
    image_from_robot : ndarray, shape (4, 4), float64
        Least-squares fit on the final pairs, det R = +1.
    robot_indices, image_indices : ndarray, shape (K,), int64
        The final pairs (robot sphere index, detection index).
    residuals_mm : ndarray, shape (K,), float64
        |T·p_robot − p_image| of each pair.
    n_iterations : int
    converged : bool
    final_gate_mm : float
    """

    image_from_robot: F64
    robot_indices: I64
    image_indices: I64
    residuals_mm: F64
    n_iterations: int
    converged: bool
    final_gate_mm: float

    @property
    def n_matched(self) -> int:
        return len(self.robot_indices)

    @property
    def rms_mm(self) -> float:
        return float(np.sqrt(np.mean(self.residuals_mm**2))) if len(self.residuals_mm) else float("inf")


def unique_pairs(dist: F64, image_idx: I64) -> tuple[I64, I64]:
    """Mutually unique pairs from a nearest-neighbour query.

    Parameters
    ----------
    dist : ndarray, shape (N,)
        Distance of each robot sphere to its nearest detection (inf = none in gate).
    image_idx : ndarray, shape (N,)
        Index of that detection.

    Returns
    -------
    robot_indices, image_indices : ndarray, shape (K,), int64
        Sorted by robot index; each detection appears at most once (the closest
        robot sphere keeps it).
    """
    cand = np.flatnonzero(np.isfinite(dist))
    if len(cand) == 0:
        return np.empty(0, dtype=np.int64), np.empty(0, dtype=np.int64)
    claimed = image_idx[cand]
    if len(np.unique(claimed)) == len(claimed):  # the usual case: already unique
        return cand.astype(np.int64), claimed.astype(np.int64)
    order = cand[np.argsort(dist[cand], kind="stable")]
    _, first = np.unique(image_idx[order], return_index=True)
    r = np.sort(order[first]).astype(np.int64)
    return r, image_idx[r].astype(np.int64)


def _final_fit(
    robot_mm: F64, image_mm: F64, tree: cKDTree, t: F64, gate_mm: float, r_idx: I64, i_idx: I64
) -> tuple[F64, I64, I64]:
    """The pairs at the final gate and their least-squares fit (the loop's pairs if fewer than 3)."""
    mapped = robot_mm @ t[:3, :3].T + t[:3, 3]
    d, j = tree.query(mapped, distance_upper_bound=gate_mm)
    r_fin, i_fin = unique_pairs(d, np.minimum(j, len(image_mm) - 1).astype(np.int64))
    if len(r_fin) < MIN_PAIRS:
        return t, r_idx, i_idx
    if not (np.array_equal(r_fin, r_idx) and np.array_equal(i_fin, i_idx)):
        t = fit_rigid_unchecked(robot_mm[r_fin], image_mm[i_fin])
    return t, r_fin, i_fin


def icp(
    robot_mm: F64,
    image_mm: F64,
    init_image_from_robot: F64,
    *,
    tree: cKDTree | None = None,
    gate_start_mm: float = GATE_START_MM,
    gate_sigma_factor: float = GATE_SIGMA_FACTOR,
    gate_floor_mm: float = GATE_FLOOR_MM,
    max_iterations: int = MAX_ITERATIONS,
    tol_mm: float = TOL_MM,
) -> IcpResult:
    """Refine ``init_image_from_robot`` by gated, trimmed, mutually unique ICP.

    Parameters
    ----------
    robot_mm : ndarray, shape (N, 3), float64
        Labelled sphere centres, robot frame, mm.
    image_mm : ndarray, shape (M, 3), float64
        Detections, image frame (LPS), mm.
    init_image_from_robot : ndarray, shape (4, 4)
        Start pose; every sphere should be within ``gate_start_mm`` of its mate.
    tree : cKDTree, optional
        A tree over ``image_mm`` (reused across calls).

    Returns
    -------
    IcpResult
        With fewer than :data:`MIN_PAIRS` pairs at any step the loop stops and returns the
        pairs it has (the caller refuses such a result).
    """
    if tree is None:
        tree = cKDTree(image_mm)
    t = np.asarray(init_image_from_robot, dtype=np.float64).copy()
    gate = float(gate_start_mm)
    prev_r: I64 | None = None
    r_idx = np.empty(0, dtype=np.int64)
    i_idx = np.empty(0, dtype=np.int64)
    converged = False
    it = 0
    for it in range(1, max_iterations + 1):
        mapped = robot_mm @ t[:3, :3].T + t[:3, 3]
        d, j = tree.query(mapped, distance_upper_bound=gate)
        r_idx, i_idx = unique_pairs(d, np.minimum(j, len(image_mm) - 1).astype(np.int64))
        if len(r_idx) < MIN_PAIRS:
            log.debug("icp: only %d pairs within %.2f mm at iteration %d", len(r_idx), gate, it)
            break
        t_new = fit_rigid_unchecked(robot_mm[r_idx], image_mm[i_idx])
        moved = robot_mm[r_idx] @ (t_new[:3, :3] - t[:3, :3]).T + (t_new[:3, 3] - t[:3, 3])
        change = float(np.sqrt(np.max(np.einsum("ij,ij->i", moved, moved))))
        res = np.linalg.norm(robot_mm[r_idx] @ t_new[:3, :3].T + t_new[:3, 3] - image_mm[i_idx], axis=1)
        # robust RMS: the median of a 3-D Gaussian residual distance is 1.538σ and its RMS 1.732σ,
        # so RMS ≈ 1.126 × median; unlike the plain RMS it is not inflated by the few outliers
        # (spurious blobs 2-4 mm from a missing sphere) that the gate is meant to trim
        rms = ROBUST_RMS_PER_MEDIAN * float(np.median(res))
        new_gate = max(gate_floor_mm, min(gate, max(gate_sigma_factor * rms, GATE_MIN_KEEP_FRACTION * gate)))
        same_pairs = prev_r is not None and np.array_equal(prev_r, r_idx)
        t = t_new
        if change < tol_mm and new_gate >= gate and same_pairs:
            converged = True
            break
        prev_r = r_idx
        gate = new_gate
    t, r_idx, i_idx = _final_fit(robot_mm, image_mm, tree, t, gate, r_idx, i_idx)
    res = np.asarray(
        np.linalg.norm(robot_mm[r_idx] @ t[:3, :3].T + t[:3, 3] - image_mm[i_idx], axis=1), dtype=np.float64
    )
    return IcpResult(
        image_from_robot=t,
        robot_indices=r_idx,
        image_indices=i_idx,
        residuals_mm=res,
        n_iterations=it,
        converged=converged,
        final_gate_mm=gate,
    )
