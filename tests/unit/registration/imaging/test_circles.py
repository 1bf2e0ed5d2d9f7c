"""Circle recognition by moment invariants (registration/imaging/circles.py): discs, ellipses, non-circles."""

from __future__ import annotations

import math

import cv2
import numpy as np
import pytest

from registration.imaging.circles import (
    PHI1_DISC,
    CircleParams,
    evaluate_contour,
    find_circles,
    hu_invariants,
    united_moment_invariants,
)

PIXEL_MM = 0.415
"""O-arm pixel size (commonly quoted, image-side.md §1.1)."""


def _slice(mask_fn, n: int = 41, metal_hu: float = 3071.0, bg_hu: float = 100.0, ss: int = 8, seed: int = 0):
    """A supersampled partial-volume slice of a shape, blurred (0.7 px), with 20 HU noise."""
    yy, xx = (np.mgrid[0 : n * ss, 0 : n * ss] + 0.5) / ss - 0.5
    inside = mask_fn(xx, yy)
    img = inside.reshape(n, ss, n, ss).mean(axis=(1, 3)) * (metal_hu - bg_hu) + bg_hu
    img = cv2.GaussianBlur(img, (0, 0), 0.7) + np.random.default_rng(seed).normal(0.0, 20.0, img.shape)
    return img.astype(np.float32)


def _disc(cx: float, cy: float, r: float):
    return lambda x, y: (x - cx) ** 2 + (y - cy) ** 2 <= r * r


def _ellipse(cx: float, cy: float, a: float, b: float, angle_deg: float = 0.0):
    t = math.radians(angle_deg)

    def f(x, y):
        u = (x - cx) * math.cos(t) + (y - cy) * math.sin(t)
        v = -(x - cx) * math.sin(t) + (y - cy) * math.cos(t)
        return (u / a) ** 2 + (v / b) ** 2 <= 1.0

    return f


def _accepted(img):
    return [c for c in find_circles(img, PIXEL_MM) if c.accepted]


@pytest.mark.parametrize("r_px", [2.5, 3.0, 4.0])  # 1.0–1.7 mm: bloomed sphere sections
@pytest.mark.parametrize("seed", [0, 1, 2])
def test_disc_is_accepted_with_centre_and_radius(r_px: float, seed: int) -> None:
    rng = np.random.default_rng(seed)
    cx, cy = 20.0 + rng.random(), 20.0 + rng.random()
    found = _accepted(_slice(_disc(cx, cy, r_px), seed=seed))
    assert len(found) == 1
    c = found[0]
    assert (
        np.hypot(c.center_px[0] - cx, c.center_px[1] - cy)
        < 0.45  # px = 0.19 mm: per-slice ellipse centres are the weak estimate (image-side.md §3.2)
    )  # px; ~0.06 mm mean per image-side.md §3.2
    # the Canny edge of a blurred disc sits near its half-maximum: radius within ~1 px
    assert abs(c.radius_px - r_px) < 1.2
    assert abs(c.hu[0] - PHI1_DISC) < 0.03  # 0.160–0.187 measured on small contours (image-side.md §2.2)


@pytest.mark.parametrize(("a", "b", "angle"), [(5.0, 2.5, 0.0), (5.0, 2.5, 37.0), (4.0, 2.4, 90.0)])
def test_ellipse_is_rejected(a: float, b: float, angle: float) -> None:
    circles = find_circles(_slice(_ellipse(20.3, 19.7, a, b, angle)), PIXEL_MM)
    assert circles, "the ellipse must produce a contour"
    assert not any(c.accepted for c in circles)
    assert any(("θ1" in c.reason) or ("axis ratio" in c.reason) or ("φ1" in c.reason) for c in circles)


def test_elongated_rectangle_is_rejected() -> None:
    img = _slice(lambda x, y: (np.abs(x - 20) <= 9) & (np.abs(y - 20) <= 2.5))
    assert not _accepted(img)


def test_large_square_is_rejected() -> None:
    img = _slice(lambda x, y: (np.abs(x - 20) <= 8) & (np.abs(y - 20) <= 8))
    circles = find_circles(img, PIXEL_MM)
    assert circles and not any(c.accepted for c in circles)


def test_triangle_is_rejected() -> None:
    pts = np.array([[8.0, 30.0], [34.0, 30.0], [21.0, 6.0]])

    def tri(x, y):
        inside = np.ones_like(x, dtype=bool)
        for p, q in ((pts[0], pts[1]), (pts[1], pts[2]), (pts[2], pts[0])):
            inside &= (q[0] - p[0]) * (y - p[1]) - (q[1] - p[1]) * (x - p[0]) <= 0
        return inside

    assert not _accepted(_slice(tri))


def test_crescent_is_rejected() -> None:
    crescent = lambda x, y: _disc(20, 20, 6)(x, y) & ~_disc(23, 20, 5)(x, y)  # noqa: E731
    assert not _accepted(_slice(crescent))


def test_disc_too_large_for_a_sphere_is_rejected_by_radius() -> None:
    circles = find_circles(_slice(_disc(20.2, 20.1, 9.0)), PIXEL_MM)  # 3.7 mm radius
    assert circles and not any(c.accepted for c in circles)
    assert any("radius" in c.reason for c in circles)


def test_few_points_are_rejected_not_fitted() -> None:
    contour = np.array([[[1, 1]], [[2, 1]], [[2, 2]]], dtype=np.int32)
    c = evaluate_contour(contour, PIXEL_MM, CircleParams())
    assert not c.accepted
    assert "points" in c.reason


def test_united_invariants_are_finite_on_a_disc() -> None:
    """On a disc φ2…φ7 vanish; the guarded θ must still be finite (image-side.md §2.2)."""
    img = np.zeros((60, 60), np.uint8)
    cv2.circle(img, (30, 30), 12, 255, -1)
    contours, _ = cv2.findContours(img, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_NONE)
    phi = hu_invariants(contours[0])
    theta = united_moment_invariants(phi)
    assert theta.shape == (8,)
    assert np.all(np.isfinite(theta))
    assert theta[0] < 0.05


def test_united_invariants_known_values() -> None:
    """θ from eq. 4 with hand-picked φ (no guard effect when all φ are positive and large)."""
    phi = np.array([0.2, 0.04, 0.01, 0.02, 0.0009, 0.003, 0.0])
    t = united_moment_invariants(phi)
    expected = [
        math.sqrt(0.04) / 0.2,
        0.003 / (0.2 * 0.02),
        math.sqrt(0.0009) / 0.02,
        0.0009 / (0.01 * 0.02),
        0.2 * 0.003 / (0.04 * 0.01),
        (0.2 + math.sqrt(0.04)) * 0.01 / 0.003,
        0.2 * 0.0009 / (0.01 * 0.003),
        (0.01 + 0.02) / math.sqrt(0.0009),
    ]
    np.testing.assert_allclose(t, expected, rtol=1e-9)


def test_united_invariants_signed_root_on_negative_phi5() -> None:
    phi = np.array([0.16, 1e-6, 1e-8, 1e-8, -4e-16, 1e-12, 0.0])
    t = united_moment_invariants(phi)
    assert np.all(np.isfinite(t))
    assert t[2] < 0  # √φ5 is signed, not NaN


def test_united_invariants_scale_invariant() -> None:
    """Any moment normalisation cancels in θ (image-side.md §2.2): scaled/rotated polygon, θ1 within 5 %."""
    poly = np.array([[10, 10], [50, 14], [44, 40], [16, 36]], dtype=np.float32)
    c = poly.mean(axis=0)
    rot = np.array([[math.cos(0.7), -math.sin(0.7)], [math.sin(0.7), math.cos(0.7)]])
    poly2 = ((poly - c) @ rot.T * 2.5 + c).astype(np.float32)
    t1 = united_moment_invariants(hu_invariants(poly.reshape(-1, 1, 2)))
    t2 = united_moment_invariants(hu_invariants(poly2.reshape(-1, 1, 2)))
    np.testing.assert_allclose(t1[[0, 1, 3]], t2[[0, 1, 3]], rtol=0.05)
