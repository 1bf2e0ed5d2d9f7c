"""Circle recognition on one slice patch by moment invariants, after Bai et al. 2018.

The paper (doi:10.1088/1742-6596/1016/1/012006, §2.2 and §3): Gaussian filter,
Canny edges, contours, the moment invariants of each contour (Hu 1962,
doi:10.1109/TIT.1962.1057692, and the eight "united moment invariants" of
Sun et al. 2003, eq. 4 of the paper), then an ellipse fit whose centre is the
circle centre and whose minor semi-axis is the circle radius.

The united invariants are degenerate on discs (image-side.md §2.2): φ2 … φ7
are 0 for a disc, so θ2 … θ8 are 0/0, and φ5, φ6 may be slightly negative, so
√φ5 is NaN.  They are computed here with guards (signed square roots, an
epsilon in every denominator) and reported as features; acceptance rests on
the quantities that are well defined on discs: φ1 ≈ 1/(2π), θ1 = √φ2/φ1 ≈ 0,
the circularity 4πA/P² and the fitted ellipse's axis ratio.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Final

import cv2
import numpy as np
from numpy.typing import NDArray

from registration.arrays import F64

PHI1_DISC: Final = 1.0 / (2.0 * math.pi)
"""Hu's φ1 of an ideal disc (η20 + η02 = 1/(2π))."""

UMI_EPS: Final = 1e-30
"""Guard added to |denominators| of the united invariants: φ_k of a contour are ≥ ~1e-20 when non-zero."""


@dataclass(frozen=True)
class CircleParams:
    """Acceptance rules of a contour as a sphere cross-section.

    Attributes
    ----------
    blur_sigma_px : float
        Gaussian pre-filter (paper §3); 3 × 3 kernel at 0.8 px as in image-side.md §3.2.
    canny_low, canny_high : float
        Canny hysteresis thresholds on the 8-bit windowed patch (image-side.md §3.2: 50 / 150).
    window_hu : tuple of float
        HU window mapped to 0 … 255 before Canny: a "metal window".  The
        spheres sit 1.25 mm under the cube face, so the plastic/air edge
        (≈ −1000 → +300 HU) and photon-starvation streaks (down to −1024 HU)
        touch them; below 500 HU everything maps to 0 and only the metal's
        edge remains (on the simulator, -1000 … 3071 lost 12 of 28 spheres
        to merged contours, 500 … 3071 lost 2).
    phi1_range : tuple of float
        Accepted Hu φ1.  Disc = 0.159; Canny contours of 2.5 mm sphere slices
        measured 0.160–0.187 (image-side.md §2.2), an ellipse of axis ratio
        0.7 gives 0.166.
    theta1_max : float
        Max θ1 = √φ2/φ1 (0 for a disc; ≤ 0.34 measured on clean sphere
        contours, image-side.md §2.2; streak-bloomed sections in the simulator
        reach 0.45, an ellipse of axis ratio 0.5 gives ≥ 0.6).
    circularity_min : float
        Min 4πA/P².  Staircase perimeters of 3–5 px discs measure 0.75–0.9
        (tests/unit/registration/imaging/test_circles.py), a square is 0.785 but fails φ1 / θ1 only
        when elongated, so this is a loose gate.
    axis_ratio_min : float
        Min minor/major axis of the fitted ellipse.  A sphere section is a
        circle; pixelation of a 3 px radius gives ≥ 0.85, blooming along a
        streak in the simulator down to 0.69; a rod section seen obliquely
        or an ellipse of ratio 0.6 is refused.
    min_points : int
        ``cv2.fitEllipse`` needs ≥ 5 points.
    radius_range_mm : tuple of float
        Accepted minor semi-axis.  Upper bound: the apparent radius of a
        bloomed 2.5 mm sphere is ≤ ~1.9 mm (image-side.md §3.3) plus margin.
    """

    blur_sigma_px: float = 0.8
    canny_low: float = 50.0
    canny_high: float = 150.0
    window_hu: tuple[float, float] = (500.0, 3071.0)
    phi1_range: tuple[float, float] = (0.150, 0.20)
    theta1_max: float = 0.5
    circularity_min: float = 0.65
    axis_ratio_min: float = 0.65
    min_points: int = 5
    radius_range_mm: tuple[float, float] = (0.2, 2.6)


@dataclass(frozen=True, eq=False)
class Circle:
    """One contour with its invariants, its ellipse and the acceptance verdict.

    Coordinates are patch pixels: x = column, y = row.
    """

    center_px: F64  # (2,) x, y of the ellipse centre
    radius_px: float  # minor semi-axis (the paper's inscribed circle)
    major_px: float  # major semi-axis
    hu: F64  # (7,) Hu's invariants φ1 … φ7
    umi: F64  # (8,) united moment invariants θ1 … θ8 (guarded)
    circularity: float
    axis_ratio: float
    n_points: int
    accepted: bool
    reason: str  # "" when accepted, else the failed rule


def hu_invariants(contour: NDArray[np.int32] | NDArray[np.float32]) -> F64:
    """Hu's seven invariants φ1 … φ7 of a contour (Green's-formula moments, ``cv2.HuMoments``)."""
    return np.asarray(cv2.HuMoments(cv2.moments(contour)).ravel(), dtype=np.float64)


def _sqrt_signed(x: float) -> float:
    return math.copysign(math.sqrt(abs(x)), x)


def _div(a: float, b: float) -> float:
    return a / math.copysign(abs(b) + UMI_EPS, b if b != 0.0 else 1.0)


def united_moment_invariants(phi: F64) -> F64:
    """The eight united moment invariants θ1 … θ8 (paper eq. 4, after Sun et al. 2003), guarded.

    θ1 = √φ2/φ1, θ2 = φ6/(φ1φ4), θ3 = √φ5/φ4, θ4 = φ5/(φ3φ4),
    θ5 = φ1φ6/(φ2φ3), θ6 = (φ1+√φ2)φ3/φ6, θ7 = φ1φ5/(φ3φ6), θ8 = (φ3+φ4)/√φ5.

    Square roots are signed (√x → sign(x)·√|x|, since φ5 and φ6 can be
    slightly negative from rasterisation) and every denominator gets
    ``UMI_EPS`` added to its magnitude, so the result is always finite.  On a
    disc θ1 ≈ 0 and θ2 … θ8 are ratios of round-off (image-side.md §2.2):
    use them as features, not for acceptance.

    Parameters
    ----------
    phi : ndarray, shape (7,)
        Hu's invariants (any consistent moment normalisation; every θ cancels it).

    Returns
    -------
    ndarray, shape (8,), float64
    """
    p1, p2, p3, p4, p5, p6, _ = (float(v) for v in phi)
    s2, s5 = _sqrt_signed(p2), _sqrt_signed(p5)
    return np.array(
        [
            _div(s2, p1),
            _div(p6, p1 * p4),
            _div(s5, p4),
            _div(p5, p3 * p4),
            _div(p1 * p6, p2 * p3),
            _div((p1 + s2) * p3, p6),
            _div(p1 * p5, p3 * p6),
            _div(p3 + p4, s5),
        ]
    )


def evaluate_contour(
    contour: NDArray[np.int32], pixel_mm: float, params: CircleParams = CircleParams()
) -> Circle:
    """Invariants, ellipse and acceptance of one contour (``cv2.findContours`` output, shape (N, 1, 2))."""
    n = len(contour)
    phi = hu_invariants(contour)
    umi = united_moment_invariants(phi)
    area = float(cv2.contourArea(contour))
    perim = float(cv2.arcLength(contour, True))
    circ = 4.0 * math.pi * area / (perim * perim) if perim > 0 else 0.0
    nan2 = np.array([math.nan, math.nan])
    if n < params.min_points:
        return Circle(
            nan2,
            math.nan,
            math.nan,
            phi,
            umi,
            circ,
            0.0,
            n,
            False,
            f"{n} contour points < {params.min_points}",
        )
    (ex, ey), (d1, d2), _ = cv2.fitEllipse(contour)
    minor, major = 0.5 * min(d1, d2), 0.5 * max(d1, d2)
    ratio = minor / major if major > 0 else 0.0
    center = np.array([ex, ey], dtype=np.float64)
    reason = ""
    r_mm = minor * pixel_mm
    if not params.phi1_range[0] <= phi[0] <= params.phi1_range[1]:
        reason = f"φ1 = {phi[0]:.3f} outside [{params.phi1_range[0]}, {params.phi1_range[1]}] (disc: 0.159)"
    elif umi[0] > params.theta1_max:
        reason = f"θ1 = {umi[0]:.3f} > {params.theta1_max} (elongated)"
    elif circ < params.circularity_min:
        reason = f"circularity {circ:.2f} < {params.circularity_min}"
    elif ratio < params.axis_ratio_min:
        reason = f"ellipse axis ratio {ratio:.2f} < {params.axis_ratio_min}"
    elif not params.radius_range_mm[0] <= r_mm <= params.radius_range_mm[1]:
        reason = f"radius {r_mm:.2f} mm outside [{params.radius_range_mm[0]}, {params.radius_range_mm[1]}] mm"
    return Circle(center, minor, major, phi, umi, circ, ratio, n, reason == "", reason)


def find_circles(
    patch_hu: NDArray[np.floating] | NDArray[np.integer],
    pixel_mm: float,
    params: CircleParams = CircleParams(),
) -> list[Circle]:
    """Every external contour of one slice patch, evaluated as a candidate circle.

    Gaussian filter → Canny on the windowed 8-bit patch → ``cv2.findContours``
    (external, no approximation) → :func:`evaluate_contour`.

    Parameters
    ----------
    patch_hu : ndarray, shape (rows, cols)
        One slice patch in HU (typically after :func:`registration.imaging.mar.reduce_metal_artifacts`).
    pixel_mm : float
        In-plane pixel size in mm.

    Returns
    -------
    list of Circle
        Accepted and rejected contours alike (``Circle.accepted``), centres in
        patch pixels (x = column, y = row).
    """
    lo, hi = params.window_hu
    img = np.asarray(patch_hu, dtype=np.float32)
    u8 = np.clip((img - np.float32(lo)) * np.float32(255.0 / (hi - lo)), 0.0, 255.0).astype(np.uint8)
    blurred = cv2.GaussianBlur(u8, (3, 3), params.blur_sigma_px)
    edges = cv2.Canny(blurred, params.canny_low, params.canny_high)
    contours, _ = cv2.findContours(edges, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_NONE)
    return [evaluate_contour(c, pixel_mm, params) for c in contours]
