"""Plan the poses of a calibration session from one registration.

Given ``image_from_robot`` of the current O-arm placement, the arm, the rod and
the phantom, propose joint configurations — as many as the calibration needs to meet a target
error over the working volume (``PlannerParams.target_rms_mm``, predicted exactly as the
calibration will predict it), or a forced count — that

* keep every sphere centre at least ``margin_mm`` inside the scan volume
  (a cylinder: the FOV disk × the axial coverage),
* spread the phantom's orientation as widely as the volume and the joint
  limits allow (tilts of its z axis up to ``max_tilt_deg`` about any
  horizontal axis, any yaw about its own z, i.e. the wrist),
* stay ``joint_margin_rad`` inside every joint limit,
* are ordered for short moves (nearest neighbour in the largest joint step,
  starting from the registration's joints),

and report the condition number of the identification Jacobian the chosen
set is predicted to give (:mod:`registration.calibration.solver`, same parameter set
and normalisation).  Candidates are solved by damped Newton IK from the
registration's joints and their wrist-flipped twin (damped least squares on the quaternion log
map, :mod:`registration.calibration.sampling`); the set is chosen greedily for the largest
log-determinant of the normalised information matrix (D-optimal design), the count is the
shortest prefix of that order meeting the target, then (≤ 15 poses) poses are swapped while that
lowers the condition number without raising the predicted error.  Collisions of the
arm with the O-arm gantry are not modelled: check the plan before running it.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, Final

import numpy as np
from numpy.typing import ArrayLike, NDArray

from registration.arrays import F64
from registration.calibration.model import (
    ErrorModel,
    Observations,
    jacobian,
    minimal_parameter_set,
)
from registration.calibration.sampling import (
    IK_ROTATION_WEIGHT_MM,
    IK_TOL_MM,
    ScanVolume,
    predicted_centres_image_mm,
    sample_poses_in_volume,
    solve_ik,
    wrist_flip,
)
from registration.calibration.targets import MAX_PLANNED_POSES, TARGET_RMS_MM
from registration.calibration.urdf import SerialChain, rotation_about
from registration.errors import PlanningError
from registration.model.frames import as_transform, invert, make_transform

__all__ = [
    "IK_ROTATION_WEIGHT_MM",
    "IK_TOL_MM",
    "PlannerParams",
    "PlanningError",
    "PosePlan",
    "ScanVolume",
    "plan_poses",
    "predict_plan",
    "predicted_centres_image_mm",
    "sample_poses_in_volume",
    "solve_ik",
]


DEFAULT_TARGET_RMS_MM: Final = TARGET_RMS_MM
DEFAULT_MAX_POSES: Final = MAX_PLANNED_POSES
MIN_PLANNED_POSES: Final = 10
"""Fewest poses the planner proposes on its own: below this the prediction rests on too few
poses to see the unmodelled error (docs/calibration.md); ``n_poses`` may force down to 6."""


@dataclass(frozen=True)
class PlannerParams:
    n_poses: int | None = None
    """Forced pose count (``--n``); None: the fewest (≥ :data:`MIN_PLANNED_POSES`) whose predicted RMS
    over the working volume meets ``target_rms_mm``, at most ``max_poses``."""
    target_rms_mm: float = DEFAULT_TARGET_RMS_MM
    max_poses: int = DEFAULT_MAX_POSES
    margin_mm: float = 5.0
    """Every sphere ≥ 5 mm inside the scan volume and FOV (a sphere cut by the FOV edge is refused)."""
    model_error_mm: float = 2.0
    """Added to ``margin_mm``: how far a sphere may really be from where the planning model puts it
    (relative to the registration pose).  An unseen TX60 cell (docs/calibration.md): nominal
    held-out error 1.03 mm mean, 1.84 mm max; 2 mm covers the max.  Plan with a calibration
    (``--calibration``) to use a smaller value (its ``predicted_chain_error_mm``)."""
    max_predicted_error_mm: float = 0.5
    """The calibration's refusal limit (``CalibrationParams.max_predicted_error_mm``): the plan says
    what it would need when its predicted error exceeds it."""
    fle_rms_mm: float = 0.07
    """Detection error assumed for the plan's predicted error (the simulator's DICOM session)."""
    joint_margin_deg: float = 5.0
    """Distance kept from every joint limit."""
    tilts_deg: tuple[float, ...] = (0.0, 25.0, 45.0, 60.0, 75.0)
    """Candidate tilts of the phantom's z axis from its registration orientation (issue: ±45° or more)."""
    tilt_azimuths: int = 8
    """Tilt axes per tilt, evenly spread in the plane ⟂ to the phantom's z."""
    yaws_deg: tuple[float, ...] = (0.0, 90.0, 180.0, 270.0)
    """Yaws about the phantom's own z (the wrist)."""
    shift_mm: float = 30.0
    """Candidates are also displaced by ± this along each image axis (cyclically over the
    orientations): at one fixed phantom position link lengths, rod length and the O-arm's
    translation are not separable (an exact null direction of the identification Jacobian)."""
    parameter_set: str = "full"


@dataclass(frozen=True, eq=False)
class PosePlan:
    """Planned joints (K, n) rad in move order, and what the plan promises."""

    joints_rad: F64
    predicted_condition_number: float
    tilt_deg: F64
    inside_margin_mm: F64
    max_joint_step_rad: F64
    n_candidates: int
    predicted_error_mm: float = float("nan")
    """Predicted RMS error at the worst pose of the working volume after calibrating with these
    poses (posterior with the priors, FLE ``PlannerParams.fle_rms_mm``)."""
    advice: str = ""
    """Empty when ``predicted_error_mm`` is within the limit; else what the plan would need."""
    predicted_rms_mm: float = float("nan")
    """Predicted RMS error over the working volume (what held-out poses measure), mm."""
    target_rms_mm: float = float("nan")
    count_reason: str = ""
    """Why this many poses: ``"target"`` (the fewest meeting ``target_rms_mm``), ``"max_poses"``
    (the target not met within the maximum), ``"candidates"`` (not met, fewer feasible poses than
    the maximum) or ``"forced"`` (``n_poses`` given)."""
    shorter: tuple[tuple[int, float, float], ...] = ()
    """(K, predicted RMS mm, worst pose mm) of a few shorter plans (the first K poses of the same
    D-optimal order), fewest first: what scanning fewer poses would cost."""

    @property
    def target_met(self) -> bool:
        return bool(self.predicted_rms_mm <= self.target_rms_mm)

    def to_dict(self) -> dict[str, Any]:
        return {
            "predicted_condition_number": self.predicted_condition_number,
            "predicted_error_mm": self.predicted_error_mm,
            "predicted_rms_mm": self.predicted_rms_mm,
            "target_rms_mm": self.target_rms_mm,
            "target_met": self.target_met,
            "n_poses": len(self.joints_rad),
            "count_reason": self.count_reason,
            "advice": self.advice,
            "n_candidates": self.n_candidates,
            "shorter_plans": [
                {"n_poses": k, "predicted_rms_mm": rms, "predicted_error_mm": worst}
                for k, rms, worst in self.shorter
            ],
            "poses": [
                {
                    "joints_rad": [float(v) for v in q],
                    "tilt_deg": float(t),
                    "inside_margin_mm": float(m),
                    "max_joint_step_from_previous_rad": float(s),
                }
                for q, t, m, s in zip(
                    self.joints_rad,
                    self.tilt_deg,
                    self.inside_margin_mm,
                    self.max_joint_step_rad,
                    strict=True,
                )
            ],
        }


def _candidate_targets(image_from_phantom_0: F64, volume: ScanVolume, p: PlannerParams) -> tuple[F64, F64]:
    """Candidate image_from_phantom (C, 4, 4) centred in the volume, and their tilts (C,) deg."""
    r0 = image_from_phantom_0[:3, :3]
    shifts = np.vstack([np.zeros(3), p.shift_mm * np.eye(3), -p.shift_mm * np.eye(3)])
    centre = np.asarray(volume.centre_image_mm)
    out: list[F64] = []
    tilts: list[float] = []
    for tilt in p.tilts_deg:
        azimuths = (
            [0.0] if tilt == 0.0 else [2 * math.pi * k / p.tilt_azimuths for k in range(p.tilt_azimuths)]
        )
        for az in azimuths:
            axis_ph = np.array([math.cos(az), math.sin(az), 0.0])
            r_tilt = rotation_about(axis_ph, np.array([math.radians(tilt)]))[0]
            for yaw in p.yaws_deg:
                r_yaw = rotation_about(np.array([0.0, 0.0, 1.0]), np.array([math.radians(yaw)]))[0]
                out.append(make_transform(r0 @ r_tilt @ r_yaw, centre + shifts[len(out) % len(shifts)]))
                tilts.append(tilt)
    return np.stack(out), np.array(tilts)


def condition_number(information: F64) -> float:
    """Condition number of the column-normalised Jacobian from its information matrix JᵀJ."""
    d = np.sqrt(np.diag(information))
    d[d == 0.0] = 1.0
    lam = np.linalg.eigvalsh(information / np.outer(d, d))
    return float(math.sqrt(lam[-1] / lam[0])) if lam[0] > 0 else float("inf")


def _greedy_d_optimal(info: F64, k: int, first: int) -> list[int]:
    chosen = [first]
    total = info[first].copy()
    scale = np.sqrt(np.diag(info.sum(axis=0)))
    scale[scale == 0.0] = 1.0
    ridge = 1e-6 * np.eye(info.shape[1])
    while len(chosen) < k:
        best, best_val = -1, -np.inf
        for c in range(len(info)):
            if c in chosen:
                continue
            m = (total + info[c]) / np.outer(scale, scale) + ridge
            val = float(np.linalg.slogdet(m)[1])
            if val > best_val:
                best, best_val = c, val
        chosen.append(best)
        total = total + info[best]
    return chosen


def _swap_for_condition(info: F64, chosen: list[int], passes: int = 2) -> list[int]:
    """Replace chosen poses (except the first) by candidates while that lowers the condition number."""
    best = condition_number(info[chosen].sum(axis=0))
    for _ in range(passes):
        improved = False
        for slot in range(1, len(chosen)):
            base = info[chosen].sum(axis=0) - info[chosen[slot]]
            for c in range(len(info)):
                if c in chosen:
                    continue
                val = condition_number(base + info[c])
                if val < best:
                    best, chosen[slot], improved = val, c, True
                    base = info[chosen].sum(axis=0) - info[chosen[slot]]
        if not improved:
            break
    return chosen


def _order_short_moves(q: F64, start: F64) -> tuple[F64, F64]:
    left = list(range(len(q)))
    cur, order, steps = start, [], []
    while left:
        d = [float(np.max(np.abs(q[i] - cur))) for i in left]
        j = left.pop(int(np.argmin(d)))
        order.append(j)
        steps.append(min(d))
        cur = q[j]
    return q[order], np.array(steps)


def feasible_poses(
    image_from_robot: ArrayLike,
    chain: SerialChain,
    tool0_from_phantom: ArrayLike,
    centres_phantom_mm: ArrayLike,
    start_joints_rad: ArrayLike,
    *,
    volume: ScanVolume = ScanVolume(),
    params: PlannerParams = PlannerParams(),
) -> tuple[F64, F64, F64]:
    """Every distinct candidate pose that passes IK, joint limits and the volume margin.

    Returns
    -------
    joints_rad : ndarray, shape (C, n)
    tilt_deg : ndarray, shape (C,)
    inside_margin_mm : ndarray, shape (C,)
        Smallest distance of a sphere centre to the volume boundary.
    """
    q, tilts, inside, _ = _feasible(
        image_from_robot, chain, tool0_from_phantom, centres_phantom_mm, start_joints_rad, volume, params
    )
    return q, tilts, inside


def _feasible(
    image_from_robot: ArrayLike,
    chain: SerialChain,
    tool0_from_phantom: ArrayLike,
    centres_phantom_mm: ArrayLike,
    start_joints_rad: ArrayLike,
    volume: ScanVolume,
    params: PlannerParams,
) -> tuple[F64, F64, F64, str]:
    """:func:`feasible_poses` and why the other candidates were dropped (for a refusal)."""
    y = as_transform(image_from_robot, "image_from_robot")
    x = as_transform(tool0_from_phantom, "tool0_from_phantom")
    pts = np.asarray(centres_phantom_mm, dtype=np.float64)
    q0 = np.asarray(start_joints_rad, dtype=np.float64).reshape(-1)
    targets_img, tilts = _candidate_targets(y @ chain.robot_from_tool0(q0) @ x, volume, params)
    targets = invert(y) @ targets_img @ invert(x)
    seeds = np.concatenate(
        [np.repeat(q0[None], len(targets), 0), np.repeat(wrist_flip(q0)[None], len(targets), 0)]
    )
    q, err = solve_ik(chain, np.concatenate([targets, targets]), seeds)
    tilts = np.concatenate([tilts, tilts])
    margin = math.radians(params.joint_margin_deg)
    reached = err < IK_TOL_MM
    in_limits = np.all((q >= chain.lower_rad + margin) & (q <= chain.upper_rad - margin), axis=1)
    fk = y @ chain.robot_from_tool0_batch(q) @ x
    inside = volume.inside_margin_mm(np.einsum("cij,nj->cni", fk[:, :3, :3], pts) + fk[:, None, :3, 3])
    in_volume = inside >= params.margin_mm + params.model_error_mm
    ok = reached & in_limits & in_volume
    n_far = int((~reached).sum())
    n_limit = int((reached & ~in_limits).sum())
    n_out = int((reached & in_limits & ~in_volume).sum())
    centre = tuple(round(v, 1) for v in volume.centre_image_mm)
    why = (
        f"of {len(q)} candidate solutions (tilts up to {max(params.tilts_deg):g}°, shifts "
        f"±{params.shift_mm:g} mm about the volume centre {centre} mm), {n_far} are out of the arm's "
        f"reach, {n_limit} come within {params.joint_margin_deg:g}° of a joint limit and {n_out} put a "
        f"sphere less than {params.margin_mm + params.model_error_mm:g} mm inside the scan volume"
    )
    idx = _unique(q, np.flatnonzero(ok))
    return q[idx], tilts[idx], inside[idx], why


@dataclass(frozen=True, eq=False)
class _PlanPredictor:
    """The calibration's own prediction (:mod:`registration.calibration.prediction`) for a pose set
    before it is scanned: the same parameters, prior weight (:class:`CalibrationParams` defaults: no
    prior for ``"ls"``), sandwich for the per-pose unmodelled error and additive terms (the
    registration's TRE at each working pose's spheres), on noise-free planning data with the
    detection error ``fle_rms_mm``, over the working volume's poses sampled once.  Before any scan
    the unmodelled error is the prior ``unmodelled_floor_mm``; the calibration replaces it by what
    its poses' held-out residuals show (``CalibrationParams.unmodelled_source``)."""

    jeff: F64  # (W, 3N, P) effective Jacobians at the working poses
    prior: F64
    s2: float
    unmodelled_mm: float
    registration_tre_ms: F64  # (W,) mean squared registration TRE at each working pose's spheres

    @classmethod
    def build(
        cls, model: ErrorModel, pts: F64, q_reg: F64, volume: ScanVolume, params: PlannerParams
    ) -> _PlanPredictor:
        from registration.calibration.prediction import (
            LS_PRIOR_WEIGHT,
            WORKING_POSES,
            WORKING_SEED,
            effective_jacobians,
            registration_tre_ms,
        )
        from registration.calibration.records import PRIORS, CalibrationParams

        cp = CalibrationParams()
        y, x, chain = model.unpack(np.zeros(len(model.params)))
        wq = sample_poses_in_volume(
            y,
            chain,
            x,
            pts,
            q_reg,
            volume.grown(cp.working_margin_mm),
            np.random.default_rng(WORKING_SEED),
            n=WORKING_POSES,
            max_tilt_deg=75.0,
            margin_mm=0.0,
            n_candidates=300,
        )
        if not len(wq):
            wq = q_reg[None]
        prior = 1.0 / np.array([PRIORS.sigma_posterior(p) for p in model.params]) ** 2
        if cp.estimator == "ls":
            prior = prior * LS_PRIOR_WEIGHT
        return cls(
            effective_jacobians(model, np.zeros(len(model.params)), wq, q_reg, pts),
            prior,
            params.fle_rms_mm**2 / 3.0,
            max(cp.unmodelled_floor_mm, cp.repeatability_rms_mm),
            registration_tre_ms(model, np.zeros(len(model.params)), wq, q_reg, pts, params.fle_rms_mm),
        )

    def predict(self, info: F64, shared_info: F64) -> tuple[float, float]:
        """(RMS over the working poses, worst pose's RMS) mm, from Σ JᵢᵀJᵢ and Σ SᵢᵀSᵢ of a set."""
        from registration.calibration.prediction import sandwich_from_sums

        cov = sandwich_from_sums(info, shared_info, self.s2, self.prior, self.unmodelled_mm)
        n = self.jeff.shape[1] // 3
        chain_ms = np.einsum("wip,pq,wiq->w", self.jeff, cov, self.jeff) / n
        chain_ms = np.where(chain_ms < 0.0, np.inf, chain_ms)
        per = np.sqrt(chain_ms + 2.0 * self.unmodelled_mm**2 + self.registration_tre_ms)
        return float(np.sqrt(np.mean(per**2))), float(per.max())


def _pose_jacobians(model: ErrorModel, pts: F64, q: F64) -> F64:
    """(C, 3N, P) sphere Jacobians of each pose at the nominal parameters."""
    n = len(pts)
    data = Observations(
        q, np.tile(pts, (len(q), 1)), np.zeros((len(q) * n, 3)), np.repeat(np.arange(len(q)), n)
    )
    jac = jacobian(model, data, np.zeros(len(model.params)))
    return np.asarray(jac.reshape(len(q), 3 * n, len(model.params)), dtype=np.float64)


def _set_sums(jac: F64) -> tuple[F64, F64]:
    """Per pose (C, P, P): JᵢᵀJᵢ and SᵢᵀSᵢ, Sᵢ the (3, P) sum of its sphere Jacobians."""
    s = jac.reshape(len(jac), -1, 3, jac.shape[2]).sum(axis=1)
    return np.einsum("cij,cik->cjk", jac, jac), np.einsum("cip,ciq->cpq", s, s)


def _refuse_too_few(n_feasible: int, need: int, why: str) -> PlanningError:
    return PlanningError(
        f"only {n_feasible} distinct feasible calibration poses found (need {need}): {why}. "
        "Centre the O-arm's volume on the phantom (or the phantom in it), start from a pose further "
        "from the joint limits, or ask for fewer poses (--n)"
    )


def plan_poses(
    image_from_robot: ArrayLike,
    chain: SerialChain,
    tool0_from_phantom: ArrayLike,
    centres_phantom_mm: ArrayLike,
    start_joints_rad: ArrayLike,
    *,
    volume: ScanVolume = ScanVolume(),
    params: PlannerParams = PlannerParams(),
) -> PosePlan:
    """Propose calibration poses (see the module docstring): ``params.n_poses`` of them, or without
    it the fewest (from :data:`MIN_PLANNED_POSES`, in the D-optimal greedy order) whose predicted RMS
    over the working volume meets ``params.target_rms_mm``, at most ``params.max_poses``.

    Raises
    ------
    PlanningError
        Fewer feasible candidates than the poses needed (the phantom cannot be placed in the
        volume at enough orientations from here: the message counts why and says what to change).
    """
    y = as_transform(image_from_robot, "image_from_robot")
    x = as_transform(tool0_from_phantom, "tool0_from_phantom")
    pts = np.asarray(centres_phantom_mm, dtype=np.float64)
    q0 = np.asarray(start_joints_rad, dtype=np.float64).reshape(-1)
    if not (np.all(np.isfinite(y)) and np.all(np.isfinite(q0)) and np.all(np.isfinite(x))):
        raise PlanningError(
            "the registration, the start joints or the rod hold a non-finite number: re-register the scan"
        )
    q, tilts, inside, why = _feasible(y, chain, x, pts, q0, volume, params)
    forced = params.n_poses is not None
    least = int(params.n_poses) if params.n_poses is not None else MIN_PLANNED_POSES
    if len(q) < least:
        raise _refuse_too_few(len(q), least, why)
    model = ErrorModel(y, x, chain, minimal_parameter_set(chain, params.parameter_set))
    jac = _pose_jacobians(model, pts, q)
    info, shared = _set_sums(jac)
    predictor = _PlanPredictor.build(model, pts, q0, volume, params)
    first = int(np.argmin(np.max(np.abs(q - q0), axis=1)))
    most = least if forced else min(params.max_poses, len(q))
    order = _greedy_d_optimal(info, max(most, least), first)
    k, reason = least, "forced"
    if not forced:
        reason = "candidates" if len(q) < params.max_poses else "max_poses"
        k = most
        for kk in range(least, most + 1):
            sel_k = order[:kk]
            if predictor.predict(info[sel_k].sum(0), shared[sel_k].sum(0))[0] <= params.target_rms_mm:
                k, reason = kk, "target"
                break
    chosen = order[:k]
    if k <= SWAP_MAX_POSES:
        swapped = _swap_for_condition(info, list(chosen))
        if (
            predictor.predict(info[swapped].sum(0), shared[swapped].sum(0))[0]
            <= predictor.predict(info[chosen].sum(0), shared[chosen].sum(0))[0]
        ):
            chosen = swapped
    sel = np.array(chosen)
    cond = condition_number(info[sel].sum(axis=0))
    ordered, steps = _order_short_moves(q[sel], q0)
    move = [int(np.flatnonzero(np.all(q[sel] == row, axis=1))[0]) for row in ordered]
    rms, worst = predictor.predict(info[sel].sum(0), shared[sel].sum(0))
    advice = _plan_advice(k, reason, rms, worst, params, len(q))
    shorter = tuple(
        (kk, *predictor.predict(info[order[:kk]].sum(0), shared[order[:kk]].sum(0)))
        for kk in shorter_counts(k)
    )
    return PosePlan(
        ordered,
        cond,
        tilts[sel][move],
        inside[sel][move],
        steps,
        len(q),
        worst,
        advice,
        rms,
        params.target_rms_mm,
        reason,
        shorter,
    )


def shorter_counts(k: int, most: int = 4) -> list[int]:
    """Up to ``most`` pose counts below ``k`` worth showing: 6 (the least a calibration takes), 10
    (the planner's least), ``k`` − 5 and ``k`` − 2."""
    counts = sorted(c for c in {6, MIN_PLANNED_POSES, k - 5, k - 2} if 6 <= c < k)
    return counts if len(counts) <= most else [counts[0], *counts[len(counts) - most + 1 :]]


SWAP_MAX_POSES: Final = 15
"""Above this many poses the condition-number swaps are skipped (their cost grows as K × candidates
and the greedy D-optimal set is already well conditioned there)."""


def _plan_advice(
    k: int, reason: str, rms: float, worst: float, params: PlannerParams, n_feasible: int
) -> str:
    parts = []
    if rms > params.target_rms_mm:
        if reason == "forced":
            parts.append(
                f"the {k} poses are predicted to leave {rms:.3f} mm RMS over the working volume, above the "
                f"target {params.target_rms_mm:g} mm: plan without --n to let the planner choose the count"
            )
        else:
            limit = (
                f"the maximum of {params.max_poses} poses"
                if reason == "max_poses"
                else f"all {n_feasible} feasible poses"
            )
            parts.append(
                f"the target {params.target_rms_mm:g} mm RMS over the working volume is not met with {limit} "
                f"(predicted {rms:.3f} mm): calibrate from a second O-arm placement, allow wider tilts, or "
                "raise calibration.max_poses"
            )
    if worst > params.max_predicted_error_mm:
        parts.append(
            f"the worst pose of the working volume is predicted at {worst:.2f} mm, above the calibration's "
            f"refusal limit {params.max_predicted_error_mm:g} mm: the calibration would be refused"
        )
    return "; ".join(parts)


def predict_plan(
    image_from_robot: ArrayLike,
    chain: SerialChain,
    tool0_from_phantom: ArrayLike,
    centres_phantom_mm: ArrayLike,
    joints_rad: ArrayLike,
    *,
    volume: ScanVolume = ScanVolume(),
    params: PlannerParams = PlannerParams(),
    registration_joints_rad: ArrayLike | None = None,
) -> tuple[float, float]:
    """(RMS over the working volume, worst pose) mm predicted for calibrating from ``joints_rad``
    (K, n) — a plan made earlier, by another planner or by hand — exactly as :func:`plan_poses`
    predicts its own."""
    y = as_transform(image_from_robot, "image_from_robot")
    x = as_transform(tool0_from_phantom, "tool0_from_phantom")
    pts = np.asarray(centres_phantom_mm, dtype=np.float64)
    q = np.asarray(joints_rad, dtype=np.float64).reshape(-1, chain.n_joints)
    q_reg = q[0] if registration_joints_rad is None else np.asarray(registration_joints_rad, dtype=np.float64)
    model = ErrorModel(y, x, chain, minimal_parameter_set(chain, params.parameter_set))
    info, shared = _set_sums(_pose_jacobians(model, pts, q))
    return _PlanPredictor.build(model, pts, q_reg.reshape(-1), volume, params).predict(
        info.sum(0), shared.sum(0)
    )


def predicted_plan_error_mm(
    y: F64, chain: SerialChain, x: F64, pts: F64, joints_rad: F64, volume: ScanVolume, params: PlannerParams
) -> float:
    """Worst-pose predicted error over the working volume of a calibration from ``joints_rad``."""
    return predict_plan(y, chain, x, pts, joints_rad, volume=volume, params=params)[1]


def _unique(q: F64, idx: NDArray[np.intp]) -> NDArray[np.intp]:
    """Drop candidates within 1° (every joint) of an earlier one."""
    keep: list[int] = []
    for i in idx:
        if all(float(np.max(np.abs(q[i] - q[j]))) > math.radians(1.0) for j in keep):
            keep.append(int(i))
    return np.array(keep, dtype=np.intp)
