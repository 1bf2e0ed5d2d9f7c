"""How large the calibrated chain's error will be where surgery happens: the posterior covariance
propagated through the kinematics at poses spread over the working volume, the unmodelled residual,
and the inflation a farthest-poses split measures (docs/calibration.md, "Predicted error")."""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, Final

import numpy as np
from numpy.typing import NDArray

from registration.arrays import F64
from registration.calibration.fit import (
    fit_parameters,
)
from registration.calibration.model import (
    ErrorModel,
    Observations,
    jacobian,
    residuals_mm,
)
from registration.calibration.records import (
    PRIORS,
    CalibrationParams,
    UnmodelledEstimate,
    WorkingPrediction,
)

if TYPE_CHECKING:
    from registration.calibration.sampling import ScanVolume


I64 = NDArray[np.int64]


WORKING_POSES: Final = 40
"""Poses sampled over the working volume for the predicted error (and the refusal)."""


LS_PRIOR_WEIGHT: Final = 1e-6
"""The least-squares estimator fits without a prior, so its covariance must not borrow one (it made
weakly seen directions look known): only this vanishing fraction of the prior stays, to keep the
normal matrix invertible where the poses see nothing (then the prediction shows it)."""


WORKING_SEED: Final = 20201202
"""Fixed: the working-volume sample is a property of the session, not a random draw per call."""


def posterior_covariance(
    model: ErrorModel,
    data: Observations,
    values: F64,
    params: CalibrationParams,
    scale: float,
    pose_shared_rms_mm: float = 0.0,
) -> F64:
    """(JᵀJ / σ̂² + Σ_prior⁻¹)⁻¹: the Gauss–Newton posterior covariance of the estimate, widened
    for the error every sphere of a scan shares.

    σ̂² = Σr² / (m − P) from the sphere residuals (at least (1 µm)²).  The prior (robot parameters:
    :data:`PRIORS` × the cross-validated scale for ``"map"``, × :data:`LS_PRIOR_WEIGHT` for
    ``"ls"``; rod and placement: :meth:`Priors.sigma_posterior`) bounds what the poses cannot see,
    so a direction they miss shows in the predicted error instead of vanishing in a pseudo-inverse.

    The Gauss–Newton form assumes independent residuals.  A pose's unmodelled error (the arm's
    repeatability, sag) moves all its spheres together, and 28 spheres sharing one error carry
    one observation of it, not 28: the covariance is the sandwich H⁻¹ (H + E) H⁻¹ with
    E = (u² / 3) Σ_poses SᵢᵀSᵢ / σ̂⁴, Sᵢ the (3, P) sum of pose i's sphere Jacobians and u the
    3-D RMS shared per-pose translation (``pose_shared_rms_mm``, what the residuals show:
    :func:`unmodelled_rms_from_fit_mm`).  Without it the chain part of the prediction was ⅓–½ of the
    measured chain error on random pose sets of the test bed (docs/calibration.md)."""
    jac = jacobian(model, data, values)
    r = residuals_mm(model, data, values)
    s2 = max(float(r @ r) / max(len(r) - len(values), 1), 1e-6)
    sig = np.array([PRIORS.sigma_posterior(p) for p in model.params])
    robot = np.array([p.group not in ("image_from_robot", "tool0_from_phantom") for p in model.params])
    sig = np.where(robot, sig * (scale if math.isfinite(scale) else 1.0), sig)
    prior = 1.0 / sig**2
    if params.estimator == "ls":
        prior = prior * LS_PRIOR_WEIGHT
    return sandwich_covariance(jac, data.pose_of, s2, prior, pose_shared_rms_mm)


def sandwich_covariance(
    jac: F64, pose_of: NDArray[np.int64], s2: float, prior: F64, pose_shared_rms_mm: float
) -> F64:
    """H⁻¹ (H + E) H⁻¹, H = JᵀJ / s2 + diag(prior), E = (u² / 3) Σ_poses SᵢᵀSᵢ / s2²
    (:func:`posterior_covariance`; the planner calls it on its noise-free planning Jacobian)."""
    per_pose = jac.reshape(-1, 3, jac.shape[1])
    sums = np.stack([per_pose[pose_of == i].sum(axis=0) for i in np.unique(pose_of)])
    return sandwich_from_sums(
        np.einsum("ij,ik->jk", jac, jac), np.einsum("kip,kiq->pq", sums, sums), s2, prior, pose_shared_rms_mm
    )


def sandwich_from_sums(info: F64, shared_info: F64, s2: float, prior: F64, pose_shared_rms_mm: float) -> F64:
    """:func:`sandwich_covariance` from JᵀJ (``info``) and Σ SᵢᵀSᵢ (``shared_info``)."""
    a = info / s2 + np.diag(prior)
    d = np.sqrt(np.diag(a))
    h_inv = np.linalg.inv(a / np.outer(d, d)) / np.outer(d, d)
    if pose_shared_rms_mm > 0.0:
        e = (pose_shared_rms_mm**2 / 3.0) * shared_info / s2**2
        h_inv = h_inv + h_inv @ e @ h_inv
    return np.asarray((h_inv + h_inv.T) / 2.0, dtype=np.float64)


def _skew_rows(p: F64) -> F64:
    """(3N, 6) Jacobian of a small rigid motion (ω, t) of points p (N, 3): ω × p + t."""
    n = len(p)
    g = np.zeros((n, 3, 6))
    g[:, 0, 1], g[:, 0, 2] = p[:, 2], -p[:, 1]
    g[:, 1, 0], g[:, 1, 2] = -p[:, 2], p[:, 0]
    g[:, 2, 0], g[:, 2, 1] = p[:, 1], -p[:, 0]
    g[:, :, 3:] = np.eye(3)
    return g.reshape(3 * n, 6)


def effective_jacobians(
    model: ErrorModel, values: F64, joints_rad: F64, reg_joints_rad: F64, pts: F64
) -> F64:
    """(W, 3N, P) sphere-position Jacobians at ``joints_rad`` after a one-scan re-registration at
    ``reg_joints_rad``: J_q − G_q G_reg⁺ J_reg (the rigid part the registration absorbs removed)."""
    q = np.vstack([joints_rad, reg_joints_rad[None]])
    n = len(pts)
    data = Observations(
        q, np.tile(pts, (len(q), 1)), np.zeros((len(q) * n, 3)), np.repeat(np.arange(len(q)), n)
    )
    jac = jacobian(model, data, values).reshape(len(q), 3 * n, len(values))
    world = model.predict(values, q, data.pts_phantom_mm, data.pose_of).reshape(len(q), n, 3)
    g_reg = _skew_rows(world[-1])
    proj = np.linalg.pinv(g_reg) @ jac[-1]  # (6, P)
    g_q = np.stack([_skew_rows(w) for w in world[:-1]])  # (W, 3N, 6)
    return np.asarray(jac[:-1] - g_q @ proj, dtype=np.float64)


def unmodelled_rms_from_fit_mm(
    model: ErrorModel, data: Observations, values: F64, fle_rms_mm: float
) -> float:
    """RMS of the per-pose rigid part of the residuals beyond what FLE leaks into it, *in sample*:
    what the fit left of the errors no geometric model has at its own poses (it absorbs most of
    them, so this is biased low; a diagnostic beside :func:`loo_unmodelled`)."""
    r = residuals_mm(model, data, values).reshape(-1, 3)
    world = model.predict(values, data.joints_rad, data.pts_phantom_mm, data.pose_of)
    ms = []
    for i in range(len(data.joints_rad)):
        rows = data.pose_of == i
        if rows.sum() < 3:
            continue
        g = _skew_rows(world[rows])
        sol, *_ = np.linalg.lstsq(g, r[rows].reshape(-1), rcond=None)
        rigid = (g @ sol).reshape(-1, 3)
        ms.append(float(np.mean(np.sum(rigid**2, axis=1))) - 2.0 * fle_rms_mm**2 / int(rows.sum()))
    return math.sqrt(max(float(np.mean(ms)) if ms else 0.0, 0.0))


@dataclass(frozen=True)
class LooMoments:
    """Per pose i of :func:`loo_unmodelled`: the rigid part of its leave-one-pose-out residual and
    what the error model expects of it.  E[``q``] = ``a`` FLE² + ``b`` u², Var[``q``] =
    ``var_fle`` FLE⁴ + ``var_cross`` FLE² u² + ``var_u`` u⁴ (a Gaussian quadratic form)."""

    q: F64
    a: F64
    b: F64
    var_fle: F64
    var_cross: F64
    var_u: F64


MAX_LOO_FLE_GAIN: Final = 100.0
"""A pose whose leave-one-pose-out residual would carry more than this many FLE² per sphere (``a`` of
:class:`LooMoments`) is not predicted by the other poses: they leave the parameters it depends on
undetermined, the linearised refit extrapolates, and its residual says nothing of the unmodelled
error.  Measured on the test bed (benchmarks/calib_testbed.py, seeds 1–3, planned poses): ``a`` is
0.07–0.3 at 10 and more poses, ≤ 5 at 8, and 6·10³–1.5·10⁵ at 6 (every pose's leave-out fit is
short of data: 6 poses gave û ≈ 190 mm and a false refusal of a calibration that measured 0.05 mm
at held-out poses)."""


def loo_moments(model: ErrorModel, data: Observations, values: F64, ridge: F64) -> LooMoments:
    """Leave-one-pose-out residuals of the linearised fit and their expected size, per pose.

    Fitting without pose i moves the estimate by −A₋ᵢ⁻¹ Jᵢᵀ rᵢ (A₋ᵢ = Σ_{k≠i} JₖᵀJₖ + diag(``ridge``),
    the normal matrix without the pose; exact for a linear model with a quadratic prior), so pose
    i's held-out residual is r̃ᵢ = rᵢ + Jᵢ A₋ᵢ⁻¹ Jᵢᵀ rᵢ — the block form of PRESS, no refit.  ``q`` is
    the mean squared rigid part of r̃ᵢ per sphere (3-D): a shared error of the pose (the arm's
    repeatability, sag the model does not have) is rigid, so the rigid part carries it while the
    detection noise leaks only 6 of its 3n dimensions into it.

    Under the error model of :func:`sandwich_covariance` (isotropic detection noise FLE² / 3 per
    component; a shared per-pose translation of u² 3-D at every pose) r̃ᵢ has covariance
    Σᵢ + Jᵢ A₋ᵢ⁻¹ (Σ_{k≠i} Jₖᵀ Σₖ Jₖ) A₋ᵢ⁻¹ Jᵢᵀ: the pose's own error and the error the other
    poses leave in the estimate.  It is linear in FLE² and u², which gives ``a`` and ``b``.

    A pose gives no residual when it has fewer than 3 spheres or the other poses do not determine
    its leave-out fit (A₋ᵢ singular, or ``a`` > :data:`MAX_LOO_FLE_GAIN`)."""
    jac = jacobian(model, data, values)
    r = residuals_mm(model, data, values)
    world = model.predict(values, data.joints_rad, data.pts_phantom_mm, data.pose_of)
    k, p = len(data.joints_rad), len(values)
    sph_rows = [np.flatnonzero(data.pose_of == i) for i in range(k)]
    comp_rows = [(3 * s[:, None] + np.arange(3)).reshape(-1) for s in sph_rows]
    js = [jac[c] for c in comp_rows]
    infos = np.stack([j.T @ j for j in js])
    sums = np.stack([j.reshape(-1, 3, p).sum(axis=0) for j in js])  # (K, 3, P)
    shared = np.einsum("kip,kiq->kpq", sums, sums)
    info_all, shared_all = infos.sum(axis=0), shared.sum(axis=0)
    out = np.full((6, k), np.nan)
    for i in range(k):
        n = len(sph_rows[i])
        if n < 3:
            continue
        a_i = info_all - infos[i] + np.diag(ridge)
        d = np.sqrt(np.clip(np.diag(a_i), 1e-300, None))
        try:
            inv = np.linalg.inv(a_i / np.outer(d, d)) / np.outer(d, d)
        except np.linalg.LinAlgError:
            continue
        ji, ri = js[i], r[comp_rows[i]]
        rt = ri + ji @ (inv @ (ji.T @ ri))
        basis, _ = np.linalg.qr(_skew_rows(world[sph_rows[i]]))  # (3n, 6): the pose's rigid motions
        qj = basis.T @ ji
        # covariance of r̃ᵢ in the rigid basis, per unit FLE²: (I + Jᵢ A⁻¹ Σ_{k≠i} JₖᵀJₖ A⁻¹ Jᵢᵀ) / 3;
        # per unit u²: (TTᵀ + Jᵢ A⁻¹ Σ_{k≠i} SₖᵀSₖ A⁻¹ Jᵢᵀ) / 3, T the (3n, 3) shared translation
        c_fle = (np.eye(6) + qj @ inv @ (info_all - infos[i]) @ inv @ qj.T) / 3.0
        qt = basis.T @ np.tile(np.eye(3), (n, 1))
        c_u = (qt @ qt.T + qj @ inv @ (shared_all - shared[i]) @ inv @ qj.T) / 3.0
        pr = basis.T @ rt
        out[:, i] = (
            float(pr @ pr) / n,
            float(np.trace(c_fle)) / n,
            float(np.trace(c_u)) / n,
            2.0 * float(np.sum(c_fle * c_fle)) / n**2,
            4.0 * float(np.sum(c_fle * c_u)) / n**2,
            2.0 * float(np.sum(c_u * c_u)) / n**2,
        )
    ok = np.all(np.isfinite(out), axis=0) & (out[1] <= MAX_LOO_FLE_GAIN)  # nan compares False
    return LooMoments(*(np.asarray(v[ok], dtype=np.float64) for v in out))


def loo_unmodelled(m: LooMoments, fle_rms_mm: float, start_mm: float) -> tuple[float, float]:
    """(û², its standard error) mm² of the per-pose unmodelled error from :func:`loo_moments`:
    generalised least squares of qᵢ − aᵢ FLE² = bᵢ u² over the poses, each weighted by the inverse
    of its variance at the current û² (from ``start_mm``², three passes).  The poses are treated
    as independent (they share the fit: a little optimistic on the standard error).  (nan, nan)
    without poses."""
    if not len(m.q):
        return math.nan, math.nan
    f2 = fle_rms_mm**2
    u2 = start_mm**2
    est, se = math.nan, math.nan
    for _ in range(3):
        var = m.var_fle * f2**2 + m.var_cross * f2 * u2 + m.var_u * u2**2
        w = m.b**2 / np.clip(var, 1e-300, None)
        est = float(np.sum(m.b / np.clip(var, 1e-300, None) * (m.q - m.a * f2)) / np.sum(w))
        se = math.sqrt(1.0 / float(np.sum(w)))
        u2 = max(est, 0.0)
    return est, se


MIN_LOO_POSES: Final = 3
"""Fewer poses with a held-out residual than this give no estimate of the unmodelled error: the
prior (``unmodelled_floor_mm``) stands."""


def estimate_unmodelled(
    model: ErrorModel, data: Observations, values: F64, fle_rms_mm: float, params: CalibrationParams
) -> UnmodelledEstimate:
    """The per-pose unmodelled error the prediction adds (and the sandwich takes), with its source.

    ``"leave-one-pose-out"`` (default): û² ± se from the session's own held-out residuals
    (:func:`loo_moments`, :func:`loo_unmodelled`); the prediction takes the upper bound
    û² + ``unmodelled_se_factor`` · se, so a session whose poses measure it poorly gets a wider
    figure.  When one standard error alone exceeds the prior (``unmodelled_floor_mm``²) the poses
    cannot tell it from the prior, and the figure is at least the prior.  Never below the arm's
    repeatability (``repeatability_rms_mm``): every move lands elsewhere by that much."""
    in_sample = unmodelled_rms_from_fit_mm(model, data, values, fle_rms_mm)
    floor, rep = params.unmodelled_floor_mm, params.repeatability_rms_mm
    if params.unmodelled_source == "prior":
        return UnmodelledEstimate(
            max(in_sample, floor, rep),
            "prior",
            f"asked for (unmodelled_source): max(in-sample rigid residual {in_sample:.4f} mm, "
            f"prior {floor:g} mm)",
            in_sample_rms_mm=in_sample,
        )
    s2 = max(fle_rms_mm**2 / 3.0, 1e-6)
    ridge = s2 * LS_PRIOR_WEIGHT / np.array([PRIORS.sigma_posterior(p) for p in model.params]) ** 2
    if model.prior_weights is not None:
        ridge = ridge + model.prior_weights**2
    moments = loo_moments(model, data, values, ridge)
    est, se = loo_unmodelled(moments, fle_rms_mm, max(rep, in_sample))
    n = len(moments.q)
    if n < MIN_LOO_POSES or not (math.isfinite(est) and math.isfinite(se)):
        return UnmodelledEstimate(
            max(floor, rep),
            "prior",
            f"only {n} of {len(data.joints_rad)} poses have a held-out residual the other poses determine "
            f"(need {MIN_LOO_POSES}): the prior {floor:g} mm",
            est,
            se,
            n,
            in_sample,
        )
    upper = math.sqrt(max(est, 0.0) + params.unmodelled_se_factor * se)
    said = (
        f"{n} poses' held-out residuals: û = {math.sqrt(max(est, 0.0)):.4f} mm, "
        f"standard error of û² {se:.2g} mm², upper bound {upper:.4f} mm"
    )
    if math.sqrt(se) > floor:
        return UnmodelledEstimate(
            max(upper, floor, rep),
            "leave-one-pose-out, widened to the prior",
            f"{said}; one standard error ({math.sqrt(se):.4f} mm) is wider than the prior {floor:g} mm: "
            "the poses do not measure it, at least the prior",
            est,
            se,
            n,
            in_sample,
        )
    return UnmodelledEstimate(max(upper, rep), "leave-one-pose-out", said, est, se, n, in_sample)


def registration_tre_ms(
    model: ErrorModel,
    values: F64,
    working_joints_rad: F64,
    registration_joints_rad: F64,
    pts: F64,
    fle_rms_mm: float,
) -> F64:
    """(W,) mean squared TRE over each working pose's spheres of the one-scan registration at
    ``registration_joints_rad`` (Fitzpatrick 1998 eq. 46, FLE ``fle_rms_mm``): the registration's
    rotation error grows with the distance from the registration scan's spheres, and a working
    pose's spheres are up to ~150 mm from them (evaluated at the registration scan's own
    spheres, the term was ⅓ of what the test bed's held-out poses measure)."""
    from registration.matching.quality import predicted_tre_mm

    q = np.vstack([working_joints_rad, registration_joints_rad[None]])
    n = len(pts)
    world = model.predict(values, q, np.tile(pts, (len(q), 1)), np.repeat(np.arange(len(q)), n))
    world = world.reshape(len(q), n, 3)
    tre = predicted_tre_mm(fle_rms_mm, world[-1], world[:-1].reshape(-1, 3)).reshape(len(q) - 1, n)
    return np.asarray(np.mean(tre**2, axis=1), dtype=np.float64)


def predict_working_error(
    model: ErrorModel,
    values: F64,
    cov: F64,
    working_joints_rad: F64,
    registration_joints_rad: F64,
    pts: F64,
    *,
    unmodelled_rms_mm: float,
    registration_fle_rms_mm: float,
    candidate_joints_rad: F64 | None = None,
) -> WorkingPrediction:
    """Posterior covariance propagated through the kinematics to the working poses (after a one-scan
    re-registration at ``registration_joints_rad``), plus √2 × the unmodelled error (at the
    pose and at the registration pose) and the registration's TRE at the pose's spheres
    (:func:`registration_tre_ms`), in quadrature."""
    jeff = effective_jacobians(model, values, working_joints_rad, registration_joints_rad, pts)
    n = len(pts)
    chain_ms = np.einsum("wip,pq,wiq->w", jeff, cov, jeff) / n
    # A covariance is PSD, so a quadratic form below rounding of its diagonal terms means the
    # inversion lost its meaning (poses that leave a direction unseen): unbounded, not 0.
    rounding_ms = 1e-9 * np.einsum("wip,p,wip->w", jeff, np.abs(np.diag(cov)), jeff) / n
    chain_ms = np.where(chain_ms < -rounding_ms, np.inf, np.clip(chain_ms, 0.0, None))
    chain_rms = np.sqrt(chain_ms)
    reg_ms = registration_tre_ms(
        model, values, working_joints_rad, registration_joints_rad, pts, registration_fle_rms_mm
    )
    per = np.sqrt(chain_ms + 2.0 * unmodelled_rms_mm**2 + reg_ms)
    worst = int(np.argmax(per))
    lam, vec = np.linalg.eigh((cov + cov.T) / 2.0)
    lo = vec * np.sqrt(np.clip(lam, 0.0, None))
    _, _, vt = np.linalg.svd(jeff[worst] @ lo, full_matrices=False)
    direction = lo @ vt[0]
    share = np.abs(direction) / np.sqrt(np.clip(np.diag(cov), 1e-300, None))
    share = share / share.sum()
    order = np.argsort(-share)[:4]
    weak = tuple((model.params[j].name, float(share[j])) for j in order)
    exciting = np.zeros((0, len(registration_joints_rad)))
    if candidate_joints_rad is not None and len(candidate_joints_rad):
        c = candidate_joints_rad
        data = Observations(
            c, np.tile(pts, (len(c), 1)), np.zeros((len(c) * n, 3)), np.repeat(np.arange(len(c)), n)
        )
        jc = jacobian(model, data, values).reshape(len(c), 3 * n, len(values))
        gain = np.linalg.norm(jc @ direction, axis=1)
        exciting = c[np.argsort(-gain)[:3]]
    return WorkingPrediction(
        working_joints_rad,
        registration_joints_rad,
        per,
        chain_rms,
        np.sqrt(reg_ms),
        float(np.sqrt(np.mean(per**2))),
        float(per.max()),
        weak,
        exciting,
    )


def farthest_split_inflation(
    model: ErrorModel,
    data: Observations,
    values: F64,
    params: CalibrationParams,
    fle_rms_mm: float,
    unmodelled_rms_mm: float,
) -> tuple[float, tuple[int, ...]]:
    """How optimistic the posterior is away from the poses: hold out the poses farthest from the
    rest (largest RMS sphere distance to their nearest other pose, ⌈K/4⌉ of them, ≥ 2), fit the
    others, and compare the held-out poses' squared error (detection error removed) with what the
    split fit's posterior (+ unmodelled) predicts there.  Returns (k² ≥ 1, held-out pose indices)."""
    k = len(data.joints_rad)
    n_out = max(2, math.ceil(k / 4))
    if k - n_out < 3:
        return 1.0, ()
    world = model.predict(values, data.joints_rad, data.pts_phantom_mm, data.pose_of)
    pts = data.pts_phantom_mm[data.pose_of == 0]
    q = data.joints_rad
    full = Observations(
        q, np.tile(pts, (k, 1)), np.zeros((k * len(pts), 3)), np.repeat(np.arange(k), len(pts))
    )
    w = model.predict(values, q, full.pts_phantom_mm, full.pose_of).reshape(k, len(pts), 3)
    d = np.sqrt(np.mean(np.sum((w[:, None] - w[None]) ** 2, axis=-1), axis=-1))
    np.fill_diagonal(d, np.inf)
    out = tuple(int(i) for i in np.argsort(-d.min(axis=1))[:n_out])
    del world
    held = np.zeros(k, dtype=bool)
    held[list(out)] = True
    train = data.subset(~held)
    v = fit_parameters(model, train, values, params)
    cov = posterior_covariance(model, train, v, params, 1.0)
    test = data.subset(held)
    r = residuals_mm(model, test, v).reshape(-1, 3)
    obs = float(np.mean(np.sum(r**2, axis=1))) - fle_rms_mm**2
    jac = jacobian(model, test, v).reshape(len(r), 3, len(v))
    pred = float(np.mean(np.einsum("lip,pq,liq->l", jac, cov, jac))) + unmodelled_rms_mm**2
    if pred <= 0.0:
        return 1.0, out
    return max(1.0, obs / pred), out


def _default_volume(meas_image_mm: F64) -> ScanVolume:
    from registration.calibration.sampling import ScanVolume

    d = ScanVolume()
    c = meas_image_mm.mean(axis=0)
    return ScanVolume(
        (float(c[0]), float(c[1]), float(c[2])), d.fov_radius_mm, d.half_length_mm, d.axis_image
    )


def working_prediction(
    model: ErrorModel,
    values: F64,
    cov: F64,
    data: Observations,
    pts: F64,
    params: CalibrationParams,
    scan_volume: ScanVolume | None,
    unmodelled_rms_mm: float,
    fle_rms_mm: float,
) -> tuple[WorkingPrediction, dict[str, Any]]:
    """Sample the working volume (scan volume + margin) with the calibrated model and predict."""
    from registration.calibration.sampling import sample_poses_in_volume

    y, x, cal_chain = model.unpack(values)
    vol = scan_volume if scan_volume is not None else _default_volume(data.meas_image_mm)
    work = vol.grown(params.working_margin_mm)
    rng = np.random.default_rng(WORKING_SEED)
    q0 = data.joints_rad[0]
    wq = sample_poses_in_volume(
        y,
        cal_chain,
        x,
        pts,
        q0,
        work,
        rng,
        n=WORKING_POSES,
        max_tilt_deg=75.0,
        margin_mm=0.0,
        n_candidates=300,
    )
    inside = sample_poses_in_volume(
        y, cal_chain, x, pts, q0, vol, rng, n=30, max_tilt_deg=75.0, margin_mm=5.0, n_candidates=300
    )
    if len(wq) == 0:
        wq = data.joints_rad
    if len(inside):
        centres = (y @ cal_chain.robot_from_tool0_batch(inside) @ x)[:, :3, 3]
        q_reg = inside[int(np.argmin(np.linalg.norm(centres - np.asarray(vol.centre_image_mm), axis=1)))]
    else:
        q_reg = q0
    pred = predict_working_error(
        model,
        values,
        cov,
        wq,
        q_reg,
        pts,
        unmodelled_rms_mm=unmodelled_rms_mm,
        registration_fle_rms_mm=fle_rms_mm,
        candidate_joints_rad=inside,
    )
    doc = {
        "scan_volume": {
            "centre_image_mm": list(vol.centre_image_mm),
            "fov_radius_mm": vol.fov_radius_mm,
            "half_length_mm": vol.half_length_mm,
            "axis_image": list(vol.axis_image),
            "from": "series geometry"
            if scan_volume is not None
            else "default O-arm cylinder on the detections",
        },
        "margin_mm": params.working_margin_mm,
        "n_poses": len(wq),
    }
    return pred, doc
