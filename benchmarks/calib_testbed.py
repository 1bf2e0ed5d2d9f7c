"""The calibration test bed of issue #20: harder than the cells the solver will meet.

One *case* = (seed, error scale, pose set).  Per case:

* a true cell (:class:`mocks.cell.TrueCell`) whose per-joint errors are ``scale`` × the solver's
  priors (:data:`registration.calibration.solver.PRIORS`), J2/J3 sag, a rod off in 6 DoF, 0.02 mm
  repeatability and encoder noise — the scale is swept (0.5 … 2 ×) so the priors are not the truth;
* an O-arm placement whose scan volume is *not* centred on the phantom at the start pose;
* a pose set the solver did not choose: ``random`` (poses drawn inside the O-arm volume, every
  sphere ≥ 5 mm inside by the nominal model) or ``planned``
  (:func:`registration.calibration.planner.plan_poses` given the scan's real volume);
* the O-arm is then moved; one registration scan at a pose of its own; 20 held-out poses spread
  over the *working volume* (the scan volume grown by :data:`WORKING_MARGIN_MM`) and ≥ 20° in
  phantom orientation from every calibration pose;
* every estimator is scored by the same rule: register the moved scan with its model, predict the
  sphere centres at the held-out poses, compare with the truth.

Detections are the true sphere centres plus isotropic Gaussian noise of :data:`FLE_RMS_MM` (3-D RMS),
the detection error the DICOM session of ``bench_calibration --dicom-session`` measures on this
project's simulator; with ``render=True`` each scan is simulated, written as DICOM, reloaded and
detected instead, the detections cached per scan (npz keyed by the scan's truth) so a rerun only
pays the solver.

The *floor* is the true geometric model (true origins, offsets and rod; the sag no geometric model
has) with an oracle registration (the true ``image_from_robot`` of the moved placement): what is
left is sag, repeatability and encoder noise.  The *peer* is a plain ``scipy.optimize.least_squares``
over 6 error parameters per joint origin, the rod and the placement (48), linear loss,
finite-difference Jacobian, no identifiability handling (issue #20).
"""

from __future__ import annotations

import hashlib
import math
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any, Final

import numpy as np
from scipy.optimize import least_squares

from mocks.cell import CellErrorSizes, TrueCell
from registration.arrays import F64
from registration.calibration.model import (
    ErrorModel,
    Observations,
    initial_estimate,
    parameter_candidates,
    residuals_mm,
    stack_observations,
)
from registration.calibration.planner import PlannerParams, ScanVolume, plan_poses, solve_ik
from registration.calibration.records import (
    PRIORS,
    CalibrationParams,
    CalibrationResult,
    MatchedPose,
)
from registration.calibration.sampling import wrist_flip
from registration.calibration.solver import (
    calibrate,
)
from registration.calibration.urdf import SerialChain, read_chain, rotation_about
from registration.matching.rigid import fit_rigid
from registration.model import frames
from registration.model.kinematics import RobotModel, default_tool0_from_phantom
from registration.model.phantom import Phantom, load_phantom

REPO: Final = Path(__file__).resolve().parents[1]
START_JOINTS_RAD: Final = (0.2, -0.15, 1.75, 0.3, 0.6, -0.9)
"""First pose of every session: phantom in front of the arm, wrist bent (bench_calibration's)."""
FLE_RMS_MM: Final = 0.07
"""3-D RMS detection error of a synthetic scan: what the DICOM session measures on the simulator."""
SCAN_VOLUME: Final = ScanVolume()
"""The O-arm export's cylinder (212 mm FOV × 160 mm), centred at the image origin."""
VOLUME_OFFSET_MM: Final = (28.0, -20.0, 12.0)
"""Where the phantom sits in the image at the start pose: 36 mm off the volume centre (issue #20)."""
WORKING_MARGIN_MM: Final = 40.0
"""Working volume = scan volume grown by this (radius and half-length): the default of
``CalibrationParams.working_margin_mm``."""
MIN_HELD_OUT_SEPARATION_DEG: Final = 20.0
"""Held-out poses are at least this far (phantom orientation) from every calibration pose."""
N_HELD_OUT: Final = 20
REF_SAG_RMS_DEG: Final = 0.005
"""J2/J3 sag RMS at error scale 1 (the issue #10 cell had 0.003°)."""
REF_ROD_TRANSLATION_MM: Final = 0.8
REF_ROD_ROTATION_DEG: Final = 0.4
"""Rod error at scale 1 (issue #20's unseen cell: 0.8 mm / 0.4°)."""


def cell_sizes(scale: float) -> CellErrorSizes:
    """The true cell's error sizes at ``scale`` × the solver's priors (per-joint) and the refs."""
    return CellErrorSizes(
        joint_origin_translation_mm=scale * PRIORS.origin_translation_mm,
        joint_origin_rotation_deg=scale * PRIORS.origin_rotation_deg,
        joint_zero_offset_deg=scale * PRIORS.zero_offset_deg,
        rod_translation_mm=scale * REF_ROD_TRANSLATION_MM,
        rod_rotation_deg=scale * REF_ROD_ROTATION_DEG,
        sag_j2j3_rms_deg=scale * REF_SAG_RMS_DEG,
        repeatability_mm=0.02,
        encoder_noise_rad=1e-5,
    )


@dataclass(frozen=True)
class Case:
    seed: int
    scale: float
    pose_set: str  # "random" | "planned"
    n_poses: int | None = 10
    """Pose count; None for ``planned``: the planner's own count (its target), 10 for ``random``."""
    start: int = 0
    """Which registration the planner starts from: 0 the first scan at :data:`START_JOINTS_RAD`,
    i ≥ 1 a scan at the i-th pose of the planner's plan from that first scan (issue #33: the planner
    must plan from any scan)."""

    @property
    def label(self) -> str:
        n = "default" if self.n_poses is None else str(self.n_poses)
        start = f" from scan {self.start + 1}" if self.start else ""
        return f"seed {self.seed} ×{self.scale:g} {self.pose_set} {n}{start}"


@dataclass(eq=False)
class Bed:
    """Everything of one case the estimators and the scoring need."""

    case: Case
    phantom: Phantom
    model: RobotModel
    chain: SerialChain
    rod: F64
    cell: TrueCell
    image_from_robot: F64
    poses: list[MatchedPose]
    cal_joints_rad: F64
    image_from_robot_moved: F64
    reg_joints_reported_rad: F64
    reg_detections_mm: F64
    held_out_rad: F64
    held_out_truth_mm: F64  # (H, N, 3)
    held_out_reported_rad: F64
    info: dict[str, Any] = field(default_factory=dict)


def _rand_rotation_tilt(rng: np.random.Generator, max_tilt_deg: float) -> F64:
    """A tilt of the z axis up to ``max_tilt_deg`` about a random horizontal axis, then any yaw."""
    az = rng.uniform(0.0, 2 * math.pi)
    tilt = math.radians(max_tilt_deg) * math.sqrt(rng.uniform())
    r_t = rotation_about(np.array([math.cos(az), math.sin(az), 0.0]), np.array([tilt]))[0]
    r_y = rotation_about(np.array([0.0, 0.0, 1.0]), np.array([rng.uniform(0.0, 2 * math.pi)]))[0]
    return np.asarray(r_t @ r_y, dtype=np.float64)


def random_poses(
    rng: np.random.Generator,
    y: F64,
    chain: SerialChain,
    rod: F64,
    pts: F64,
    q0: F64,
    volume: ScanVolume,
    *,
    n: int,
    max_tilt_deg: float,
    margin_mm: float,
    n_candidates: int = 600,
) -> F64:
    """Up to ``n`` random feasible poses: random phantom orientation (tilt ≤ ``max_tilt_deg`` from
    the start orientation, any yaw), random position in ``volume``; IK from the start joints and
    their wrist flip; joint limits − 5°; every sphere ≥ ``margin_mm`` inside ``volume`` (nominal)."""
    r0 = (y @ chain.robot_from_tool0(q0) @ rod)[:3, :3]
    axis = np.asarray(volume.axis_image) / np.linalg.norm(volume.axis_image)
    targets = []
    for _ in range(n_candidates):
        rr = volume.fov_radius_mm * math.sqrt(rng.uniform()) * 0.8
        ph = rng.uniform(0.0, 2 * math.pi)
        u = np.cross(axis, [1.0, 0.0, 0.0])
        if np.linalg.norm(u) < 1e-6:
            u = np.cross(axis, [0.0, 1.0, 0.0])
        u /= np.linalg.norm(u)
        w = np.cross(axis, u)
        c = (
            np.asarray(volume.centre_image_mm)
            + rr * (math.cos(ph) * u + math.sin(ph) * w)
            + rng.uniform(-0.8, 0.8) * volume.half_length_mm * axis
        )
        targets.append(frames.make_transform(r0 @ _rand_rotation_tilt(rng, max_tilt_deg), c))
    timg = np.stack(targets)
    trob = frames.invert(y) @ timg @ frames.invert(rod)
    seeds = np.concatenate([np.repeat(q0[None], len(trob), 0), np.repeat(wrist_flip(q0)[None], len(trob), 0)])
    q, err = solve_ik(chain, np.concatenate([trob, trob]), seeds)
    lim = math.radians(5.0)
    ok = (err < 1e-4) & np.all((q >= chain.lower_rad + lim) & (q <= chain.upper_rad - lim), axis=1)
    fk = y @ chain.robot_from_tool0_batch(q) @ rod
    inside = volume.inside_margin_mm(np.einsum("cij,nj->cni", fk[:, :3, :3], pts) + fk[:, None, :3, 3])
    ok &= inside >= margin_mm
    idx = np.flatnonzero(ok)
    keep: list[int] = []
    for i in idx:  # distinct configurations (first of a wrist-flip pair wins)
        if all(float(np.max(np.abs(q[i] - q[j]))) > math.radians(2.0) for j in keep):
            keep.append(int(i))
        if len(keep) >= n:
            break
    return np.asarray(q[keep], dtype=np.float64)


def _orientation_gap_deg(r_a: F64, r_b: F64) -> F64:
    """Geodesic angle (deg) between every rotation of r_a (A,3,3) and every of r_b (B,3,3) → (A,B)."""
    tr = np.einsum("aji,bji->ab", r_a, r_b)
    return np.asarray(np.degrees(np.arccos(np.clip((tr - 1.0) / 2.0, -1.0, 1.0))), dtype=np.float64)


def _spread_pick(centres: F64, k: int) -> list[int]:
    """Farthest-point sampling of ``k`` indices over ``centres`` (C, 3)."""
    chosen = [int(np.argmin(np.linalg.norm(centres - centres.mean(axis=0), axis=1)))]
    d = np.linalg.norm(centres - centres[chosen[0]], axis=1)
    while len(chosen) < min(k, len(centres)):
        j = int(np.argmax(d))
        chosen.append(j)
        d = np.minimum(d, np.linalg.norm(centres - centres[j], axis=1))
    return chosen


def grown(volume: ScanVolume, margin_mm: float) -> ScanVolume:
    return replace(
        volume,
        fov_radius_mm=volume.fov_radius_mm + margin_mm,
        half_length_mm=volume.half_length_mm + margin_mm,
    )


def _detect(rng: np.random.Generator, truth_mm: F64, fle_rms_mm: float = FLE_RMS_MM) -> F64:
    """A synthetic detection: the true centres + isotropic Gaussian noise of ``fle_rms_mm`` 3-D RMS."""
    return np.asarray(
        truth_mm + rng.normal(0.0, fle_rms_mm / math.sqrt(3.0), truth_mm.shape), dtype=np.float64
    )


def build(case: Case, *, render_cache: Path | None = None) -> Bed:
    """The case's cell, placement, calibration scans, moved scan and held-out poses."""
    phantom = load_phantom(REPO / "configs" / "phantoms" / "bai2018_cube.toml")
    model = RobotModel.load("tx60")
    chain = read_chain(model.urdf_path)
    rod = default_tool0_from_phantom()
    pts = phantom.centres_phantom_mm
    cell = TrueCell.sample(case.seed, model, rod, cell_sizes(case.scale))
    rng = np.random.default_rng(
        case.seed * 7919 + int(case.scale * 100) + (0 if case.pose_set == "random" else 1)
    )
    q0 = np.array(START_JOINTS_RAD)
    # placement: the phantom at VOLUME_OFFSET_MM from the volume centre at q0 (true cell), rotated
    rpy = rng.uniform(-15.0, 15.0, 3) + np.array([10.0, -5.0, 30.0])
    image_from_phantom = frames.transform_from_xyz_rpy(VOLUME_OFFSET_MM, rpy)
    y = image_from_phantom @ frames.invert(cell.robot_from_tool0_true(q0) @ cell.tool0_from_phantom)
    # the first scan, registered with the nominal model: what the operator / planner start from
    first = _detect(rng, frames.apply(cell.image_from_phantom_true(y, q0, rng), pts))
    q0_rep = cell.reported_joints(q0, rng)
    y_reg0 = fit_rigid(frames.apply(model.robot_from_tool0(q0_rep) @ rod, pts), first)
    plan = None
    if case.pose_set == "planned":
        q_start, y_start = q0_rep, y_reg0
        if case.start:
            q_s = plan_poses(y_reg0, chain, rod, pts, q0_rep, volume=SCAN_VOLUME).joints_rad[case.start - 1]
            det = _detect(rng, frames.apply(cell.image_from_phantom_true(y, q_s, rng), pts))
            q_start = cell.reported_joints(q_s, rng)
            y_start = fit_rigid(frames.apply(model.robot_from_tool0(q_start) @ rod, pts), det)
        plan = plan_poses(
            y_start, chain, rod, pts, q_start, volume=SCAN_VOLUME, params=PlannerParams(n_poses=case.n_poses)
        )
        cal_q = plan.joints_rad
    else:
        cal_q = random_poses(
            rng,
            y_reg0,
            chain,
            rod,
            pts,
            q0_rep,
            SCAN_VOLUME,
            n=case.n_poses or 10,
            max_tilt_deg=60.0,
            margin_mm=5.0,
        )
    poses = []
    cal_truth = []
    for i, q in enumerate(cal_q):
        truth = frames.apply(cell.image_from_phantom_true(y, q, rng), pts)
        cal_truth.append(truth)
        det = _render(render_cache, truth, phantom, rng) if render_cache else _detect(rng, truth)
        idx = np.flatnonzero(np.isfinite(det[:, 0]))
        poses.append(MatchedPose(f"pose-{i:02d}", cell.reported_joints(q, rng), idx, det[idx]))
    # O-arm moved: a new placement, one registration scan near the start pose
    y2 = frames.transform_from_xyz_rpy([12.0, -8.0, 5.0], [2.0, -3.0, 4.0]) @ y
    reg_q = random_poses(rng, y2, chain, rod, pts, q0, SCAN_VOLUME, n=1, max_tilt_deg=10.0, margin_mm=10.0)
    if not len(reg_q):
        reg_q = q0[None]
    reg_truth = frames.apply(cell.image_from_phantom_true(y2, reg_q[0], rng), pts)
    reg_det = _render(render_cache, reg_truth, phantom, rng) if render_cache else _detect(rng, reg_truth)
    reg_rep = cell.reported_joints(reg_q[0], rng)
    # held-out poses: spread over the working volume, ≥ 20° from every calibration pose
    work = grown(SCAN_VOLUME, WORKING_MARGIN_MM)
    cand = random_poses(
        rng, y2, chain, rod, pts, q0, work, n=400, max_tilt_deg=75.0, margin_mm=0.0, n_candidates=1500
    )
    r_cal = (y @ chain.robot_from_tool0_batch(cal_q) @ rod)[:, :3, :3]
    fk = y2 @ chain.robot_from_tool0_batch(cand) @ rod
    r_c = np.einsum("ij,cjk->cik", (y @ frames.invert(y2))[:3, :3], fk[:, :3, :3])  # in the first placement
    gap = _orientation_gap_deg(r_c, r_cal).min(axis=1)
    cand, fk = cand[gap >= MIN_HELD_OUT_SEPARATION_DEG], fk[gap >= MIN_HELD_OUT_SEPARATION_DEG]
    pick = _spread_pick(fk[:, :3, 3], N_HELD_OUT)
    held = cand[pick]
    truth_h = np.stack([frames.apply(cell.image_from_phantom_true(y2, q, rng), pts) for q in held])
    rep_h = np.stack([cell.reported_joints(q, rng) for q in held])
    return Bed(
        case,
        phantom,
        model,
        chain,
        rod,
        cell,
        y,
        poses,
        cal_q,
        y2,
        reg_rep,
        reg_det,
        held,
        truth_h,
        rep_h,
        {
            "n_held_out_candidates": len(cand),
            "cal_truth_mm": cal_truth,
            "reg_truth_mm": reg_truth,
            "reg_joints_rad": reg_q[0],
            "plan": plan,
        },
    )


def redraw_detections(bed: Bed, rng: np.random.Generator, fle_rms_mm: float = FLE_RMS_MM) -> Bed:
    """The same case (cell, poses, placements, held-out truth) with fresh synthetic detection noise
    on every calibration scan and on the registration scan: what varies from one session to the
    next that no predictor can know in advance."""
    poses = []
    for p, truth in zip(bed.poses, bed.info["cal_truth_mm"], strict=True):
        idx = np.asarray(p.sphere_indices)
        poses.append(MatchedPose(p.name, p.joints_rad, idx, _detect(rng, truth[idx], fle_rms_mm)))
    return replace(bed, poses=poses, reg_detections_mm=_detect(rng, bed.info["reg_truth_mm"], fle_rms_mm))


def redraw_session(bed: Bed, rng: np.random.Generator, fle_rms_mm: float = FLE_RMS_MM) -> Bed:
    """The same cell, pose set, placements and held-out poses with everything a session draws anew:
    each move's repeatability scatter and encoder noise (calibration, registration and held-out
    poses) and the detection noise of every scan.  Only the cell (its geometry and sag) and the
    poses stay: what a predictor that knew the cell could know, and no more."""
    pts = bed.phantom.centres_phantom_mm
    cell = bed.cell
    poses = []
    for p, q in zip(bed.poses, bed.cal_joints_rad, strict=True):
        truth = frames.apply(cell.image_from_phantom_true(bed.image_from_robot, q, rng), pts)
        idx = np.asarray(p.sphere_indices)
        det = _detect(rng, truth[idx], fle_rms_mm)
        poses.append(MatchedPose(p.name, cell.reported_joints(q, rng), idx, det))
    q_reg = bed.info["reg_joints_rad"]
    y2 = bed.image_from_robot_moved
    reg_truth = frames.apply(cell.image_from_phantom_true(y2, q_reg, rng), pts)
    truth_h = np.stack(
        [frames.apply(cell.image_from_phantom_true(y2, q, rng), pts) for q in bed.held_out_rad]
    )
    return replace(
        bed,
        poses=poses,
        reg_joints_reported_rad=cell.reported_joints(q_reg, rng),
        reg_detections_mm=_detect(rng, reg_truth, fle_rms_mm),
        held_out_truth_mm=truth_h,
        held_out_reported_rad=np.stack([cell.reported_joints(q, rng) for q in bed.held_out_rad]),
    )


def _render(cache: Path, truth_mm: F64, phantom: Phantom, rng: np.random.Generator) -> F64:
    """Simulate + DICOM + detect one scan posed so its sphere centres are ``truth_mm`` (cached)."""
    import tempfile

    from mocks.oarm.dicom_export import write_dicom_series
    from mocks.oarm.simulator import AcquisitionSettings, simulate_scan
    from registration.detection import detect_spheres, params_for_spheres
    from registration.dicom import load_series

    key = hashlib.sha256(np.round(truth_mm, 9).tobytes()).hexdigest()[:20]
    path = cache / f"{key}.npz"
    cache.mkdir(parents=True, exist_ok=True)
    if path.is_file():
        return np.asarray(np.load(path)["centres"], dtype=np.float64)
    pose = fit_rigid(phantom.centres_phantom_mm, truth_mm)
    settings = AcquisitionSettings.preset("small", rows=300, columns=300, n_slices=160)
    with tempfile.TemporaryDirectory(prefix="calib-render-") as tmp:
        scan = simulate_scan(phantom, pose, settings)
        write_dicom_series(scan, Path(tmp), write_truth=False)
        vol = load_series(Path(tmp))
        det = detect_spheres(vol, params_for_spheres(phantom.sphere_material, phantom.sphere_diameter_mm))
    out = np.full_like(truth_mm, np.nan)
    # pair each detection with the nearest true centre (≤ 1.5 mm), the rest stay NaN
    for c in det.centres_image_mm:
        d = np.linalg.norm(truth_mm - c, axis=1)
        j = int(np.argmin(d))
        if d[j] < 1.5:
            out[j] = c
    np.savez(path, centres=out)
    return out


# ---------------------------------------------------------------- estimators → predictors

Predictor = Callable[[F64], F64]
"""joints (n,) → robot_from_phantom (4, 4) of a calibrated model."""


def score(bed: Bed, robot_from_phantom: Predictor) -> F64:
    """Per-sphere held-out errors (mm) of a model: register the moved scan with it, predict."""
    pts = bed.phantom.centres_phantom_mm
    seen = np.isfinite(bed.reg_detections_mm[:, 0])  # a rendered scan may miss a sphere
    y2 = fit_rigid(
        frames.apply(robot_from_phantom(bed.reg_joints_reported_rad), pts[seen]), bed.reg_detections_mm[seen]
    )
    errs = [
        np.linalg.norm(frames.apply(y2 @ robot_from_phantom(q), pts) - t, axis=1)
        for q, t in zip(bed.held_out_reported_rad, bed.held_out_truth_mm, strict=True)
    ]
    return np.concatenate(errs)


def floor_errors(bed: Bed) -> F64:
    """The true geometric model (no sag) with the true moved placement (an oracle registration)."""
    pts = bed.phantom.centres_phantom_mm
    c = bed.cell
    errs = []
    for q, t in zip(bed.held_out_reported_rad, bed.held_out_truth_mm, strict=True):
        m = c.chain.robot_from_tool0(q + c.joint_offsets_rad) @ c.tool0_from_phantom
        errs.append(np.linalg.norm(frames.apply(bed.image_from_robot_moved @ m, pts) - t, axis=1))
    return np.concatenate(errs)


def nominal_predictor(bed: Bed) -> Predictor:
    return lambda q: bed.model.robot_from_tool0(q) @ bed.rod


def result_predictor(r: CalibrationResult) -> Predictor:
    return lambda q: r.chain.robot_from_tool0(q) @ r.tool0_from_phantom


def peer_fit(bed: Bed) -> Predictor:
    """Plain least squares over 6 error parameters per joint origin + rod + placement (48)."""
    pts = bed.phantom.centres_phantom_mm
    data: Observations = stack_observations(bed.poses, pts)
    y0, x0 = initial_estimate(bed.poses, bed.chain, pts)
    model = ErrorModel(y0, x0, bed.chain, tuple(parameter_candidates(bed.chain)))
    res = least_squares(lambda v: residuals_mm(model, data, v), np.zeros(len(model.params)))
    _, x, ch = model.unpack(np.asarray(res.x, dtype=np.float64))
    return lambda q: ch.robot_from_tool0(q) @ x


def run_calibrate(bed: Bed, params: CalibrationParams) -> CalibrationResult:
    return calibrate(
        bed.poses, bed.chain, bed.rod, bed.phantom.centres_phantom_mm, params, scan_volume=SCAN_VOLUME
    )


def true_model_predictor(bed: Bed) -> Predictor:
    """The true geometric model (origins, zero offsets, rod; no sag)."""
    c = bed.cell
    return lambda q: c.chain.robot_from_tool0(q + c.joint_offsets_rad) @ c.tool0_from_phantom
