"""Multi-pose calibration of robot geometry, connecting rod and O-arm placement.

One session = K ≥ 6 scans of the phantom at different robot poses with the
O-arm left in place (one FrameOfReferenceUID).  Sphere ``k`` detected in scan
``i`` at ``d_ik`` (image, mm) is explained by::

    d_ik = Y · T(q_i; θ) · X · p_k

``Y`` = ``image_from_robot`` of the session, ``X`` = ``tool0_from_phantom``,
``T`` the arm's forward kinematics (:class:`~registration.calibration.urdf.SerialChain`)
with joint-origin corrections ``θ``, ``p_k`` the phantom's CAD centres.

**Parameter set** (``CalibrationParams.parameter_set``).  Each joint origin
``M_i`` gets a small correction ``M_i · E(ω, v)`` (rotation vector ω, translation
v, in joint *i*'s frame); a rotation about the joint's own axis ``a_i`` is its
zero offset.  Not all 36 components are identifiable: a rotation about / a
translation along ``a_i`` commutes with ``Rot(a_i, q_i)`` and so moves into the
next origin (or into X after the last joint), everything before joint 1 (and
joint 1's offset) is absorbed by Y, and everything after joint 6 by X.  With
the 12 parameters of X and Y this leaves the 30 of the minimal complete model
of a 6R arm measured in full pose (4R + 2P + 6, research/calibration.md §1),
i.e. **18 robot parameters**.  :func:`parameter_candidates` lists the 36 in a
fixed priority (offsets first, then axis tilts, axis shifts, slides) and
:func:`minimal_parameter_set` keeps, in that order, every one that adds rank
to the identification Jacobian at generic configurations — FIGAROH's QR
selection (research note §1), done greedily so the kept set is readable.
For the TX60 (and TX2-60) it is, 18 in all: the zero offsets of J2–J5 (4);
origin tilts J2 x, J3 x and z, J4 x, J5 x, J6 x and y (7); origin shifts J2 x,
J3 z, J4 x and y, J5 x and z, J6 y (7).  (Frames of the URDF: J1, J4, J6 turn
about z, J2, J3, J5 about y.)  J1's origin and offset and J6's offset are
absorbed by Y and X; parallel J2/J3 cost the shift of J3 along x.  Plain DH
would be singular for that parallel pair (research note §1); these local
origin corrections are not.
``"offsets"`` fits X, Y and the joint offsets only (research note §1,
"joint-offset-only model"); ``"hand-eye"`` fits X and Y only.

**Method.** Shah's closed form for AX = YB (Kronecker product, doi:10.1115/1.4024473)
from per-pose rigid fits gives X and Y with nominal kinematics; then
``scipy.optimize.least_squares`` (TRF, analytic Jacobian, ``x_scale="jac"``) on all sphere
residuals with a robust soft-L1 loss estimates X, Y and θ jointly (research note §2: point LSQ
after Shah).  The loss is applied to each sphere's 3-D distance (a callable loss, see
:func:`_sphere_soft_l1`), not to its x, y, z separately, so it does not depend on the image axes.

**Identifiability.** The SVD of the column-normalised Jacobian gives numeric
rank and condition number; above ``max_condition`` (default 100, Schroer et
al. as quoted by Nahvi & Hollerbach, ICRA 1996, research note §1) the set is
refused naming the parameters of the weakest direction and the motion to add,
or (``on_weak="drop"``) those robot parameters are dropped until it passes.
"""

from __future__ import annotations

import math
import time
from collections.abc import Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, Final

import numpy as np
from numpy.typing import ArrayLike, NDArray

from registration.arrays import F64
from registration.calibration.fit import (
    cross_validate,
    fit_parameters,
    fit_without_outliers,
    leave_one_out_errors_mm,
    per_pose_errors_mm,
    prior_weights_for,
)
from registration.calibration.model import (
    ErrorModel,
    Observations,
    initial_estimate,
    jacobian,
    minimal_parameter_set,
    normalised_svd,
    residuals_mm,
    stack_observations,
)
from registration.calibration.prediction import (
    estimate_unmodelled,
    farthest_split_inflation,
    posterior_covariance,
    working_prediction,
)
from registration.calibration.records import (
    DROP_CONDITION,
    MIN_POSES,
    CalibrationParams,
    CalibrationResult,
    MatchedPose,
    Parameter,
    UnmodelledEstimate,
    WorkingPrediction,
)
from registration.calibration.urdf import SerialChain
from registration.errors import NotIdentifiableError, OarmRegError, SessionMismatchError, TooFewPosesError
from registration.model.frames import as_transform

if TYPE_CHECKING:
    from registration.calibration.sampling import ScanVolume

I64 = NDArray[np.int64]

MIN_JOINT_SPREAD_DEG: Final = 5.0
"""A joint whose range over the session's poses is below this is named as not moving."""


# ---------------------------------------------------------------- parametrisation


# ---------------------------------------------------------------- closed-form start


# ---------------------------------------------------------------- checks and advice


def check_session(poses: Sequence[MatchedPose], min_poses: int = MIN_POSES) -> None:
    """Refuse fewer than ``min_poses`` scans or scans from several O-arm placements.

    Raises
    ------
    TooFewPosesError, SessionMismatchError
    """
    if len(poses) < min_poses:
        raise TooFewPosesError(
            f"calibration needs at least {min_poses} scans at different poses, got {len(poses)}; "
            "add scans that tilt the phantom by ±45° about two axes and turn the wrist"
        )
    groups: dict[str, list[str]] = {}
    for p in poses:
        groups.setdefault(p.frame_of_reference_uid, []).append(p.name)
    if len(groups) > 1:
        listing = "; ".join(f"FrameOfReferenceUID {u or '(none)'}: {', '.join(n)}" for u, n in groups.items())
        raise SessionMismatchError(
            "all scans of a calibration session must share one O-arm placement (one "
            f"FrameOfReferenceUID (0020,0052)); found {len(groups)}: {listing}. Rescan the odd ones "
            "without moving the O-arm, or run one calibration per placement"
        )


def _motion_advice(weak: Sequence[Parameter], joints_rad: F64, names: Sequence[str]) -> str:
    """Which motion to add: the joints that barely move, else the joints of the weakest direction."""
    spread_deg = np.degrees(np.ptp(joints_rad, axis=0))
    still = [n for n, s in zip(names, spread_deg, strict=True) if s < MIN_JOINT_SPREAD_DEG]
    moving = [n for n in names if n not in still]
    parts = []
    if still:
        if moving and len(moving) <= 2:
            parts.append(f"the poses differ only in {', '.join(moving)}")
        ranges = ", ".join(f"{n} ({s:.1f}°)" for n, s in zip(names, spread_deg, strict=True) if n in still)
        parts.append(f"joints that barely move across the poses: {ranges}")
        parts.append(f"add poses that move {', '.join(still)} by ±45° or more")
    weak_joints = sorted({p.group for p in weak if p.group in names} - set(still))
    if any(p.group in ("image_from_robot", "tool0_from_phantom") for p in weak) and not still:
        parts.append(
            "add poses that rotate the phantom about at least two non-parallel axes by ±45° and "
            "shift it within the scan volume"
        )
    if weak_joints:
        parts.append(f"add poses that move {', '.join(weak_joints)} (and its neighbours) over a wider range")
    return "; ".join(parts)


def _identifiability(
    jac: F64, params: Sequence[Parameter], rtol: float
) -> tuple[int, float, F64, list[Parameter], list[Parameter]]:
    """(rank, condition number, singular values, main parameters of the weakest direction, all
    parameters by decreasing weight in it)."""
    s, vt = normalised_svd(jac)
    rank = int(np.sum(s > rtol * s[0]))
    cond = float(s[0] / s[-1]) if s[-1] > 0 else float("inf")
    v = np.abs(vt[-1])
    order = np.argsort(-v)
    weak = [params[j] for j in order if v[j] >= 0.5 * v.max()]
    return rank, cond, s, weak, [params[j] for j in order]


def _select_parameters(
    model: ErrorModel, data: Observations, params: CalibrationParams, names: Sequence[str]
) -> tuple[ErrorModel, tuple[str, ...], int, float, F64]:
    """Check identifiability at the start; refuse or drop weak robot parameters."""
    dropped: list[str] = []
    limit = params.max_condition
    if limit is None and params.on_weak == "drop":
        limit = DROP_CONDITION
    while True:
        jac = jacobian(model, data, np.zeros(len(model.params)))
        rank, cond, s, weak, ranked = _identifiability(jac, model.params, params.rank_rtol)
        if limit is None or cond <= limit:
            return model, tuple(dropped), rank, cond, s
        robot_weak = [p for p in ranked if p.group in names]
        if params.on_weak == "drop" and robot_weak:
            dropped.append(robot_weak[0].name)
            model = ErrorModel(
                model.y0, model.x0, model.chain, tuple(p for p in model.params if p is not robot_weak[0])
            )
            continue
        raise NotIdentifiableError(
            f"the {len(data.joints_rad)} poses do not identify the requested '{params.parameter_set}' "
            f"set of {len(model.params)} parameters: numeric rank {rank}, condition number {cond:.3g} > "
            f"{limit:g} (--max-condition); weakest: {', '.join(p.name for p in weak[:4])}. "
            f"{_motion_advice(weak, data.joints_rad, names)}"
        )


# ---------------------------------------------------------------- fitting


def _fle_rms_mm(r: F64, n_params: int) -> float:
    """RMS detection error per sphere (3-D) implied by the fit residuals: Σr² / (m − P) × 3."""
    return math.sqrt(3.0 * float(r @ r) / max(len(r) - n_params, 1))


def registration_tre_rms_for_fle_mm(fle_rms_mm: float, centres_phantom_mm: F64) -> float:
    from registration.matching.quality import predicted_tre_mm

    tre = predicted_tre_mm(fle_rms_mm, centres_phantom_mm, centres_phantom_mm)
    return math.sqrt(float(np.mean(np.asarray(tre) ** 2)))


# ---------------------------------------------------------------- MAP: priors, cross-validation, posterior


def _prediction_refusal(
    pred: WorkingPrediction, params: CalibrationParams, joints_rad: F64, names: Sequence[str]
) -> str:
    weak = ", ".join(f"{n} ({100 * v:.0f} %)" for n, v in pred.weak_direction)
    poses = "; ".join(
        "[" + ", ".join(f"{math.degrees(v):.1f}" for v in q) + "]" for q in pred.exciting_joints_rad
    )
    return (
        f"predicted error over the working volume (scan volume + {params.working_margin_mm:g} mm) up to "
        + (
            f"{pred.max_mm:.3f} mm RMS at the worst pose (mean {pred.rms_mm:.3f} mm)"
            if math.isfinite(pred.max_mm)
            else "an unbounded figure at the worst pose (the poses leave a direction unconstrained)"
        )
        + " > the limit "
        f"{params.max_predicted_error_mm:g} mm; weak direction: {weak}. "
        + (f"Poses inside the scan volume that would excite it (joints in deg): {poses}. " if poses else "")
        + _motion_advice([], joints_rad, names)
    ).strip()


def calibrate(
    poses: Sequence[MatchedPose],
    chain: SerialChain,
    tool0_from_phantom: ArrayLike,
    centres_phantom_mm: ArrayLike,
    params: CalibrationParams = CalibrationParams(),
    scan_volume: ScanVolume | None = None,
) -> CalibrationResult:
    """Estimate ``image_from_robot``, ``tool0_from_phantom`` and joint-origin corrections.

    ``scan_volume``: the session's reconstructed cylinder (image frame); the working volume is it
    grown by ``params.working_margin_mm``.  None: the O-arm export's default cylinder
    (:class:`registration.calibration.sampling.ScanVolume`) centred on the centroid of the detections.

    Parameters
    ----------
    poses : sequence of MatchedPose, length K ≥ ``params.min_poses``
    chain : SerialChain
        The nominal arm (:func:`registration.calibration.urdf.read_chain`).
    tool0_from_phantom : array_like, shape (4, 4)
        Nominal rod (mm); only used to name the gauge — the fit starts from Shah's estimate.
    centres_phantom_mm : array_like, shape (N, 3)
        The phantom's sphere centres (CAD, mm), indexed by ``MatchedPose.sphere_indices``.
    params : CalibrationParams

    Returns
    -------
    CalibrationResult
        Calibrated chain (offsets folded into the origins), X, Y, parameters with standard
        errors, rank / condition number, per-pose and per-sphere residuals, outlier poses,
        leave-one-pose-out errors.

    Raises
    ------
    TooFewPosesError, SessionMismatchError, NotIdentifiableError, OutlierPoseError
    """
    t0 = time.perf_counter()
    as_transform(tool0_from_phantom, "tool0_from_phantom")
    check_session(poses, params.min_poses)
    pts = np.asarray(centres_phantom_mm, dtype=np.float64)
    data = stack_observations(poses, pts)
    model, dropped = _start_model(poses, chain, pts, data, params)
    timings = {"start_s": time.perf_counter() - t0}
    fit = _solve(model, data, poses, params, timings)
    jac = jacobian(fit.model, fit.data, fit.values)
    r = residuals_mm(fit.model, fit.data, fit.values)
    rank, cond, s, weak, _ = _identifiability(jac, fit.model.params, params.rank_rtol)
    _refuse_if_outliers_left_it_weak(poses, fit, cond, weak, params, chain.joint_names)
    pred = _predict(fit, r, pts, params, scan_volume, timings)
    if not pred.prediction.max_mm <= params.max_predicted_error_mm:  # NaN (unbounded) refuses too
        raise NotIdentifiableError(
            _prediction_refusal(pred.prediction, params, fit.data.joints_rad, chain.joint_names)
        )
    t2 = time.perf_counter()
    nan = np.full(len(poses), np.nan)
    lopo, lopo_rms = (
        leave_one_out_errors_mm(fit.model, data, fit.values, fit.used, params)
        if params.leave_one_out
        else (nan, nan)
    )
    timings["leave_one_out_s"] = time.perf_counter() - t2
    y, x, cal_chain = fit.model.unpack(fit.values)
    return CalibrationResult(
        image_from_robot=y,
        tool0_from_phantom=x,
        chain=cal_chain,
        parameters=fit.model.params,
        values=fit.values,
        std_errors=np.sqrt(np.clip(np.diag(pred.cov), 0.0, None)),
        rank=rank,
        condition_number=cond,
        singular_values=s,
        dropped=dropped,
        pose_names=tuple(p.name for p in poses),
        used=fit.used,
        pose_rms_mm=fit.rms,
        pose_max_mm=fit.mx,
        sphere_residuals_mm=tuple(fit.per),
        sphere_indices=tuple(np.asarray(p.sphere_indices, dtype=np.int64) for p in poses),
        outliers=tuple(poses[int(i)].name for i in np.flatnonzero(~fit.used)),
        lopo_pose_mean_mm=lopo,
        lopo_pose_rms_mm=lopo_rms,
        timings_s=timings,
        fit_rms_mm=float(np.sqrt(np.mean(r**2) * 3.0)),
        fle_rms_mm=pred.fle,
        registration_tre_rms_mm=pred.reg_tre,
        estimator=params.estimator,
        prior_scale=fit.scale,
        cv_scores=fit.cv,
        posterior_cov=pred.cov,
        unmodelled_rms_mm=pred.unmodelled.rms_mm,
        unmodelled=pred.unmodelled,
        prediction=pred.prediction,
        working_volume=pred.volume_doc,
        target_rms_mm=params.target_rms_mm,
    )


def _start_model(
    poses: Sequence[MatchedPose], chain: SerialChain, pts: F64, data: Observations, params: CalibrationParams
) -> tuple[ErrorModel, tuple[str, ...]]:
    """Shah's closed-form start, the identifiable parameter set and the priors at scale 1."""
    y0, x0 = initial_estimate(poses, chain, pts)
    # MAP puts its priors on the physical joint-origin errors (6 per joint, "all"): on the minimal set
    # the priors would sit on combinations that absorb the redundant errors (misspecified: 1.5 × the
    # LS error on the tuning seeds, measured), so "full" means "all" for the MAP estimator.
    pset = "all" if params.estimator == "map" and params.parameter_set == "full" else params.parameter_set
    model = ErrorModel(y0, x0, chain, minimal_parameter_set(chain, pset))
    model, dropped, _, _, _ = _select_parameters(model, data, params, chain.joint_names)
    return model.with_prior(prior_weights_for(model, params, 1.0)), dropped


@dataclass(frozen=True)
class _Solved:
    """The robust fit without its outlier poses, at the chosen prior scale."""

    model: ErrorModel
    values: F64
    used: NDArray[np.bool_]
    data: Observations
    """The poses kept (``used``)."""
    rms: F64
    mx: F64
    per: list[F64]
    scale: float
    cv: dict[float, float] | None


def _solve(
    model: ErrorModel,
    data: Observations,
    poses: Sequence[MatchedPose],
    params: CalibrationParams,
    timings: dict[str, float],
) -> _Solved:
    """Fit, drop outlier poses, then (MAP) refit at the given or cross-validated prior scale."""
    t1 = time.perf_counter()
    values, used, (rms, mx, per) = fit_without_outliers(model, data, poses, params)
    fit_data = data.subset(used)
    scale, cv = (float("nan"), None) if params.estimator == "ls" else (float(params.prior_scales[0]), None)
    if params.estimator == "map" and len(params.prior_scales) == 1:
        model = model.with_prior(prior_weights_for(model, params, scale))
        values = fit_parameters(model, fit_data, values, params)
        rms, mx, per = per_pose_errors_mm(model, data, values, len(poses))
    if params.estimator == "map" and len(params.prior_scales) > 1:
        t_cv = time.perf_counter()
        scale, cv = cross_validate(model, fit_data, values, params)
        timings["cross_validation_s"] = time.perf_counter() - t_cv
        model = model.with_prior(prior_weights_for(model, params, scale))
        values = fit_parameters(model, fit_data, values, params)
        rms, mx, per = per_pose_errors_mm(model, data, values, len(poses))
    timings["solve_s"] = time.perf_counter() - t1
    return _Solved(model, values, used, fit_data, rms, mx, per, scale, cv)


def _refuse_if_outliers_left_it_weak(
    poses: Sequence[MatchedPose],
    fit: _Solved,
    cond: float,
    weak: Sequence[Parameter],
    params: CalibrationParams,
    joint_names: Sequence[str],
) -> None:
    """NotIdentifiableError when dropping the outlier poses left the parameters unidentified."""
    limit = params.max_condition if params.max_condition is not None else math.inf
    if not fit.used.all() and cond > limit and params.on_weak == "refuse":
        excluded = ", ".join(p.name for p, u in zip(poses, fit.used, strict=True) if not u)
        advice = _motion_advice(weak, fit.data.joints_rad, joint_names)
        raise NotIdentifiableError(
            f"without the outlier scans {excluded} the remaining poses no longer identify the parameters "
            f"(condition number {cond:.3g} > {limit:g}); rescan them. {advice}"
        )


@dataclass(frozen=True)
class _Predicted:
    """The error figures of the fit and the error to expect over the working volume."""

    fle: float
    reg_tre: float
    unmodelled: UnmodelledEstimate
    cov: F64
    prediction: WorkingPrediction
    volume_doc: dict[str, Any]


def _predict(
    fit: _Solved,
    r: F64,
    pts: F64,
    params: CalibrationParams,
    scan_volume: ScanVolume | None,
    timings: dict[str, float],
) -> _Predicted:
    """FLE, the unmodelled error, the posterior covariance and the working-volume prediction."""
    fle = _fle_rms_mm(r, len(fit.model.params))
    reg_tre = registration_tre_rms_for_fle_mm(fle, pts)
    unmodelled = estimate_unmodelled(fit.model, fit.data, fit.values, fle, params)
    unmod = unmodelled.rms_mm
    # the per-pose error the prediction adds at every working pose was there at the calibration poses
    # too, and the fit absorbed it into the parameters: the sandwich takes the same figure
    cov = posterior_covariance(
        fit.model,
        fit.data,
        fit.values,
        params,
        fit.scale,
        pose_shared_rms_mm=max(unmod, params.repeatability_rms_mm),
    )
    t_p = time.perf_counter()
    inflation, split = (
        farthest_split_inflation(fit.model, fit.data, fit.values, params, fle, unmod)
        if params.farthest_split
        else (1.0, ())
    )
    prediction, volume_doc = working_prediction(
        fit.model,
        fit.values,
        cov * inflation,
        fit.data,
        pts,
        params,
        scan_volume,
        unmod * math.sqrt(inflation),
        fle,
    )
    volume_doc["farthest_split"] = {"poses": [int(i) for i in split], "variance_inflation": inflation}
    timings["prediction_s"] = time.perf_counter() - t_p
    return _Predicted(fle, reg_tre, unmodelled, cov, prediction, volume_doc)


def match_pose(
    name: str,
    joints_rad: ArrayLike,
    centres_image_mm: ArrayLike,
    robot_mm: ArrayLike,
    *,
    phantom: Any = None,
    series_uid: str = "",
    frame_of_reference_uid: str = "",
) -> MatchedPose:
    """Match one scan's detections to the phantom's spheres with the click-free registration.

    ``robot_mm`` are the sphere centres by the *nominal* model and rod (their 1-mm error is far
    inside the registration's gates).  Errors of :func:`registration.matching.register.register_points`
    are re-raised with the scan name.
    """
    from registration.matching.register import register_points

    try:
        reg = register_points(robot_mm, centres_image_mm, phantom=phantom)
    except OarmRegError as e:
        raise type(e)(f"calibration scan {name}: {e}") from None
    img = np.asarray(centres_image_mm, dtype=np.float64)
    return MatchedPose(
        name=name,
        joints_rad=np.asarray(joints_rad, dtype=np.float64).reshape(-1),
        sphere_indices=reg.robot_indices.astype(np.int64),
        centres_image_mm=img[reg.image_indices],
        series_uid=series_uid,
        frame_of_reference_uid=frame_of_reference_uid,
    )
