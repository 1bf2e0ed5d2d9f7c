"""The phantom's face offset: one depth β shared by every sphere of a scan, fitted with the pose.

A detected sphere centre sits systematically deeper in (or higher out of) its hole than the
phantom file says: scatter and detector blur acting on a sphere seated in a drilled hole pull the
estimate along the hole's axis, by an amount and a sign that depend on how the hole is built and
on the estimator (measured: −0.007 … −0.024 mm on unseen scans, +0.004 … +0.019 mm on the
simulator's tight fit).  A pull shared by every sphere along its own outward axis shrinks or grows
the detected pattern and does not average out in a rigid fit, so it is measured in every scan:

    c_i = R · (p_i + β · n_i) + t          (7 parameters: R, t and β)

with p_i the hole centre, n_i its outward unit axis (both in the model frame: the phantom's, or the
robot's after the kinematics) and c_i the detected centre.  The centres are reported with β · n_i
removed; β and its standard error are kept in the records.  β is solved by Gauss–Newton from the
Kabsch pose (β = 0): three linearised 7 × 7 steps converge to rounding for |β| ≪ the pattern size.

The standard error is the usual least-squares one, σ̂ · √((JᵀJ)⁻¹)_ββ with σ̂² the residual sum of
squares over 3N − 7 degrees of freedom: it assumes independent isotropic localisation errors, so
it is a floor where the errors correlate between spheres.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Final

import numpy as np
from numpy.typing import ArrayLike

from registration.arrays import F64
from registration.errors import FaceOffsetError, PointSetError
from registration.matching.rigid import as_points, fit_rigid_unchecked

MAX_FACE_OFFSET_MM: Final = 0.15
"""Largest |β| accepted.  Origin: the pulls measured along the hole axis are 0.004–0.024 mm for the
chosen estimators and 0.05–0.09 mm for the worst one (``model``); the phantom is
machined to ±0.02 mm (Bai 2018 §2.1).  A shared offset beyond 0.15 mm is not a detection bias: the
spheres are not pressed home, the phantom file's ``hole_centre_depth_mm`` or
``sphere_diameter_mm`` is wrong, or the spheres are of another size than the file says."""


GAUSS_NEWTON_STEPS: Final = 3
"""Linearised steps from the Kabsch pose at β = 0; the first is exact to O(β · angle), the third
moves β by < 1e-12 mm on the simulator's scans."""


@dataclass(frozen=True, eq=False)
class FaceOffsetFit:
    """The 7-parameter fit of one scan's matched spheres.

    Attributes
    ----------
    beta_mm : float
        Shared offset along each hole's outward axis, mm (negative: deeper in the hole).
    beta_se_mm : float
        Its least-squares standard error, mm (NaN with fewer than 3 faces' worth of data).
    image_from_model : ndarray, shape (4, 4), float64
        The rigid part: c_i ≈ image_from_model @ (p_i + β n_i).
    centres_image_mm : ndarray, shape (K, 3), float64
        The detected centres with β · R n_i removed (image frame, LPS mm), input order.
    residuals_mm : ndarray, shape (K,), float64
        Distances of the corrected centres from the fitted model points.
    """

    beta_mm: float
    beta_se_mm: float
    image_from_model: F64
    centres_image_mm: F64
    residuals_mm: F64


def _skew(v: F64) -> F64:
    """(K, 3, 3) cross-product matrices [v]× of the rows of ``v``."""
    z = np.zeros(len(v))
    return np.stack(
        [
            np.stack([z, -v[:, 2], v[:, 1]], axis=1),
            np.stack([v[:, 2], z, -v[:, 0]], axis=1),
            np.stack([-v[:, 1], v[:, 0], z], axis=1),
        ],
        axis=1,
    )


def _rotation_from_vector(w: F64) -> F64:
    """Rodrigues: the rotation exp([w]×)."""
    angle = float(np.linalg.norm(w))
    if angle < 1e-15:
        return np.eye(3)
    k = _skew((w / angle).reshape(1, 3))[0]
    return np.asarray(np.eye(3) + math.sin(angle) * k + (1.0 - math.cos(angle)) * (k @ k), dtype=np.float64)


def fit_face_offset(model_mm: ArrayLike, axes_model: ArrayLike, image_mm: ArrayLike) -> FaceOffsetFit:
    """Fit c_i = R (p_i + β n_i) + t to matched pairs (Gauss–Newton on 7 parameters).

    Parameters
    ----------
    model_mm : array_like, shape (K, 3)
        Hole (sphere) centres p_i in the model frame (phantom or robot), mm.
    axes_model : array_like, shape (K, 3)
        Outward unit axes n_i of the same holes, same frame.
    image_mm : array_like, shape (K, 3)
        Detected centres c_i, image frame (LPS), mm; row i pairs with row i above.

    Returns
    -------
    FaceOffsetFit

    Raises
    ------
    PointSetError
        Mismatched or malformed arrays, fewer than 3 pairs.
    """
    p = as_points(model_mm, "model points")
    n = as_points(axes_model, "hole axes")
    c = as_points(image_mm, "image points")
    if not (len(p) == len(n) == len(c)) or len(p) < 3:
        raise PointSetError(
            f"face-offset fit needs ≥ 3 matched pairs with one axis each, got {len(p)} points, "
            f"{len(n)} axes, {len(c)} detections"
        )
    t_fit = fit_rigid_unchecked(p, c)
    rot, trans, beta = t_fit[:3, :3].copy(), t_fit[:3, 3].copy(), 0.0
    jac = np.zeros((3 * len(p), 7))
    for _ in range(GAUSS_NEWTON_STEPS):
        q = (p + beta * n) @ rot.T  # R (p + β n)
        r = (q + trans - c).reshape(-1)
        # d r_i = −[q_i]× ω + dt + R n_i dβ  (left-multiplied small rotation ω)
        jac[:, :3] = -_skew(q).reshape(-1, 3)
        jac[:, 3:6] = np.tile(np.eye(3), (len(p), 1))
        jac[:, 6] = (n @ rot.T).reshape(-1)
        step, *_ = np.linalg.lstsq(jac, -r, rcond=None)
        d_rot = _rotation_from_vector(np.asarray(step[:3], dtype=np.float64))
        rot = d_rot @ rot
        trans = d_rot @ trans + step[3:6]  # the rotation acts on R p + t about the image origin
        beta += float(step[6])
    q = (p + beta * n) @ rot.T + trans
    res = c - q
    dof = 3 * len(p) - 7
    se = math.nan
    if dof > 0:
        jtj = jac.T @ jac
        cov_bb = float(np.linalg.pinv(jtj)[6, 6])
        se = math.sqrt(float(np.sum(res**2)) / dof * cov_bb) if cov_bb > 0 else math.nan
    image_from_model = np.eye(4)
    image_from_model[:3, :3], image_from_model[:3, 3] = rot, trans
    return FaceOffsetFit(
        beta_mm=beta,
        beta_se_mm=se,
        image_from_model=image_from_model,
        centres_image_mm=c - beta * (n @ rot.T),
        residuals_mm=np.linalg.norm(res, axis=1),
    )


def check_face_offset(
    fit: FaceOffsetFit, hole_ids: tuple[str, ...], max_abs_mm: float = MAX_FACE_OFFSET_MM
) -> None:
    """Refuse a scan whose shared face offset exceeds ``max_abs_mm`` (FaceOffsetError), naming the holes."""
    if abs(fit.beta_mm) <= max_abs_mm:
        return
    where = "deeper in" if fit.beta_mm < 0 else "higher out of"
    named = ", ".join(hole_ids[:6]) + (f" and {len(hole_ids) - 6} more" if len(hole_ids) > 6 else "")
    raise FaceOffsetError(
        f"the detected spheres sit {abs(fit.beta_mm):.3f} ± {fit.beta_se_mm:.3f} mm {where} their holes "
        f"({named}) than the phantom file says, all together; at most {max_abs_mm:g} mm is a detection "
        "bias. Check that every sphere is pressed home, and the phantom file's hole_centre_depth_mm and "
        "sphere_diameter_mm against the phantom"
    )
