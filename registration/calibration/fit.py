"""The robust fit: a soft-L1 loss on each sphere's distance (not its x, y, z, so it does not depend on
the image axes), Gaussian priors as extra residuals (``map``), scipy's trust-region solver with the
analytic Jacobian, outlier poses, leave-one-pose-out, and the prior weight chosen by
cross-validation over poses (never on held-out data)."""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import TYPE_CHECKING, Any, Final

import numpy as np
from numpy.typing import NDArray
from scipy.optimize import least_squares

from registration.arrays import F64
from registration.calibration.model import (
    ErrorModel,
    Observations,
    jacobian,
    residuals_mm,
)
from registration.calibration.records import PRIORS, CalibrationParams, MatchedPose
from registration.errors import OutlierPoseError

if TYPE_CHECKING:
    pass


I64 = NDArray[np.int64]


MAX_NFEV: Final = 100
"""Residual evaluations of the robust fit at most (the 10 × 28 benchmark session takes ~15)."""


FTOL: Final = 1e-12
"""``least_squares`` ftol: relative cost decrease to stop at.  On the 10 × 28 session of
``benchmarks/bench_calibration.py --solve-only`` it stops after ~15 evaluations instead of ~33 at
machine epsilon, the parameters within 3e-8 (rad, mm) of the ε-converged ones (the smallest
standard error is 1e-5); on exact data the cost falls by more than this every step until round-off, so
held-out poses are still recovered to 1e-6 mm (tests/unit/registration/calibration/test_calibration.py)."""


XTOL: Final = float(np.finfo(np.float64).eps)
"""``least_squares`` xtol and gtol: machine epsilon, the smallest scipy accepts (a backstop; the
hand-written LM ``least_squares`` replaced stopped on a 1e-13 scaled step)."""


GTOL: Final = XTOL


TR_SOLVER: Final = "lsmr"
"""Trust-region subproblem solver of TRF: ``"lsmr"`` (matrix-vector products only), not
``"exact"``, whose SVD of the (3L, P) Jacobian per iteration goes through scipy's threaded OpenBLAS
— on the shared 2-core machine 0.09–0.47 s per 840 × 30 SVD vs 4 ms single-threaded (measured
with ``OPENBLAS_NUM_THREADS=1``; threadpoolctl is not installed): 0.5–2.2 s per calibration
without LOPO vs 0.2–0.6 s with lsmr (``benchmarks/bench_calibration.py --solve-only``)."""


LSMR_TOL: Final = 1e-14
"""lsmr ``atol`` = ``btol`` of the TRF subproblem.  At lsmr's default 1e-6 the inexact steps stall
TRF (100 evaluations, not converged, measured); at 1e-14 it converges as with ``"exact"``."""


def _sphere_soft_l1(z: F64) -> F64:
    """soft-L1 ρ(s) = 2(√(1+s) − 1) of each sphere's squared 3-D distance s = Σ over its x, y, z
    components of ``z`` (already divided by ``f_scale``²), in ``least_squares``'s callable-loss form:
    rows ρ, ρ′, ρ″ per residual component (ρ split in three so the cost sums per sphere).

    ρ″ is returned as 0: the cross-component Hessian of a per-sphere loss is not diagonal, and
    with 0 the trust-region model is the IRLS one (gradient exact, weights ρ′ per sphere)."""
    s = np.repeat(z.reshape(-1, 3).sum(axis=1), 3)
    root = np.sqrt(1.0 + s)
    return np.stack([2.0 * (root - 1.0) / 3.0, 1.0 / root, np.zeros_like(s)])


def _prior_loss(n_data: int) -> Any:
    """The per-sphere soft-L1 on the first ``n_data`` components, a plain square on the prior rows."""

    def loss(z: F64) -> F64:
        out = np.empty((3, len(z)))
        out[:, :n_data] = _sphere_soft_l1(z[:n_data])
        out[0, n_data:], out[1, n_data:], out[2, n_data:] = z[n_data:], 1.0, 0.0
        return out

    return loss


def _augmented(model: ErrorModel, data: Observations) -> tuple[Any, Any, Any]:
    """(residuals, Jacobian, loss) of the MAP cost: sphere residuals, then w_j θ_j per prior row."""
    w = model.prior_weights
    if w is None or not np.any(w > 0):
        return (lambda v: residuals_mm(model, data, v)), (lambda v: jacobian(model, data, v)), _sphere_soft_l1
    rows = np.flatnonzero(w > 0)
    prior_jac = np.zeros((len(rows), len(w)))
    prior_jac[np.arange(len(rows)), rows] = w[rows]
    n_data = 3 * len(data.pose_of)

    def fun(v: F64) -> F64:
        return np.concatenate([residuals_mm(model, data, v), w[rows] * v[rows]])

    def jac(v: F64) -> F64:
        return np.vstack([jacobian(model, data, v), prior_jac])

    return fun, jac, _prior_loss(n_data)


def fit_parameters(model: ErrorModel, data: Observations, x0: F64, params: CalibrationParams) -> F64:
    """Robust least squares on all sphere residuals: ``scipy.optimize.least_squares`` (TRF) with
    the analytic Jacobian and a soft-L1 loss of scale ``robust_scale_mm`` on each sphere's 3-D
    distance; with ``model.prior_weights`` the MAP cost (prior rows squared)."""
    fun, jac, loss = _augmented(model, data)
    res = least_squares(
        fun,
        np.asarray(x0, dtype=np.float64),
        jac=jac,
        method="trf",
        loss=loss,
        f_scale=params.robust_scale_mm,
        x_scale="jac",
        tr_solver=TR_SOLVER,
        tr_options={"atol": LSMR_TOL, "btol": LSMR_TOL} if TR_SOLVER == "lsmr" else {},
        ftol=FTOL,
        xtol=XTOL,
        gtol=GTOL,
        max_nfev=MAX_NFEV,
    )
    return np.asarray(res.x, dtype=np.float64)


def per_pose_errors_mm(
    model: ErrorModel, data: Observations, values: F64, n_poses: int
) -> tuple[F64, F64, list[F64]]:
    err = np.linalg.norm(residuals_mm(model, data, values).reshape(-1, 3), axis=1)
    per = [err[data.pose_of == i] for i in range(n_poses)]
    rms = np.array([math.sqrt(float(np.mean(e**2))) if e.size else float("nan") for e in per])
    mx = np.array([float(e.max()) if e.size else float("nan") for e in per])
    return rms, mx, per


def _outliers(rms_mm: F64, used: NDArray[np.bool_], params: CalibrationParams) -> NDArray[np.bool_]:
    med = float(np.median(rms_mm[used]))
    return np.asarray(
        used & (rms_mm > max(params.outlier_factor * med, params.outlier_floor_mm)), dtype=np.bool_
    )


def leave_one_out_errors_mm(
    model: ErrorModel, data: Observations, values: F64, used: NDArray[np.bool_], params: CalibrationParams
) -> tuple[F64, F64]:
    """Mean and RMS sphere prediction error (mm) of each used pose from a fit without it (NaN if unused)."""
    out = np.full(len(used), np.nan)
    out_rms = np.full(len(used), np.nan)
    idx = np.flatnonzero(used)
    for k in idx:
        keep = used.copy()
        keep[k] = False
        v = fit_parameters(model, data.subset(keep), values, params)
        one = np.zeros(len(used), dtype=bool)
        one[k] = True
        held = data.subset(one)
        err = np.linalg.norm(residuals_mm(model, held, v).reshape(-1, 3), axis=1)
        out[k], out_rms[k] = float(err.mean()), math.sqrt(float(np.mean(err**2)))
    return out, out_rms


def fit_without_outliers(
    model: ErrorModel, data: Observations, poses: Sequence[MatchedPose], params: CalibrationParams
) -> tuple[F64, NDArray[np.bool_], tuple[F64, F64, list[F64]]]:
    """Fit all poses; flag poses whose RMS residual stands out, then refit without them (or refuse)."""
    values = fit_parameters(model, data, np.zeros(len(model.params)), params)
    used = np.ones(len(poses), dtype=bool)
    rms, mx, per = per_pose_errors_mm(model, data, values, len(poses))
    flagged = _outliers(rms, used, params)
    if flagged.any():
        names = [f"{poses[int(i)].name} (RMS {rms[i]:.3f} mm)" for i in np.flatnonzero(flagged)]
        if params.outliers == "refuse" or int((~flagged).sum()) < params.min_poses:
            raise OutlierPoseError(
                "scans inconsistent with the others (robot moved during the scan, wrong joints or a wrong "
                f"sphere match): {', '.join(names)}; median pose RMS {np.median(rms):.3f} mm. Rescan them"
            )
        used = ~flagged
        values = fit_parameters(model, data.subset(used), values, params)
        rms, mx, per = per_pose_errors_mm(model, data, values, len(poses))
    return values, used, (rms, mx, per)


def prior_weights_for(model: ErrorModel, params: CalibrationParams, scale: float) -> F64 | None:
    """σ_d / (s σ_j) per parameter (0 for the flat-prior rod and placement); None for ``"ls"``."""
    if params.estimator == "ls":
        return None
    sig = np.array([PRIORS.sigma(p) for p in model.params])
    return np.where(np.isfinite(sig), params.data_sd_mm / (scale * np.where(np.isfinite(sig), sig, 1.0)), 0.0)


def cross_validate(
    model: ErrorModel, data: Observations, x0: F64, params: CalibrationParams
) -> tuple[float, dict[float, float]]:
    """Prior scale with the least mean squared sphere error on left-out poses (k-fold over poses).

    Each fold leaves out every ``cv_folds``-th pose, fits the rest (same O-arm placement, so the
    left-out poses are predicted with the fitted ``image_from_robot``) and scores the left-out
    detections.  Never sees the held-out poses of a benchmark."""
    n = len(data.joints_rad)
    k = max(2, min(params.cv_folds, n))
    folds = [np.arange(n) % k == f for f in range(k)]
    scores: dict[float, float] = {}
    for scale in params.prior_scales:
        m = model.with_prior(prior_weights_for(model, params, scale))
        sq, cnt = 0.0, 0
        for f in folds:
            v = fit_parameters(m, data.subset(~f), x0, params)
            r = residuals_mm(m, data.subset(f), v)
            sq += float(r @ r)
            cnt += len(r) // 3
        scores[scale] = sq / max(cnt, 1)
    return min(scores, key=lambda s_: scores[s_]), scores
