"""Pre-registration from four named marks (Bai et al. 2018 §2.4, eq. 5–8).

The paper stacks four non-coplanar marks as homogeneous columns,
P_r = [[x₁ … x₄], [y₁ … y₄], [z₁ … z₄], [1 … 1]] in robot (patient) space and
P_i likewise in image space, and takes ᶦT_r¹ = P_i · P_r⁻¹ (eq. 7).  With four
noisy marks that matrix is a general *affine* map (12 DoF) with a little scale
and shear; it is projected here to the nearest proper rotation (polar
decomposition via SVD with the determinant fix) and the translation that best
maps the marks' centroid, and the non-rigidity is reported.  ICP
(:mod:`registration.matching.icp`) refines it from there.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Final

import numpy as np
from numpy.typing import ArrayLike

from registration.arrays import F64
from registration.errors import (
    DegenerateConfigurationError,
    MirroredInputError,
    PreregistrationError,
)
from registration.matching.rigid import nearest_rotation

MIN_MARK_PLANARITY: Final = 1e-3
"""λ3/λ1 of the four marks below this = (near) coplanar: P_r is (nearly) singular (eq. 7)."""

MAX_NONRIGIDITY: Final = 0.10
"""Largest |singular value − 1| of the affine accepted: 10 % scale/shear means mislabelled marks
(with σ ≈ 0.25 mm on ~60 mm spreads the expected value is < 1 %)."""


@dataclass(frozen=True, eq=False)
class PreregResult:
    """Outcome of :func:`preregister`.

    Attributes
    ----------
    affine : ndarray, shape (4, 4)
        P_i · P_r⁻¹ (eq. 7), exact at the four marks.
    image_from_robot : ndarray, shape (4, 4)
        The nearest proper rigid transform.
    singular_values : ndarray, shape (3,)
        Of the affine's linear part (all 1 when rigid).
    nonrigidity : float
        max |singular value − 1|.
    rms_mm : float
        RMS distance between the rigid and the affine image of the marks (mm).
    max_distance_mismatch_mm : float
        Largest difference of the six inter-mark distances between spaces (mm).
    """

    affine: F64
    image_from_robot: F64
    singular_values: F64
    nonrigidity: float
    rms_mm: float
    max_distance_mismatch_mm: float


def preregister(
    marks_robot_mm: ArrayLike,
    marks_image_mm: ArrayLike,
    *,
    min_planarity: float = MIN_MARK_PLANARITY,
    max_nonrigidity: float = MAX_NONRIGIDITY,
) -> PreregResult:
    """Paper eq. 7 on four marks, projected to the nearest rigid transform.

    Parameters
    ----------
    marks_robot_mm : array_like, shape (4, 3)
        The marks in robot space (mm).
    marks_image_mm : array_like, shape (4, 3)
        The same marks, same order, in image space (LPS mm).

    Raises
    ------
    DegenerateConfigurationError
        The robot or image marks are (nearly) coplanar.
    MirroredInputError
        det of the affine is negative: the marks are mislabelled or the image is mirrored.
    PreregistrationError
        The affine is far from rigid (> ``max_nonrigidity``): mislabelled marks.
    """
    pr = np.asarray(marks_robot_mm, dtype=np.float64)
    pi = np.asarray(marks_image_mm, dtype=np.float64)
    if pr.shape != (4, 3) or pi.shape != (4, 3):
        raise ValueError(f"preregister: need (4, 3) marks in each space, got {pr.shape} and {pi.shape}")
    for name, pts in (("robot", pr), ("image", pi)):
        c = pts - pts.mean(axis=0)
        w = np.sort(np.linalg.eigvalsh(c.T @ c / 4.0))[::-1]
        if w[0] <= 0 or w[2] / w[0] < min_planarity:
            raise DegenerateConfigurationError(
                f"pre-registration: the four {name} marks are (nearly) coplanar (λ3/λ1 = "
                f"{(w[2] / w[0]) if w[0] > 0 else 0.0:.2e} < {min_planarity:g}); eq. 7 needs P_r invertible. "
                "Pick four holes that are not on one face"
            )
    p_r = np.vstack([pr.T, np.ones(4)])  # eq. 5
    p_i = np.vstack([pi.T, np.ones(4)])  # eq. 6
    affine = p_i @ np.linalg.inv(p_r)  # eq. 7
    lin = affine[:3, :3]
    if np.linalg.det(lin) <= 0.0:
        raise MirroredInputError(
            "pre-registration: the four marks map with a reflection (det < 0): either the marks are "
            "mislabelled, or the image matches the robot points only as a mirror image: check slice "
            "order / ImageOrientationPatient / a flipped axis in the export"
        )
    rot, s = nearest_rotation(lin)
    nonrigidity = float(np.max(np.abs(s - 1.0)))
    t = pi.mean(axis=0) - rot @ pr.mean(axis=0)
    rigid = np.eye(4)
    rigid[:3, :3] = rot
    rigid[:3, 3] = t
    rigid_marks = pr @ rot.T + t
    rms = float(np.sqrt(np.mean(np.sum((rigid_marks - pi) ** 2, axis=1))))
    iu = np.triu_indices(4, 1)
    dr = np.linalg.norm(pr[:, None] - pr[None], axis=2)[iu]
    di = np.linalg.norm(pi[:, None] - pi[None], axis=2)[iu]
    mismatch = float(np.max(np.abs(dr - di)))
    if nonrigidity > max_nonrigidity:
        raise PreregistrationError(
            f"pre-registration: the four marks are not related by a rigid motion (scale/shear "
            f"{nonrigidity:.1%} > {max_nonrigidity:.0%}, inter-mark distances differ by up to "
            f"{mismatch:.1f} mm); check that each robot hole is paired with its own image sphere"
        )
    return PreregResult(
        affine=np.asarray(affine, dtype=np.float64),
        image_from_robot=rigid,
        singular_values=s,
        nonrigidity=nonrigidity,
        rms_mm=rms,
        max_distance_mismatch_mm=mismatch,
    )
