"""Verification of a registration on a second scan (Bai et al. 2018 §3, eq. 10, Figure 7).

Move the robot, scan again: the sphere centres predicted through the current
registration, ``image_from_robot @ p_robot`` (robot centres from kinematics at
the new pose), are compared with the centres detected in the new scan.  The
per-sphere position error e_k = |T·p_r,k − p_i,k| (eq. 10) is a measured TRE of
the whole chain (kinematics, detection, registration), unlike FRE.

Pairs are made by predicted position only (nearest detection within a gate,
each detection used once): the registration itself supplies the labels, so no
symmetry search is needed, and a bad registration shows up as large errors or
too few pairs, never as a silently re-fitted pose.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.spatial import cKDTree

from registration.arrays import F64
from registration.errors import TooFewSpheresError
from registration.matching.icp import unique_pairs
from registration.matching.records import RegistrationParams
from registration.matching.rigid import as_points
from registration.model.frames import as_transform

I64 = NDArray[np.int64]


@dataclass(frozen=True, eq=False)
class VerificationResult:
    """Per-sphere position errors of a registration on a second scan.

    Attributes
    ----------
    errors_mm : ndarray, shape (K,), float64
        |image_from_robot · p_robot − p_image| per matched sphere (eq. 10).
    robot_indices, image_indices : ndarray, shape (K,), int64
    mean_mm, rms_mm, max_mm, p95_mm : float
    n_expected, n_detected, n_matched : int
    gate_mm : float
    """

    errors_mm: F64
    robot_indices: I64
    image_indices: I64
    mean_mm: float
    rms_mm: float
    max_mm: float
    p95_mm: float = 0.0
    n_expected: int = 0
    n_detected: int = 0
    n_matched: int = 0
    gate_mm: float = 0.0
    predicted_image_mm: F64 = field(default_factory=lambda: np.empty((0, 3)))
    image_mm: F64 = field(default_factory=lambda: np.empty((0, 3)))

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready dict: the ``oarmreg verify --json`` format."""
        return {
            "n_expected": self.n_expected,
            "n_detected": self.n_detected,
            "n_matched": self.n_matched,
            "mean_mm": self.mean_mm,
            "rms_mm": self.rms_mm,
            "max_mm": self.max_mm,
            "p95_mm": self.p95_mm,
            "gate_mm": self.gate_mm,
            "spheres": [
                {
                    "index": int(r),
                    "image_index": int(i),
                    "predicted_image_mm": [float(v) for v in self.predicted_image_mm[r]]
                    if len(self.predicted_image_mm)
                    else None,
                    "image_mm": [float(v) for v in self.image_mm[i]] if len(self.image_mm) else None,
                    "error_mm": float(e),
                }
                for r, i, e in zip(self.robot_indices, self.image_indices, self.errors_mm, strict=True)
            ],
        }


def verify_registration(
    image_from_robot: ArrayLike,
    robot_mm: ArrayLike,
    image_mm: ArrayLike,
    *,
    params: RegistrationParams = RegistrationParams(),
    gate_mm: float | None = None,
) -> VerificationResult:
    """Per-sphere position errors of ``image_from_robot`` on a second scan (paper eq. 10).

    Parameters
    ----------
    image_from_robot : array_like, shape (4, 4)
        The registration under test.
    robot_mm : array_like, shape (N, 3)
        Sphere centres at the new robot pose, robot frame, mm.
    image_mm : array_like, shape (M, 3)
        Detections in the second scan, image frame (LPS), mm, any order.
    params : RegistrationParams
        ``verify_gate_mm`` and ``min_matched`` are used.
    gate_mm : float, optional
        Overrides ``params.verify_gate_mm``.

    Raises
    ------
    NotRigidError
        ``image_from_robot`` is not a proper rigid transform.
    TooFewSpheresError
        Fewer than ``params.min_matched`` spheres lie within the gate of their prediction.
    """
    t = as_transform(image_from_robot, "image_from_robot")
    robot = as_points(robot_mm, "robot points")
    image = as_points(image_mm, "image points")
    gate = params.verify_gate_mm if gate_mm is None else float(gate_mm)
    predicted = robot @ t[:3, :3].T + t[:3, 3]
    if len(image) == 0:
        r_idx = i_idx = np.empty(0, dtype=np.int64)
    else:
        d, j = cKDTree(image).query(predicted, distance_upper_bound=gate)
        r_idx, i_idx = unique_pairs(d, np.minimum(j, len(image) - 1).astype(np.int64))
    if len(r_idx) < params.min_matched:
        raise TooFewSpheresError(
            f"verification: only {len(r_idx)} of {len(robot)} predicted spheres have a detection within "
            f"{gate:g} mm ({len(image)} detected, {params.min_matched} needed). Either the registration is "
            "off by more than the gate, or the robot points do not belong to this scan's pose"
        )
    err = np.linalg.norm(predicted[r_idx] - image[i_idx], axis=1)
    return VerificationResult(
        errors_mm=np.asarray(err, dtype=np.float64),
        robot_indices=r_idx,
        image_indices=i_idx,
        mean_mm=float(np.mean(err)),
        rms_mm=float(np.sqrt(np.mean(err**2))),
        max_mm=float(np.max(err)),
        p95_mm=float(np.percentile(err, 95)),
        n_expected=len(robot),
        n_detected=len(image),
        n_matched=len(r_idx),
        gate_mm=gate,
        predicted_image_mm=np.asarray(predicted, dtype=np.float64),
        image_mm=image,
    )
