"""Frame names and rigid-transform helpers.

Transforms are 4 × 4 float64 arrays named ``<to>_from_<from>``: they map points
expressed in frame *from* into frame *to* (``p_image = image_from_robot @
p_robot``).  Point sets are (N, 3) float64 arrays in millimetres.
"""

from __future__ import annotations

from typing import Final

import numpy as np
from numpy.typing import ArrayLike

from registration.arrays import F64
from registration.errors import NotRigidError

FRAMES: Final = ("voxel", "image", "robot", "tool0", "phantom")
"""Every frame the project names (design.md §3)."""

RIGID_TOLERANCE: Final = 1e-6
"""Max |RᵀR − I| and |det R − 1| accepted as rigid (float64 round-off of a chain of ~10 products)."""


def as_transform(matrix: ArrayLike, name: str = "transform", *, tol: float = RIGID_TOLERANCE) -> F64:
    """Return ``matrix`` as a checked 4 × 4 rigid transform (float64).

    Raises
    ------
    NotRigidError
        If the shape is not 4 × 4, the last row is not (0, 0, 0, 1), the
        rotation block is not orthonormal or its determinant is not +1.  The
        message names ``name`` and reports the residual.
    """
    m = np.asarray(matrix, dtype=np.float64)
    if m.shape != (4, 4):
        raise NotRigidError(f"{name}: expected a 4 × 4 matrix, got shape {m.shape}")
    if not np.all(np.isfinite(m)):
        raise NotRigidError(f"{name}: contains NaN or infinite values")
    last_row_err = float(np.max(np.abs(m[3] - (0.0, 0.0, 0.0, 1.0))))
    if last_row_err > tol:
        raise NotRigidError(f"{name}: last row must be (0, 0, 0, 1), found {m[3].tolist()}")
    r = m[:3, :3]
    ortho_err = float(np.max(np.abs(r.T @ r - np.eye(3))))
    det = float(np.linalg.det(r))
    if ortho_err > tol or abs(det - 1.0) > tol:
        kind = "a reflection (det = −1)" if det < 0 else "not a proper rotation"
        raise NotRigidError(
            f"{name}: rotation block is {kind}: |RᵀR − I| = {ortho_err:.2e}, det = {det:.6f} "
            f"(tolerance {tol:g}); check the matrix for scaling, shear or a mirrored axis"
        )
    return m


def make_transform(rotation: ArrayLike, translation_mm: ArrayLike) -> F64:
    """Build a 4 × 4 transform from a 3 × 3 rotation and a translation in mm."""
    t = np.eye(4)
    t[:3, :3] = np.asarray(rotation, dtype=np.float64)
    t[:3, 3] = np.asarray(translation_mm, dtype=np.float64).reshape(3)
    return t


def invert(transform: ArrayLike) -> F64:
    """Inverse of a rigid transform (exact: Rᵀ, −Rᵀt)."""
    m = np.asarray(transform, dtype=np.float64)
    r = m[:3, :3]
    out = np.eye(4)
    out[:3, :3] = r.T
    out[:3, 3] = -r.T @ m[:3, 3]
    return out


def apply(transform: ArrayLike, points_mm: ArrayLike) -> F64:
    """Map (N, 3) points through a 4 × 4 transform; returns (N, 3) float64."""
    m = np.asarray(transform, dtype=np.float64)
    p = np.asarray(points_mm, dtype=np.float64)
    single = p.ndim == 1
    p2 = p.reshape(-1, 3)
    out = p2 @ m[:3, :3].T + m[:3, 3]
    return out.reshape(3) if single else out


def rotation_angle_deg(rotation: ArrayLike) -> float:
    """Rotation angle of a 3 × 3 rotation matrix, in degrees (0…180)."""
    r = np.asarray(rotation, dtype=np.float64)
    c = (float(np.trace(r)) - 1.0) / 2.0
    return float(np.degrees(np.arccos(np.clip(c, -1.0, 1.0))))


def transform_from_xyz_rpy(translation_mm: ArrayLike, rpy_deg: ArrayLike) -> F64:
    """Transform from a translation (mm) and roll-pitch-yaw angles (deg).

    Convention as URDF ``<origin rpy>``: R = Rz(yaw) · Ry(pitch) · Rx(roll),
    i.e. extrinsic x-y-z rotations.
    """
    from scipy.spatial.transform import Rotation

    r = Rotation.from_euler("xyz", np.asarray(rpy_deg, dtype=np.float64).reshape(3), degrees=True)
    return make_transform(r.as_matrix(), translation_mm)
