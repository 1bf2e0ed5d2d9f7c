"""Closed-form least-squares rigid fit (Kabsch / Arun / Umeyama) with the determinant fix.

Given paired points ``p_k`` (source) and ``q_k`` (target), find the proper
rotation R (det R = +1) and translation t minimising ``Σ w_k |R p_k + t − q_k|²``.

Arun, Huang & Blostein 1987 (doi:10.1109/TPAMI.1987.4767965) solve it with the
SVD of the cross-covariance H = Σ w_k (p_k − p̄)(q_k − q̄)ᵀ = U S Vᵀ, R = V Uᵀ.
That R is a *reflection* (det −1) when the data are mirrored or coplanar with
noise; Umeyama 1991 (doi:10.1109/34.88573, eq. 39–43) fixes it with
D = diag(1, 1, sign det(V Uᵀ)): R = V D Uᵀ.  Every function here applies that
fix, so nothing in this module ever returns det R = −1: a mirrored input shows
up as a large residual instead of being fitted silently
(research/registration-ecosystem.md §1.6, "reflection trap").
"""

from __future__ import annotations

import logging
from typing import Final

import numpy as np
from numpy.typing import ArrayLike

from registration.arrays import F64
from registration.errors import DegenerateConfigurationError, PointSetError

log = logging.getLogger(__name__)

MIN_POINTS: Final = 3
"""A rigid fit needs at least three non-collinear point pairs."""


def as_points(a: ArrayLike, name: str) -> F64:
    """``a`` as an (N, 3) float64 array of finite points (mm); :class:`PointSetError` naming ``name``
    and the bad shape or rows otherwise.  The one point-set check of the registration."""
    arr = np.asarray(a, dtype=np.float64)
    if arr.ndim != 2 or arr.shape[1] != 3:
        raise PointSetError(
            f"{name}: expected an (N, 3) array of sphere centres in mm, got shape {arr.shape}"
        )
    if not np.all(np.isfinite(arr)):
        bad = np.flatnonzero(~np.all(np.isfinite(arr), axis=1))
        raise PointSetError(f"{name}: rows {bad[:5].tolist()} contain NaN or infinite values")
    return arr


def fit_rigid(
    source_mm: ArrayLike,
    target_mm: ArrayLike,
    weights: ArrayLike | None = None,
) -> F64:
    """Least-squares proper rigid transform ``target_from_source`` (Umeyama 1991 without scale).

    Parameters
    ----------
    source_mm : array_like, shape (N, 3), float
        Source points (e.g. robot frame, mm).
    target_mm : array_like, shape (N, 3), float
        Target points paired row by row with ``source_mm`` (e.g. image frame, mm).
    weights : array_like, shape (N,), optional
        Non-negative weights (e.g. 1/σ² of each pair); uniform if omitted.

    Returns
    -------
    ndarray, shape (4, 4), float64
        ``target_from_source`` with det R = +1 exactly (up to round-off).

    Raises
    ------
    PointSetError
        A point set is not (N, 3) or has non-finite values.
    ValueError
        Shapes differ, fewer than 3 pairs or bad weights (programming errors: callers validate user
        data first).
    DegenerateConfigurationError
        All source or target points coincide (rotation undetermined).
    """
    p = as_points(source_mm, "source_mm")
    q = as_points(target_mm, "target_mm")
    if p.shape != q.shape:
        raise ValueError(f"fit_rigid: source has {len(p)} points, target {len(q)}; they must be paired")
    if len(p) < MIN_POINTS:
        raise ValueError(f"fit_rigid: need at least {MIN_POINTS} point pairs, got {len(p)}")
    if weights is None:
        w = np.full(len(p), 1.0 / len(p))
    else:
        w = np.asarray(weights, dtype=np.float64).reshape(-1)
        if w.shape != (len(p),) or not np.all(np.isfinite(w)) or np.any(w < 0) or w.sum() <= 0:
            raise ValueError("fit_rigid: weights must be N finite non-negative values with a positive sum")
        w = w / w.sum()
    p_bar = w @ p  # weighted centroids (Umeyama eq. 34, 35)
    q_bar = w @ q
    pc = p - p_bar
    qc = q - q_bar
    if float(np.max(np.abs(pc))) == 0.0 or float(np.max(np.abs(qc))) == 0.0:
        raise DegenerateConfigurationError(
            "rigid fit: all points coincide, the rotation is undetermined; need >= 3 distinct, "
            "non-collinear spheres"
        )
    h = (pc * w[:, None]).T @ qc  # cross-covariance Σ w p_c q_cᵀ (Arun eq. 11)
    rot = _rotation_from_covariance(h)
    out = np.eye(4)
    out[:3, :3] = rot
    out[:3, 3] = q_bar - rot @ p_bar
    return out


def fit_rigid_unchecked(source_mm: F64, target_mm: F64) -> F64:
    """:func:`fit_rigid` without input validation, uniform weights (for inner loops such as ICP).

    ``source_mm`` and ``target_mm`` must be finite (K, 3) float64 arrays, K ≥ 3.
    """
    p_bar = source_mm.mean(axis=0)
    q_bar = target_mm.mean(axis=0)
    h = (source_mm - p_bar).T @ (target_mm - q_bar)
    rot = _rotation_from_covariance(h)
    out = np.eye(4)
    out[:3, :3] = rot
    out[:3, 3] = q_bar - rot @ p_bar
    return out


def _rotation_from_covariance(h: F64) -> F64:
    """R = V D Uᵀ with D = diag(1, 1, sign det(V Uᵀ)) from H = U S Vᵀ (Umeyama eq. 39–43)."""
    u, _, vt = np.linalg.svd(h)
    v = vt.T
    if np.linalg.det(v @ u.T) < 0.0:
        v = v.copy()
        v[:, 2] = -v[:, 2]  # V D with D = diag(1, 1, −1)
    return np.asarray(v @ u.T, dtype=np.float64)


def fit_rigid_batch(source_mm: F64, target_mm: F64) -> F64:
    """Vectorised :func:`fit_rigid` for many small problems at once (uniform weights).

    Parameters
    ----------
    source_mm : ndarray, shape (H, K, 3) or (K, 3)
        Source points per problem (a single (K, 3) set is shared by all problems).
    target_mm : ndarray, shape (H, K, 3)
        Target points per problem, paired with the source rows.

    Returns
    -------
    ndarray, shape (H, 4, 4), float64
        ``target_from_source`` per problem, each with det R = +1.  Degenerate
        problems (coincident points) yield an arbitrary proper rotation; callers
        score hypotheses afterwards, so no error is raised here.
    """
    q = np.asarray(target_mm, dtype=np.float64)
    p = np.asarray(source_mm, dtype=np.float64)
    if p.ndim == 2:
        p = np.broadcast_to(p, q.shape)
    p_bar = p.mean(axis=1)
    q_bar = q.mean(axis=1)
    h = np.einsum("hki,hkj->hij", p - p_bar[:, None, :], q - q_bar[:, None, :])
    u, _, vt = np.linalg.svd(h)
    v = np.swapaxes(vt, 1, 2)
    ut = np.swapaxes(u, 1, 2)
    det = np.linalg.det(v @ ut)
    d = np.where(det < 0.0, -1.0, 1.0)
    v = v.copy()
    v[:, :, 2] *= d[:, None]  # V D: flip the last column of V where det(V Uᵀ) < 0
    rot = v @ ut
    out = np.zeros((len(q), 4, 4))
    out[:, :3, :3] = rot
    out[:, :3, 3] = q_bar - np.einsum("hij,hj->hi", rot, p_bar)
    out[:, 3, 3] = 1.0
    return out


def nearest_rotation(matrix: ArrayLike) -> tuple[F64, F64]:
    """Closest proper rotation to a 3 × 3 matrix (polar decomposition via SVD, det fix).

    Returns
    -------
    rotation : ndarray, shape (3, 3)
        The proper rotation R minimising the Frobenius distance |A − R| among
        det R = +1 matrices.
    singular_values : ndarray, shape (3,)
        Singular values of A (all 1 for a rotation): the non-rigidity of A.
    """
    a = np.asarray(matrix, dtype=np.float64).reshape(3, 3)
    u, s, vt = np.linalg.svd(a)
    d = np.sign(np.linalg.det(u @ vt))
    if d == 0.0:
        d = 1.0
    return np.asarray(u @ np.diag([1.0, 1.0, d]) @ vt, dtype=np.float64), np.asarray(s, dtype=np.float64)


def residuals_mm(transform: F64, source_mm: F64, target_mm: F64) -> F64:
    """Per-pair distances |T·p_k − q_k| in mm, shape (N,)."""
    mapped = source_mm @ transform[:3, :3].T + transform[:3, 3]
    return np.asarray(np.linalg.norm(mapped - target_mm, axis=1), dtype=np.float64)


def rotation_difference_deg(r_a: F64, r_b: F64) -> float:
    """Angle of the rotation taking ``r_b`` to ``r_a`` (deg, 0…180)."""
    c = (float(np.trace(r_a @ r_b.T)) - 1.0) / 2.0
    return float(np.degrees(np.arccos(np.clip(c, -1.0, 1.0))))
