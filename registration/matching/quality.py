"""Quality figures of a point-based rigid registration (design.md §5).

FRE is the RMS residual over the N matched spheres; it is *not* accuracy:
TRE and FRE are statistically independent to first order (Danilchenko &
Fitzpatrick 2011, IEEE TMI 30(3), PMC4607070; research/registration-ecosystem.md §2).
What is reported instead is Fitzpatrick, West & Maurer 1998, "Predicting error
in rigid-body point-based registration", IEEE TMI 17(5):694
(doi:10.1109/42.736021):

* eq. 10: ⟨FRE²⟩ ≈ (1 − 2/N)·⟨FLE²⟩, hence FLE ≈ FRE·√(N/(N−2));
* eq. 46: ⟨TRE²(r)⟩ ≈ (⟨FLE²⟩/N)·(1 + ⅓ Σ_k d_k²/f_k²), with d_k the distance of
  target r from principal axis k of the fiducial configuration and f_k the
  RMS distance of the fiducials from that axis.

FLE here is the total localisation error of both spaces (robot and image).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Final

import numpy as np
from numpy.typing import ArrayLike

from registration.arrays import F64
from registration.errors import DegenerateConfigurationError

MIN_COLLINEAR_RATIO: Final = 1e-3
"""λ2/λ1 of the centred point covariance below this = collinear: the rotation about the line is
undetermined.  1e-3 is a spread ratio of ≈ 3 % (√1e-3); SlicerIGT refuses at an absolute 1e-4."""

MIN_COPLANAR_RATIO: Final = 1e-3
"""λ3/λ1 below this = coplanar: a planar set is its own mirror image, so handedness (and a
flipped slice axis) cannot be checked, and off-plane TRE grows (research §1.6)."""


@dataclass(frozen=True)
class Conditioning:
    """Principal spread of a point configuration.

    Attributes
    ----------
    eigenvalues_mm2 : tuple of float
        λ1 ≥ λ2 ≥ λ3 of the centred covariance (mm²).
    collinearity : float
        λ2/λ1 (0 = collinear).
    planarity : float
        λ3/λ1 (0 = coplanar).
    """

    eigenvalues_mm2: tuple[float, float, float]
    collinearity: float
    planarity: float


def fre_mm(residuals_mm: ArrayLike) -> float:
    """Fiducial registration error: RMS of the per-sphere residual distances (mm)."""
    r = np.asarray(residuals_mm, dtype=np.float64).reshape(-1)
    if len(r) == 0:
        raise ValueError("fre_mm: no residuals")
    return float(np.sqrt(np.mean(r**2)))


def fle_from_fre(fre: float, n: int) -> float:
    """FLE (RMS, 3-D, both spaces) implied by FRE: FRE·√(N/(N−2)) (Fitzpatrick 1998 eq. 10).

    Raises
    ------
    ValueError
        N ≤ 2 (a 3-D rigid fit of ≤ 2 points has no residual degrees of freedom).
    """
    if n <= 2:
        raise ValueError(f"fle_from_fre: need N > 2 fiducials, got {n}")
    return float(fre * np.sqrt(n / (n - 2.0)))


def fre_from_fle(fle: float, n: int) -> float:
    """Expected FRE for a given FLE: FLE·√(1 − 2/N) (Fitzpatrick 1998 eq. 10)."""
    if n <= 2:
        raise ValueError(f"fre_from_fle: need N > 2 fiducials, got {n}")
    return float(fle * np.sqrt(1.0 - 2.0 / n))


def principal_axes(fiducials_mm: ArrayLike) -> tuple[F64, F64, F64]:
    """Centroid (3,), eigenvalues (3,) descending (mm²) and axes (3, 3; columns) of a configuration."""
    x = np.asarray(fiducials_mm, dtype=np.float64)
    c = x.mean(axis=0)
    xc = x - c
    w, v = np.linalg.eigh(xc.T @ xc / len(x))
    order = np.argsort(w)[::-1]
    return (
        c,
        np.asarray(np.maximum(w[order], 0.0), dtype=np.float64),
        np.asarray(v[:, order], dtype=np.float64),
    )


def predicted_tre_mm(fle: float, fiducials_mm: ArrayLike, targets_mm: ArrayLike) -> F64:
    """Fitzpatrick's predicted RMS TRE at each target (1998 eq. 46).

    Parameters
    ----------
    fle : float
        RMS fiducial localisation error (3-D, both spaces), mm.
    fiducials_mm : array_like, shape (N, 3)
        The matched fiducials in the frame of the targets (here: robot frame).
    targets_mm : array_like, shape (T, 3)
        Target points, same frame.

    Returns
    -------
    ndarray, shape (T,), float64
        √⟨TRE²⟩ at each target, mm.
    """
    x = np.asarray(fiducials_mm, dtype=np.float64)
    r = np.asarray(targets_mm, dtype=np.float64).reshape(-1, 3)
    n = len(x)
    c, _, axes = principal_axes(x)
    xc = x - c
    rc = r - c
    sum_ratio = np.zeros(len(r))
    for k in range(3):
        u = axes[:, k]
        f2 = float(np.mean(np.einsum("ij,ij->i", xc, xc) - (xc @ u) ** 2))  # RMS² distance from axis k
        d2 = np.einsum("ij,ij->i", rc, rc) - (rc @ u) ** 2
        if f2 <= 0.0:
            raise DegenerateConfigurationError(
                "predicted TRE: the fiducials are collinear, the rotation about their line is undetermined"
            )
        sum_ratio += d2 / f2
    return np.asarray(np.sqrt(fle**2 / n * (1.0 + sum_ratio / 3.0)), dtype=np.float64)


def conditioning(points_mm: ArrayLike) -> Conditioning:
    """Collinearity (λ2/λ1) and planarity (λ3/λ1) of a point configuration."""
    _, w, _ = principal_axes(points_mm)
    l1 = float(w[0])
    if l1 <= 0.0:
        return Conditioning((0.0, 0.0, 0.0), 0.0, 0.0)
    return Conditioning((float(w[0]), float(w[1]), float(w[2])), float(w[1]) / l1, float(w[2]) / l1)


def check_configuration(
    points_mm: ArrayLike,
    what: str,
    *,
    min_collinear_ratio: float = MIN_COLLINEAR_RATIO,
    min_coplanar_ratio: float = MIN_COPLANAR_RATIO,
) -> Conditioning:
    """Refuse a collinear or coplanar configuration.

    Raises
    ------
    DegenerateConfigurationError
        λ2/λ1 < ``min_collinear_ratio`` (collinear) or λ3/λ1 < ``min_coplanar_ratio``
        (coplanar); the message names ``what`` and gives the ratio.
    """
    x = np.asarray(points_mm, dtype=np.float64)
    if len(x) < 3:
        raise DegenerateConfigurationError(f"{what}: {len(x)} point(s); a rigid registration needs >= 3")
    cond = conditioning(x)
    if cond.collinearity < min_collinear_ratio:
        raise DegenerateConfigurationError(
            f"{what}: the {len(x)} spheres are (nearly) collinear (λ2/λ1 = {cond.collinearity:.2e} < "
            f"{min_collinear_ratio:g}); the rotation about their line is undetermined. Use spheres on "
            "more than one row/face of the phantom"
        )
    if cond.planarity < min_coplanar_ratio:
        raise DegenerateConfigurationError(
            f"{what}: the {len(x)} spheres are (nearly) coplanar (λ3/λ1 = {cond.planarity:.2e} < "
            f"{min_coplanar_ratio:g}); handedness cannot be checked and off-plane error grows. Make "
            "sure spheres on at least two faces of the phantom are inside the scanned volume"
        )
    return cond


def assert_proper_rotation(transform: F64, tol: float = 1e-6) -> float:
    """Return det(R) of a 4 × 4 transform after checking it is +1 within ``tol``.

    Raises
    ------
    AssertionError
        det(R) is not +1: a bug (the fits always apply the determinant fix).
    """
    det = float(np.linalg.det(transform[:3, :3]))
    if abs(det - 1.0) > tol:
        raise AssertionError(
            f"registration produced det(R) = {det:.6f}; the determinant fix must prevent this"
        )
    return det
