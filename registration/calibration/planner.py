"""Plan the poses of a calibration session from one registration.

Given ``image_from_robot`` of the current O-arm placement, the arm, the rod and
the phantom, propose K joint configurations that

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
registration's joints and their wrist-flipped twin; the set is chosen greedily
for the largest log-determinant of the normalised information matrix
(D-optimal design), then poses are swapped while that lowers the condition
number.  Collisions of the
arm with the O-arm gantry are not modelled: check the plan before running it.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from registration.calibration.model import (
    _Data,
    _jacobian,
    _Model,
    minimal_parameter_set,
)
from registration.calibration.sampling import (
    IK_ROTATION_WEIGHT_MM,
    IK_TOL_MM,
    ScanVolume,
    _wrist_flip,
    predicted_centres_image_mm,
    sample_poses_in_volume,
    solve_ik,
)
from registration.calibration.urdf import SerialChain, rotation_about
from registration.errors import RegistrationError
from registration.model.frames import as_transform, invert, make_transform

__all__ = [
    "IK_ROTATION_WEIGHT_MM",
    "IK_TOL_MM",
    "PlannerParams",
    "PlanningError",
    "PosePlan",
    "ScanVolume",
    "plan_poses",
    "predicted_centres_image_mm",
    "sample_poses_in_volume",
    "solve_ik",
]

F64 = NDArray[np.float64]


class PlanningError(RegistrationError):
    title = "Cannot plan calibration poses"


@dataclass(frozen=True)
class PlannerParams:
    n_poses: int = 10
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

    def to_dict(self) -> dict[str, Any]:
        return {
            "predicted_condition_number": self.predicted_condition_number,
            "predicted_error_mm": self.predicted_error_mm,
            "advice": self.advice,
            "n_candidates": self.n_candidates,
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


def _information(chain: SerialChain, y: F64, x: F64, pts: F64, q: F64, parameter_set: str) -> F64:
    """(C, P, P) information matrices JᵀJ of each candidate pose."""
    params = minimal_parameter_set(chain, parameter_set)
    model = _Model(y, x, chain, params)
    n_pts = len(pts)
    data = _Data(
        q, np.tile(pts, (len(q), 1)), np.zeros((len(q) * n_pts, 3)), np.repeat(np.arange(len(q)), n_pts)
    )
    jac = _jacobian(model, data, np.zeros(len(params))).reshape(len(q), n_pts * 3, len(params))
    return np.asarray(np.einsum("cij,cik->cjk", jac, jac), dtype=np.float64)


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
        [np.repeat(q0[None], len(targets), 0), np.repeat(_wrist_flip(q0)[None], len(targets), 0)]
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
    """Propose ``params.n_poses`` calibration poses (see the module docstring).

    Raises
    ------
    PlanningError
        Fewer feasible candidates than poses requested (the phantom cannot be placed in the
        volume at enough orientations from here: move the O-arm or the arm's start pose).
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
    if len(q) < params.n_poses:
        raise PlanningError(
            f"only {len(q)} distinct feasible calibration poses found (need {params.n_poses}): {why}. "
            "Centre the O-arm's volume on the phantom (or the phantom in it), start from a pose further "
            "from the joint limits, or ask for fewer poses (--n)"
        )
    info = _information(chain, y, x, pts, q, params.parameter_set)
    first = int(np.argmin(np.max(np.abs(q - q0), axis=1)))
    sel = np.array(_swap_for_condition(info, _greedy_d_optimal(info, params.n_poses, first)))
    cond = condition_number(info[sel].sum(axis=0))
    ordered, steps = _order_short_moves(q[sel], q0)
    order = [int(np.flatnonzero(np.all(q[sel] == row, axis=1))[0]) for row in ordered]
    pred = predicted_plan_error_mm(y, chain, x, pts, q[sel], volume, params)
    advice = ""
    if pred > params.max_predicted_error_mm:
        more = (
            q[np.argsort(-np.einsum("cii->c", info))[: 2 * params.n_poses]]
            if len(q) > params.n_poses
            else q[sel]
        )
        pred_more = predicted_plan_error_mm(y, chain, x, pts, more, volume, params)
        advice = (
            f"the {params.n_poses} poses are predicted to leave {pred:.2f} mm at the worst pose of the "
            f"working volume (> {params.max_predicted_error_mm:g} mm); "
            + (
                f"{len(more)} poses would give {pred_more:.2f} mm — plan with --n {len(more)}"
                if pred_more <= params.max_predicted_error_mm
                else f"even {len(more)} poses give {pred_more:.2f} mm: allow a wider tilt (tilts_deg up to "
                f"{max(params.tilts_deg):g}° now) or calibrate from a second O-arm placement"
            )
        )
    return PosePlan(ordered, cond, tilts[sel][order], inside[sel][order], steps, len(q), pred, advice)


def predicted_plan_error_mm(
    y: F64, chain: SerialChain, x: F64, pts: F64, joints_rad: F64, volume: ScanVolume, params: PlannerParams
) -> float:
    """Worst-pose predicted error over the working volume of a calibration from ``joints_rad``:
    the calibration's posterior (its priors; data noise FLE/√3 per component) propagated as
    :func:`registration.calibration.solver.predict_working_error` does, on noise-free planning data."""
    from registration.calibration.prediction import (
        WORKING_POSES,
        WORKING_SEED,
        predict_working_error,
    )
    from registration.calibration.records import (
        PRIORS,
        CalibrationParams,
    )

    cp = CalibrationParams()
    model = _Model(y, x, chain, minimal_parameter_set(chain, params.parameter_set))
    n = len(pts)
    k = len(joints_rad)
    data = _Data(joints_rad, np.tile(pts, (k, 1)), np.zeros((k * n, 3)), np.repeat(np.arange(k), n))
    jac = _jacobian(model, data, np.zeros(len(model.params)))
    s2 = params.fle_rms_mm**2 / 3.0
    sig = np.array([PRIORS.sigma_posterior(p) for p in model.params])
    a = np.einsum("ij,ik->jk", jac, jac) / s2 + np.diag(1.0 / sig**2)
    d = np.sqrt(np.diag(a))
    cov = np.linalg.inv(a / np.outer(d, d)) / np.outer(d, d)
    rng = np.random.default_rng(WORKING_SEED)
    work = volume.grown(cp.working_margin_mm)
    wq = sample_poses_in_volume(
        y,
        chain,
        x,
        pts,
        joints_rad[0],
        work,
        rng,
        n=WORKING_POSES,
        max_tilt_deg=75.0,
        margin_mm=0.0,
        n_candidates=300,
    )
    if not len(wq):
        wq = joints_rad
    from registration.calibration.solver import _registration_tre_rms_mm

    pred = predict_working_error(
        model,
        np.zeros(len(model.params)),
        cov,
        wq,
        joints_rad[0],
        pts,
        unmodelled_rms_mm=cp.unmodelled_floor_mm,
        registration_tre_rms_mm=_registration_tre_rms_mm(params.fle_rms_mm, pts),
    )
    return pred.max_mm


def _unique(q: F64, idx: NDArray[np.intp]) -> NDArray[np.intp]:
    """Drop candidates within 1° (every joint) of an earlier one."""
    keep: list[int] = []
    for i in idx:
        if all(float(np.max(np.abs(q[i] - q[j]))) > math.radians(1.0) for j in keep):
            keep.append(int(i))
    return np.array(keep, dtype=np.intp)
