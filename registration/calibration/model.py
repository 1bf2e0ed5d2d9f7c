"""The error model the calibration fits: which geometric errors it can estimate, how they change the
robot's kinematics, and the residuals and analytic Jacobian of the sphere positions.

Also the closed-form start (Shah's AX = YB for the O-arm placement and the rod) and
:func:`predict_image_mm`, a calibrated model's sphere centres in the image."""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING, Final

import numpy as np
from numpy.typing import ArrayLike, NDArray

from registration.arrays import F64
from registration.calibration.records import CalibrationResult, MatchedPose, Parameter
from registration.calibration.urdf import SerialChain, rotation_about
from registration.errors import CalibrationError
from registration.matching.rigid import fit_rigid, nearest_rotation
from registration.model.frames import as_transform, invert, make_transform

if TYPE_CHECKING:
    pass


I64 = NDArray[np.int64]


FD_STEP: Final = 1e-6
"""Central-difference step of the Jacobian (rad or mm): truncation ~1e-12, round-off ~1e-10."""


STRUCTURAL_RANK_TOL: Final = 1e-5
"""A candidate column whose normalised residual after projection on the kept ones is below this is
structurally redundant (exact redundancies leave ~1e-10, genuine parameters ≥ 1e-2)."""


def _perpendicular_pair(axis: F64) -> tuple[F64, F64]:
    """Two unit vectors ⟂ ``axis`` (the other coordinate axes when ``axis`` is one)."""
    e = np.eye(3)
    k = int(np.argmax(np.abs(axis)))
    if abs(abs(axis[k]) - 1.0) < 1e-12:
        others = [e[j] for j in range(3) if j != k]
        return others[0], others[1]
    u = np.cross(axis, e[int(np.argmin(np.abs(axis)))])
    u /= np.linalg.norm(u)
    return u, np.cross(axis, u)


def _dir_name(d: F64) -> str:
    for j, n in enumerate("xyz"):
        if abs(abs(d[j]) - 1.0) < 1e-12:
            return ("-" if d[j] < 0 else "") + n
    return "(" + ",".join(f"{v:+.3f}" for v in d) + ")"


def parameter_candidates(chain: SerialChain) -> list[Parameter]:
    """Every candidate, in selection priority: Y (6), X (6), offsets, tilts, shifts, slides."""
    e = np.eye(3)
    out = [
        Parameter(f"{g} {k} {n}", g, k, tuple(e[j]))
        for g in ("image_from_robot", "tool0_from_phantom")
        for k in ("rot", "trans")
        for j, n in enumerate("xyz")
    ]
    names, axes = chain.joint_names, chain.axes
    out += [Parameter(f"{names[i]} offset", names[i], "rot", tuple(axes[i])) for i in range(len(names))]
    for i, name in enumerate(names):
        u, w = _perpendicular_pair(axes[i])
        out += [Parameter(f"{name} origin tilt {_dir_name(d)}", name, "rot", tuple(d)) for d in (u, w)]
    for i, name in enumerate(names):
        u, w = _perpendicular_pair(axes[i])
        out += [Parameter(f"{name} origin shift {_dir_name(d)}", name, "trans", tuple(d)) for d in (u, w)]
    out += [
        Parameter(f"{n} origin slide {_dir_name(axes[i])}", n, "trans", tuple(axes[i]))
        for i, n in enumerate(names)
    ]
    return out


def _rotvec_matrix(w: F64) -> F64:
    ang = float(np.linalg.norm(w))
    if ang == 0.0:
        return np.eye(3)
    k = w / ang
    kx = np.array([[0.0, -k[2], k[1]], [k[2], 0.0, -k[0]], [-k[1], k[0], 0.0]])
    return np.asarray(np.eye(3) + math.sin(ang) * kx + (1.0 - math.cos(ang)) * (kx @ kx), dtype=np.float64)


def _corrections(params: Sequence[Parameter], values: F64) -> dict[str, F64]:
    """group → E(ω, v) (4 × 4) from the parameter values."""
    acc: dict[str, tuple[F64, F64]] = {}
    for p, v in zip(params, values, strict=True):
        w, t = acc.setdefault(p.group, (np.zeros(3), np.zeros(3)))
        (w if p.kind == "rot" else t)[:] += float(v) * np.asarray(p.direction)
    return {g: make_transform(_rotvec_matrix(w), t) for g, (w, t) in acc.items()}


@dataclass(frozen=True, eq=False)
class ErrorModel:
    """Nominal X, Y, chain and the parameter list: maps a parameter vector to (Y, X, chain)."""

    y0: F64
    x0: F64
    chain: SerialChain
    params: tuple[Parameter, ...]
    prior_weights: F64 | None = None
    """Per parameter σ_d / (s σ_j) of the MAP prior residual (0 = flat prior); None = plain LS."""

    def with_prior(self, weights: F64 | None) -> ErrorModel:
        return ErrorModel(self.y0, self.x0, self.chain, self.params, weights)

    def unpack(self, values: F64) -> tuple[F64, F64, SerialChain]:
        c = _corrections(self.params, values)
        eye = np.eye(4)
        y = self.y0 @ c.get("image_from_robot", eye)
        x = self.x0 @ c.get("tool0_from_phantom", eye)
        m = np.stack(
            [
                mi @ c.get(n, eye)
                for mi, n in zip(self.chain.parent_from_joint, self.chain.joint_names, strict=True)
            ]
        )
        return y, x, self.chain.with_origins(m)

    def predict(self, values: F64, joints_rad: F64, pts_phantom_mm: F64, pose_of: I64) -> F64:
        y, x, chain = self.unpack(values)
        t = y @ chain.robot_from_tool0_batch(joints_rad) @ x
        tp = t[pose_of]
        return np.asarray(
            np.einsum("lij,lj->li", tp[:, :3, :3], pts_phantom_mm) + tp[:, :3, 3], dtype=np.float64
        )


@dataclass(frozen=True, eq=False)
class Observations:
    joints_rad: F64  # (K, n)
    pts_phantom_mm: F64  # (L, 3)
    meas_image_mm: F64  # (L, 3)
    pose_of: I64  # (L,)

    def subset(self, keep: NDArray[np.bool_]) -> Observations:
        new_index = np.cumsum(keep) - 1
        rows = keep[self.pose_of]
        return Observations(
            self.joints_rad[keep],
            self.pts_phantom_mm[rows],
            self.meas_image_mm[rows],
            new_index[self.pose_of[rows]].astype(np.int64),
        )


def residuals_mm(model: ErrorModel, data: Observations, values: F64) -> F64:
    pred = model.predict(values, data.joints_rad, data.pts_phantom_mm, data.pose_of)
    return np.asarray((pred - data.meas_image_mm).reshape(-1), dtype=np.float64)


def _jacobian_fd(model: ErrorModel, data: Observations, values: F64) -> F64:
    """Central-difference Jacobian (3L, P) of the residuals (the reference for the analytic one)."""
    cols = []
    for j in range(len(values)):
        step = np.zeros_like(values)
        step[j] = FD_STEP
        cols.append(
            (residuals_mm(model, data, values + step) - residuals_mm(model, data, values - step))
            / (2 * FD_STEP)
        )
    return np.stack(cols, axis=1)


def _frames(model: ErrorModel, values: F64, joints_rad: F64) -> tuple[F64, dict[str, tuple[F64, F64]]]:
    """``image_from_phantom`` (K, 4, 4) and, per group, (R_A (K, 3, 3), o_F (K, 3)).

    ``A`` is everything left of the group's correction ``E``; ``F = A · E``.  A rotation
    parameter about ``d`` moves a point P by (R_A d) × (P − o_F) per radian, a translation
    parameter by R_A d per mm (exact at zero corrections, first-order in them otherwise).
    """
    c = _corrections(model.params, values)
    eye = np.eye(4)
    k = len(joints_rad)
    out: dict[str, tuple[F64, F64]] = {}
    cur = np.broadcast_to(model.y0, (k, 4, 4)).copy()
    e = c.get("image_from_robot", eye)
    out["image_from_robot"] = (cur[:, :3, :3].copy(), (cur @ e)[:, :3, 3].copy())
    cur = cur @ e
    ch = model.chain
    for i, name in enumerate(ch.joint_names):
        cur = cur @ ch.parent_from_joint[i]
        e = c.get(name, eye)
        out[name] = (cur[:, :3, :3].copy(), (cur @ e)[:, :3, 3].copy())
        cur = cur @ e
        cur[:, :3, :3] = cur[:, :3, :3] @ rotation_about(ch.axes[i], joints_rad[:, i])
    cur = cur @ ch.last_from_tool0 @ model.x0
    e = c.get("tool0_from_phantom", eye)
    out["tool0_from_phantom"] = (cur[:, :3, :3].copy(), (cur @ e)[:, :3, 3].copy())
    return cur @ e, out


def jacobian(model: ErrorModel, data: Observations, values: F64) -> F64:
    """Analytic Jacobian (3L, P) of the residuals (see :func:`_frames`)."""
    t, frames = _frames(model, values, data.joints_rad)
    tp = t[data.pose_of]
    world = np.einsum("lij,lj->li", tp[:, :3, :3], data.pts_phantom_mm) + tp[:, :3, 3]
    groups = [p.group for p in model.params]
    rot_a = np.stack([frames[g][0] for g in groups])  # (P, K, 3, 3)
    o_f = np.stack([frames[g][1] for g in groups])[:, data.pose_of]  # (P, L, 3)
    dirs = np.array([p.direction for p in model.params], dtype=np.float64)
    axis = np.einsum("pkij,pj->pki", rot_a, dirs)[:, data.pose_of]  # (P, L, 3)
    is_rot = np.array([p.kind == "rot" for p in model.params])
    cols = np.where(is_rot[:, None, None], np.cross(axis, world[None] - o_f), axis)
    return np.asarray(cols.reshape(len(groups), -1).T, dtype=np.float64)


def normalised_svd(jac: F64) -> tuple[F64, F64]:
    """Singular values (descending) and right singular vectors (rows) of the column-normalised
    Jacobian, from the eigen-decomposition of its P × P normal matrix (no tall-matrix LAPACK)."""
    norms = np.sqrt(np.einsum("ij,ij->j", jac, jac))
    norms[norms == 0.0] = 1.0
    jn = jac / norms
    lam, vec = np.linalg.eigh(np.einsum("ij,ik->jk", jn, jn))
    order = np.argsort(lam)[::-1]
    return np.sqrt(np.clip(lam[order], 0.0, None)), np.asarray(vec[:, order].T, dtype=np.float64)


def minimal_parameter_set(chain: SerialChain, parameter_set: str = "full") -> tuple[Parameter, ...]:
    """The identifiable subset of :func:`parameter_candidates` (see the module docstring).

    Structural: evaluated at 24 fixed generic configurations inside the joint
    limits with 4 non-coplanar points, so the result depends on the arm only.
    """
    cands = parameter_candidates(chain)
    if parameter_set == "hand-eye":
        return tuple(cands[:12])
    if parameter_set == "all":  # every joint origin in 6 DoF: only meaningful with priors (MAP)
        return tuple(cands)
    gen = np.random.default_rng(20181016)  # fixed: a structural property, not a sample
    lo, hi = np.maximum(chain.lower_rad, -2.0), np.minimum(chain.upper_rad, 2.0)
    q = lo + (hi - lo) * gen.uniform(0.1, 0.9, (24, chain.n_joints))
    pts = np.array([[40.0, 0, 0], [0, 40.0, 0], [0, 0, 40.0], [-30.0, -30.0, -30.0]])
    data = Observations(q, np.tile(pts, (24, 1)), np.zeros((96, 3)), np.repeat(np.arange(24), 4))
    model = ErrorModel(np.eye(4), np.eye(4), chain, tuple(cands))
    jac = jacobian(model, data, np.zeros(len(cands)))
    jac = jac / np.linalg.norm(jac, axis=0).clip(1e-300)
    basis = np.zeros((jac.shape[0], 0))
    kept: list[Parameter] = []
    for j, p in enumerate(cands):
        if parameter_set == "offsets" and j >= 12 and not p.name.endswith(" offset"):
            continue
        r = jac[:, j] - basis @ (basis.T @ jac[:, j])
        if np.linalg.norm(r) > STRUCTURAL_RANK_TOL:
            basis = np.column_stack([basis, r / np.linalg.norm(r)])
            kept.append(p)
    return tuple(kept)


def shah_ax_yb(a: Sequence[F64], b: Sequence[F64]) -> tuple[F64, F64]:
    """Solve A_i X = Y B_i for rigid X, Y (Shah 2013, doi:10.1115/1.4024473), numpy only.

    Rotation: (I ⊗ R_A) vec R_X − (R_Bᵀ ⊗ I) vec R_Y = 0 (column-major vec) stacked over the
    poses; the null vector is scaled to det +1 and projected onto SO(3).  Translation: linear
    least squares of R_A t_X − t_Y = R_Y t_B − t_A.

    Returns
    -------
    x, y : ndarray, shape (4, 4)
    """
    eye = np.eye(3)
    rows = [
        np.hstack([np.kron(eye, ai[:3, :3]), -np.kron(bi[:3, :3].T, eye)])
        for ai, bi in zip(a, b, strict=True)
    ]
    _, _, vt = np.linalg.svd(np.vstack(rows))
    v = vt[-1]
    vx, vy = v[:9].reshape(3, 3, order="F"), v[9:].reshape(3, 3, order="F")
    det_x = float(np.linalg.det(vx))
    scale = math.copysign(abs(det_x) ** (-1.0 / 3.0), det_x) if det_x != 0.0 else 1.0
    rx, _ = nearest_rotation(scale * vx)
    ry, _ = nearest_rotation(scale * vy)
    lhs = np.vstack([np.hstack([ai[:3, :3], -eye]) for ai in a])
    rhs = np.concatenate([ry @ bi[:3, 3] - ai[:3, 3] for ai, bi in zip(a, b, strict=True)])
    t, *_ = np.linalg.lstsq(lhs, rhs, rcond=None)
    return make_transform(rx, t[:3]), make_transform(ry, t[3:])


def initial_estimate(
    poses: Sequence[MatchedPose], chain: SerialChain, centres_phantom_mm: F64
) -> tuple[F64, F64]:
    """(image_from_robot, tool0_from_phantom) from per-pose rigid fits and Shah with nominal FK."""
    robot_from_tool0 = chain.robot_from_tool0_batch(np.stack([p.joints_rad for p in poses]))
    image_from_phantom = [fit_rigid(centres_phantom_mm[p.sphere_indices], p.centres_image_mm) for p in poses]
    # Y B X = A  ⇔  B X = Y⁻¹ A: Shah's A X = Y B with A = robot_from_tool0, B = image_from_phantom
    x, robot_from_image = shah_ax_yb(list(robot_from_tool0), image_from_phantom)
    return invert(robot_from_image), x


def stack_observations(poses: Sequence[MatchedPose], centres_phantom_mm: F64) -> Observations:
    for p in poses:
        if len(p.sphere_indices) != len(p.centres_image_mm) or len(p.sphere_indices) < 3:
            raise CalibrationError(
                f"scan {p.name}: needs ≥ 3 matched spheres paired with centres, "
                f"got {len(p.sphere_indices)} indices / {len(p.centres_image_mm)} centres"
            )
    return Observations(
        np.stack([np.asarray(p.joints_rad, dtype=np.float64) for p in poses]),
        np.concatenate([centres_phantom_mm[p.sphere_indices] for p in poses]),
        np.concatenate([np.asarray(p.centres_image_mm, dtype=np.float64) for p in poses]),
        np.concatenate([np.full(len(p.sphere_indices), i, dtype=np.int64) for i, p in enumerate(poses)]),
    )


def predict_image_mm(
    result: CalibrationResult,
    joints_rad: ArrayLike,
    centres_phantom_mm: ArrayLike,
    image_from_robot: ArrayLike | None = None,
) -> F64:
    """Sphere centres (image mm) the calibration predicts at ``joints_rad`` (optionally another Y)."""
    y = result.image_from_robot if image_from_robot is None else as_transform(image_from_robot)
    t = y @ result.chain.robot_from_tool0(joints_rad) @ result.tool0_from_phantom
    pts = np.asarray(centres_phantom_mm, dtype=np.float64)
    return np.asarray(pts @ t[:3, :3].T + t[:3, 3], dtype=np.float64)
