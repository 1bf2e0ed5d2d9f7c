"""The scan volume as a cylinder and poses of the arm inside it: damped-Newton IK and random
feasible poses (used by the pose planner and by the calibration's prediction over the working
volume; kept apart from both so neither imports the other)."""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Final

import numpy as np
from numpy.typing import ArrayLike
from scipy.spatial.transform import Rotation

from registration.arrays import F64
from registration.calibration.urdf import SerialChain, rotation_about
from registration.model.frames import apply, as_transform, invert

IK_ROTATION_WEIGHT_MM: Final = 100.0
"""Rotation errors (rad) are weighted as this lever (mm) in the IK residual."""
IK_TOL_MM: Final = 1e-4
"""An IK solution is accepted when its pose error (with the weight above) is below this."""


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


IK_DAMPING: Final = 1e-3
"""Damping of the IK step, as a fraction of the largest singular value of its Jacobian: the step
is the damped least-squares (Levenberg–Marquardt) one, finite at singular configurations."""
IK_MAX_STEP_RAD: Final = 0.3
"""Largest change of one joint per IK iteration."""


def _rotation_log(r: F64) -> F64:
    """(C, 3) rotation vectors of rotations (C, 3, 3): the log map, through the unit quaternion.

    Smooth up to and including 180° (unlike θ / (2 sin θ) · vee(R − Rᵀ), which divides by a vanishing
    sin θ there: the planner's ``Singular matrix`` without it).  A non-finite rotation gives NaN."""
    out = np.full((len(r), 3), np.nan)
    ok = np.all(np.isfinite(r), axis=(1, 2))
    if ok.any():
        out[ok] = Rotation.from_matrix(r[ok]).as_rotvec()
    return out


def _pose_error(chain: SerialChain, q: F64, target: F64) -> F64:
    """(C, 6) residual: position (mm) and weighted rotation vector of target⁻¹ · FK(q)."""
    return _pose_error_at(chain.robot_from_tool0_batch(q), target)


def _pose_error_at(t: F64, target: F64) -> F64:
    dr = np.einsum("cji,cjk->cik", target[:, :3, :3], t[:, :3, :3])
    rot = _rotation_log(dr)
    return np.concatenate([t[:, :3, 3] - target[:, :3, 3], IK_ROTATION_WEIGHT_MM * rot], axis=1)


def _fk_and_body_jacobian(chain: SerialChain, q: F64) -> tuple[F64, F64]:
    """``robot_from_tool0`` (C, 4, 4) and the (C, 6, n) Jacobian of (position mm, weighted rotation)
    with the rotation part in the tool's own frame (R(q + dq) = R(q) exp(J_rot dq)): always a small
    rotation, so no branch of the log map is crossed however far the target is.  With the residual
    e = log(R_targetᵀ R(q)) the step J_rot dq = −e is exact for the rotation (R_targetᵀ R exp(−ê) = I)."""
    n = chain.n_joints
    out = np.broadcast_to(np.eye(4), (len(q), 4, 4)).copy()
    origins = np.zeros((len(q), n, 3))
    axes = np.zeros((len(q), n, 3))
    for i in range(n):
        out = out @ chain.parent_from_joint[i]
        origins[:, i] = out[:, :3, 3]
        axes[:, i] = out[:, :3, :3] @ chain.axes[i]
        out[:, :3, :3] = out[:, :3, :3] @ rotation_about(chain.axes[i], q[:, i])
    t = np.asarray(out @ chain.last_from_tool0, dtype=np.float64)
    lin = np.cross(axes, t[:, None, :3, 3] - origins)  # (C, n, 3)
    ang = np.einsum("cji,cnj->cni", t[:, :3, :3], axes)
    return t, np.concatenate([lin, IK_ROTATION_WEIGHT_MM * ang], axis=2).transpose(0, 2, 1)


def _damped_step(jac: F64, r: F64) -> F64:
    """(C, n) damped least-squares step −(JᵀJ + λ²I)⁻¹ Jᵀ r, λ² = :data:`IK_DAMPING`² · tr(JᵀJ)
    (≥ that fraction of the largest singular value squared): the normal matrix is positive definite
    at every configuration, singular ones included, so the step is bounded and the solve cannot
    fail on a finite Jacobian."""
    jt = np.swapaxes(jac, 1, 2)
    normal = jt @ jac
    lam2 = IK_DAMPING**2 * np.trace(normal, axis1=1, axis2=2) + 1e-12
    lhs = normal + lam2[:, None, None] * np.eye(jac.shape[2])
    return np.asarray(-np.linalg.solve(lhs, jt @ r[..., None])[..., 0], dtype=np.float64)


def solve_ik(
    chain: SerialChain, robot_from_tool0: F64, seeds_rad: F64, iterations: int = 40
) -> tuple[F64, F64]:
    """Damped least-squares IK for C targets (C, 4, 4) from C seeds (C, n) → (joints (C, n),
    error (C,)).  Never raises on a target: one that cannot be reached (or a non-finite seed) ends
    with a large (or infinite) error, which the callers' tolerance refuses."""
    q = np.array(seeds_rad, dtype=np.float64)
    target = np.asarray(robot_from_tool0, dtype=np.float64)
    finite = np.all(np.isfinite(q), axis=1) & np.all(np.isfinite(target), axis=(1, 2))
    q[~finite] = 0.0
    for _ in range(iterations):
        t, jac = _fk_and_body_jacobian(chain, q)
        r = _pose_error_at(t, target)
        ok = np.all(np.isfinite(jac), axis=(1, 2)) & np.all(np.isfinite(r), axis=1)
        step = np.zeros_like(q)
        step[ok] = _damped_step(jac[ok], r[ok])
        q = q + np.clip(step, -IK_MAX_STEP_RAD, IK_MAX_STEP_RAD)
    err = np.linalg.norm(_pose_error(chain, q, target), axis=1)
    err = np.where(finite & np.isfinite(err), err, np.inf)
    return q, err


def wrist_flip(q: F64) -> F64:
    f = q.copy()
    f[3] += math.pi if f[3] < 0 else -math.pi
    f[4] = -f[4]
    f[5] += math.pi if f[5] < 0 else -math.pi
    return f


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
        [np.repeat(q0[None], n_candidates, 0), np.repeat(wrist_flip(q0)[None], n_candidates, 0)]
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
