"""Quality figures: FRE, FLE from FRE (eq. 10), Fitzpatrick TRE (eq. 46), conditioning."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from registration.errors import DegenerateConfigurationError
from registration.matching.quality import (
    assert_proper_rotation,
    check_configuration,
    conditioning,
    fle_from_fre,
    fre_from_fle,
    fre_mm,
    predicted_tre_mm,
    principal_axes,
)
from registration.matching.rigid import fit_rigid
from registration.model import frames

CUBE = np.array([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)], dtype=np.float64) * 30.0


def test_fre_is_rms() -> None:
    assert fre_mm([3.0, 4.0]) == pytest.approx(np.sqrt(12.5))


def test_fre_of_nothing_is_an_error() -> None:
    with pytest.raises(ValueError):
        fre_mm([])


def test_fle_from_fre_eq10_and_inverse() -> None:
    assert fle_from_fre(0.3, 10) == pytest.approx(0.3 * np.sqrt(10 / 8))
    assert fre_from_fle(fle_from_fre(0.3, 10), 10) == pytest.approx(0.3)


def test_fle_needs_more_than_two_points() -> None:
    with pytest.raises(ValueError, match="N > 2"):
        fle_from_fre(0.1, 2)


def test_tre_at_centroid_is_fle_over_sqrt_n() -> None:
    # eq. 46 with d_k = 0
    tre = predicted_tre_mm(0.5, CUBE, [[0.0, 0.0, 0.0]])
    assert tre[0] == pytest.approx(0.5 / np.sqrt(8))


def test_tre_known_answer_off_axis() -> None:
    # cube corners: every axis has f_k² = 2 · 30² (distance² from a principal axis); a target at
    # 150 mm along x is at d = 0 from the x axis and 150 mm from the y and z axes
    f2 = 2 * 30.0**2
    expected = np.sqrt(0.5**2 / 8 * (1 + (0 + 150.0**2 / f2 + 150.0**2 / f2) / 3))
    assert predicted_tre_mm(0.5, CUBE, [[150.0, 0, 0]])[0] == pytest.approx(expected)


def test_tre_is_frame_invariant() -> None:
    t = frames.make_transform(Rotation.random(random_state=3).as_matrix(), [10.0, -20.0, 5.0])
    targets = np.array([[100.0, 20.0, -40.0], [0.0, 0.0, 150.0]])
    a = predicted_tre_mm(0.2, CUBE, targets)
    b = predicted_tre_mm(0.2, frames.apply(t, CUBE), frames.apply(t, targets))
    np.testing.assert_allclose(a, b, rtol=1e-12)


def test_tre_prediction_matches_monte_carlo() -> None:
    """eq. 46 against simulation (research §2 did the same at 4000 trials)."""
    rng = np.random.default_rng(0)
    pts = rng.uniform(-35, 35, (20, 3))
    target = np.array([[150.0, 0.0, 0.0]])
    sigma = 0.1  # per axis, in one space only: FLE² = 3σ²
    errs = []
    for _ in range(1500):
        t = fit_rigid(pts, pts + rng.normal(0, sigma, pts.shape))
        errs.append(np.linalg.norm(frames.apply(t, target) - target))
    measured = float(np.sqrt(np.mean(np.square(errs))))
    predicted = float(predicted_tre_mm(np.sqrt(3) * sigma, pts, target)[0])
    assert measured == pytest.approx(predicted, rel=0.1)


def test_tre_collinear_fiducials_refused() -> None:
    line = np.outer(np.arange(5.0), [1.0, 0.0, 0.0])
    with pytest.raises(DegenerateConfigurationError, match="collinear"):
        predicted_tre_mm(0.1, line, [[0.0, 10.0, 0.0]])


def test_principal_axes_sorted() -> None:
    pts = np.random.default_rng(1).normal(size=(200, 3)) * [30.0, 10.0, 1.0]
    _, w, axes = principal_axes(pts)
    assert w[0] > w[1] > w[2]
    assert abs(axes[0, 0]) > 0.99 and abs(axes[2, 2]) > 0.99


def test_conditioning_of_cube() -> None:
    c = conditioning(CUBE)
    assert c.collinearity == pytest.approx(1.0) and c.planarity == pytest.approx(1.0)


def test_check_configuration_refuses_collinear() -> None:
    pts = np.outer(np.arange(6.0), [1.0, 1.0, 0.0]) + np.random.default_rng(2).normal(0, 1e-3, (6, 3))
    with pytest.raises(DegenerateConfigurationError, match="collinear"):
        check_configuration(pts, "test points")


def test_check_configuration_refuses_coplanar() -> None:
    pts = CUBE * [1.0, 1.0, 0.001]
    with pytest.raises(DegenerateConfigurationError, match="coplanar"):
        check_configuration(pts, "test points")


def test_check_configuration_refuses_too_few() -> None:
    with pytest.raises(DegenerateConfigurationError, match=">= 3"):
        check_configuration(CUBE[:2], "test points")


def test_check_configuration_accepts_cube() -> None:
    assert check_configuration(CUBE, "cube").planarity > 0.5


def test_assert_proper_rotation() -> None:
    assert assert_proper_rotation(np.eye(4)) == pytest.approx(1.0)
    with pytest.raises(AssertionError, match="det"):
        assert_proper_rotation(np.diag([1.0, 1.0, -1.0, 1.0]))
