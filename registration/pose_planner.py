"""Plan the poses of a calibration session from one registration (issue #10).

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
set is predicted to give (:mod:`registration.calibration`, same parameter set
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
from typing import Any, Final

import numpy as np
from numpy.typing import ArrayLike, NDArray

from registration.calibration import _Data, _jacobian, _Model, minimal_parameter_set
from registration.errors import RegistrationError
from registration.frames import apply, as_transform, invert, make_transform
from registration.urdf_writer import SerialChain, rotation_about

F64 = NDArray[np.float64]

IK_ROTATION_WEIGHT_MM: Final = 100.0
"""Rotation errors (rad) are weighted as this lever (mm) in the IK residual."""
IK_TOL_MM: Final = 1e-4
"""An IK solution is accepted when its pose error (with the weight above) is below this."""


class PlanningError(RegistrationError):
    title = "Cannot plan calibration poses"


@dataclass(frozen=True)
class ScanVolume:
    """The reconstructed volume as a cylinder in the image frame (mm).

    Defaults: the ``oarm`` export, 512 × 0.415 mm = 212 mm FOV, 192 × 0.833 mm = 160 mm axial
    (research/calibration.md §4, unverified values), axis = image z.
    """

    centre_image_mm: tuple[float, float, float] = (0.0, 0.0, 0.0)
    fov_radius_mm: float = 106.24
    half_length_mm: float = 79.97
    axis_image: tuple[float, float, float] = (0.0, 0.0, 1.0)

    def grown(self, margin_mm: float) -> ScanVolume:
        """The same cylinder with radius and half-length grown by ``margin_mm``."""
        return ScanVolume(
            self.centre_image_mm,
            self.fov_radius_mm + margin_mm,
            self.half_length_mm + margin_mm,
            self.axis_image,
        )

    def inside_margin_mm(self, points_image_mm: F64) -> F64:
        """Smallest distance (mm) of each point set (…, N, 3) to the cylinder's boundary (< 0 outside)."""
        axis = np.asarray(self.axis_image) / np.linalg.norm(self.axis_image)
        rel = points_image_mm - np.asarray(self.centre_image_mm)
        along = rel @ axis
        radial = np.linalg.norm(rel - along[..., None] * axis, axis=-1)
        per_point = np.minimum(self.fov_radius_mm - radial, self.half_length_mm - np.abs(along))
        return np.asarray(per_point.min(axis=-1), dtype=np.float64)


@dataclass(frozen=True)
class PlannerParams:
    n_poses: int = 10
    margin_mm: float = 5.0
    """Issue #10: every sphere ≥ 5 mm inside the scan volume and FOV."""
    model_error_mm: float = 2.0
    """Added to ``margin_mm``: how far a sphere may really be from where the planning model puts it
    (relative to the registration pose).  Issue #20's unseen cell: nominal held-out error 1.03 mm
    mean, 1.84 mm max; 2 mm covers the max.  Plan with a calibration (``--calibration``) to use a
    smaller value (its ``predicted_chain_error_mm``)."""
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


def _pose_error(chain: SerialChain, q: F64, target: F64) -> F64:
    """(C, 6) residual: position (mm) and weighted rotation vector of target⁻¹ · FK(q)."""
    t = chain.robot_from_tool0_batch(q)
    dr = np.einsum("cji,cjk->cik", target[:, :3, :3], t[:, :3, :3])
    cos = np.clip((np.trace(dr, axis1=1, axis2=2) - 1.0) / 2.0, -1.0, 1.0)
    ang = np.arccos(cos)
    vee = np.stack([dr[:, 2, 1] - dr[:, 1, 2], dr[:, 0, 2] - dr[:, 2, 0], dr[:, 1, 0] - dr[:, 0, 1]], axis=1)
    sin = np.sin(ang)
    factor = np.where(sin > 1e-9, ang / np.maximum(2.0 * sin, 1e-300), 0.5)
    rot = vee * factor[:, None]
    return np.concatenate([t[:, :3, 3] - target[:, :3, 3], IK_ROTATION_WEIGHT_MM * rot], axis=1)


def solve_ik(
    chain: SerialChain, robot_from_tool0: F64, seeds_rad: F64, iterations: int = 40
) -> tuple[F64, F64]:
    """Damped-Newton IK for C targets (C, 4, 4) from C seeds (C, n) → (joints (C, n), error (C,))."""
    q = np.array(seeds_rad, dtype=np.float64)
    n = chain.n_joints
    h = 1e-6
    for _ in range(iterations):
        r = _pose_error(chain, q, robot_from_tool0)
        probes = q[:, None, :] + h * np.eye(n)[None]
        rp = _pose_error(chain, probes.reshape(-1, n), np.repeat(robot_from_tool0, n, axis=0)).reshape(
            len(q), n, 6
        )
        jac = np.swapaxes((rp - r[:, None, :]) / h, 1, 2)  # (C, 6, n)
        jt = np.swapaxes(jac, 1, 2)
        lhs = jt @ jac + 1e-6 * np.eye(n)
        step = np.linalg.solve(lhs, -(jt @ r[..., None]))[..., 0]
        q = q + np.clip(step, -0.3, 0.3)
    err = np.linalg.norm(_pose_error(chain, q, robot_from_tool0), axis=1)
    return q, err


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


def _wrist_flip(q: F64) -> F64:
    f = q.copy()
    f[3] += math.pi if f[3] < 0 else -math.pi
    f[4] = -f[4]
    f[5] += math.pi if f[5] < 0 else -math.pi
    return f


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
    ok = (err < IK_TOL_MM) & np.all((q >= chain.lower_rad + margin) & (q <= chain.upper_rad - margin), axis=1)
    fk = y @ chain.robot_from_tool0_batch(q) @ x
    inside = volume.inside_margin_mm(np.einsum("cij,nj->cni", fk[:, :3, :3], pts) + fk[:, None, :3, 3])
    ok &= inside >= params.margin_mm + params.model_error_mm
    idx = _unique(q, np.flatnonzero(ok))
    return q[idx], tilts[idx], inside[idx]


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
    q, tilts, inside = feasible_poses(y, chain, x, pts, q0, volume=volume, params=params)
    if len(q) < params.n_poses:
        raise PlanningError(
            f"only {len(q)} feasible calibration poses found (need {params.n_poses}): the phantom cannot be "
            f"kept {params.margin_mm:g} mm inside the scan volume within the joint limits at enough "
            "orientations; centre the O-arm on the phantom or start from a pose further from the limits"
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
    :func:`registration.calibration.predict_working_error` does, on noise-free planning data."""
    from registration.calibration import (
        PRIORS,
        WORKING_POSES,
        WORKING_SEED,
        CalibrationParams,
        predict_working_error,
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
    from registration.calibration import _registration_tre_rms_mm

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


def predicted_centres_image_mm(
    image_from_robot: F64,
    chain: SerialChain,
    tool0_from_phantom: F64,
    centres_phantom_mm: F64,
    joints_rad: F64,
) -> F64:
    """Sphere centres (image mm) at ``joints_rad`` by ``chain`` (for checks and tests)."""
    return apply(
        image_from_robot @ chain.robot_from_tool0(joints_rad) @ tool0_from_phantom, centres_phantom_mm
    )


def sample_poses_in_volume(
    image_from_robot: ArrayLike,
    chain: SerialChain,
    tool0_from_phantom: ArrayLike,
    centres_phantom_mm: ArrayLike,
    start_joints_rad: ArrayLike,
    volume: ScanVolume,
    rng: np.random.Generator,
    *,
    n: int,
    max_tilt_deg: float,
    margin_mm: float,
    n_candidates: int = 600,
    joint_margin_deg: float = 5.0,
) -> F64:
    """Up to ``n`` random feasible poses (n', n) rad: phantom orientation tilted ≤ ``max_tilt_deg``
    from the start pose's (random horizontal axis, any yaw about its own z), position uniform in
    80 % of ``volume``; IK from the start joints and their wrist flip; joint limits −
    ``joint_margin_deg``; every sphere ≥ ``margin_mm`` inside ``volume`` by ``chain``.  Distinct
    (> 2° in some joint), in draw order."""
    y = as_transform(image_from_robot, "image_from_robot")
    x = as_transform(tool0_from_phantom, "tool0_from_phantom")
    pts = np.asarray(centres_phantom_mm, dtype=np.float64)
    q0 = np.asarray(start_joints_rad, dtype=np.float64).reshape(-1)
    r0 = (y @ chain.robot_from_tool0(q0) @ x)[:3, :3]
    axis = np.asarray(volume.axis_image, dtype=np.float64) / np.linalg.norm(volume.axis_image)
    u = np.cross(axis, [1.0, 0.0, 0.0]) if abs(axis[0]) < 0.9 else np.cross(axis, [0.0, 1.0, 0.0])
    u /= np.linalg.norm(u)
    w = np.cross(axis, u)
    rr = 0.8 * volume.fov_radius_mm * np.sqrt(rng.uniform(size=n_candidates))
    ph = rng.uniform(0.0, 2 * math.pi, n_candidates)
    ax = rng.uniform(-0.8, 0.8, n_candidates) * volume.half_length_mm
    centres = (
        np.asarray(volume.centre_image_mm)
        + (rr * np.cos(ph))[:, None] * u
        + (rr * np.sin(ph))[:, None] * w
        + ax[:, None] * axis
    )
    az = rng.uniform(0.0, 2 * math.pi, n_candidates)
    tilt = math.radians(max_tilt_deg) * np.sqrt(rng.uniform(size=n_candidates))
    yaw = rng.uniform(0.0, 2 * math.pi, n_candidates)
    rots = np.stack(
        [
            r0
            @ rotation_about(np.array([math.cos(a), math.sin(a), 0.0]), np.array([t]))[0]
            @ rotation_about(np.array([0.0, 0.0, 1.0]), np.array([yw]))[0]
            for a, t, yw in zip(az, tilt, yaw, strict=True)
        ]
    )
    timg = np.zeros((n_candidates, 4, 4))
    timg[:, :3, :3], timg[:, :3, 3], timg[:, 3, 3] = rots, centres, 1.0
    trob = invert(y) @ timg @ invert(x)
    seeds = np.concatenate(
        [np.repeat(q0[None], n_candidates, 0), np.repeat(_wrist_flip(q0)[None], n_candidates, 0)]
    )
    q, err = solve_ik(chain, np.concatenate([trob, trob]), seeds)
    lim = math.radians(joint_margin_deg)
    ok = (err < IK_TOL_MM) & np.all((q >= chain.lower_rad + lim) & (q <= chain.upper_rad - lim), axis=1)
    fk = y @ chain.robot_from_tool0_batch(q) @ x
    inside = volume.inside_margin_mm(np.einsum("cij,nj->cni", fk[:, :3, :3], pts) + fk[:, None, :3, 3])
    ok &= inside >= margin_mm
    keep: list[int] = []
    for i in np.flatnonzero(ok):
        if all(float(np.max(np.abs(q[i] - q[j]))) > math.radians(2.0) for j in keep):
            keep.append(int(i))
        if len(keep) >= n:
            break
    return np.asarray(q[keep], dtype=np.float64).reshape(len(keep), chain.n_joints)
