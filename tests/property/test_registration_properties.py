"""Hypothesis properties of the registration (style.md "Tests": tests/property)."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays
from numpy.typing import NDArray
from scipy.spatial.transform import Rotation

from registration.errors import MirroredInputError
from registration.matching.register import register_points
from registration.model import frames

F64 = NDArray[np.float64]
SETTINGS = settings(max_examples=25, deadline=None, suppress_health_check=[HealthCheck.too_slow])

JITTER_MM = 1.0
"""Each drawn point moves at most this far from its base point."""


def _base_points(n: int = 40, min_gap_mm: float = 6.0 + 2 * JITTER_MM) -> F64:
    """Fixed, generic (asymmetric, non-coplanar) points ≥ 8 mm apart in a 70 × 70 × 80 mm box.

    A constant of the test, not drawn: hypothesis draws which of them to use, how far each one
    moves and the transforms, so a failure shrinks to few points, no jitter, simple poses.
    """
    rng = np.random.default_rng(20181016)
    pts: list[F64] = []
    while len(pts) < n:
        p = rng.uniform(-1.0, 1.0, 3) * [35.0, 35.0, 40.0]
        if all(np.linalg.norm(p - q) >= min_gap_mm for q in pts):
            pts.append(p)
    return np.array(pts)


BASE_MM = _base_points()
unit = st.floats(min_value=-1.0, max_value=1.0, allow_nan=False, allow_infinity=False)


@st.composite
def clouds(draw: st.DrawFn, min_size: int = 8, max_size: int = 30) -> F64:
    """(n, 3) float64 points (mm): a drawn subset of BASE_MM, each moved by ≤ JITTER_MM per axis."""
    idx = draw(st.lists(st.integers(0, len(BASE_MM) - 1), min_size=min_size, max_size=max_size, unique=True))
    jitter = draw(arrays(np.float64, (len(idx), 3), elements=unit))
    return BASE_MM[idx] + JITTER_MM * jitter


@st.composite
def rigid_transforms(draw: st.DrawFn, max_translation_mm: float = 500.0) -> F64:
    """4 × 4 proper rigid transforms: a rotation from a drawn quaternion, a drawn translation (mm)."""
    quat = draw(arrays(np.float64, 4, elements=unit).filter(lambda v: np.linalg.norm(v) > 0.1))
    t = draw(arrays(np.float64, 3, elements=unit)) * max_translation_mm
    return frames.make_transform(Rotation.from_quat(quat).as_matrix(), t)


def noise(n: int, amplitude_mm: float = 0.05) -> st.SearchStrategy[F64]:
    """(n, 3) detection noise, uniform within ±amplitude_mm per axis."""
    return arrays(np.float64, (n, 3), elements=unit).map(lambda a: a * amplitude_mm)


@SETTINGS
@given(data=st.data(), robot=clouds(), truth=rigid_transforms())
def test_random_rigid_transform_recovered_in_any_order(data: st.DataObject, robot: F64, truth: F64) -> None:
    n = len(robot)
    perm = np.array(data.draw(st.permutations(range(n)), label="image order"))
    image = frames.apply(truth, robot)[perm]
    res = register_points(robot, image)
    assert res.n_matched == n
    np.testing.assert_array_equal(perm[res.image_indices], res.robot_indices)
    err = np.linalg.norm(frames.apply(res.image_from_robot, robot) - frames.apply(truth, robot), axis=1)
    assert err.max() < 1e-9
    assert abs(res.rotation_det - 1.0) < 1e-12


@SETTINGS
@given(robot=clouds(), truth=rigid_transforms(), axis=st.integers(min_value=0, max_value=2))
def test_mirrored_input_refused(robot: F64, truth: F64, axis: int) -> None:
    image = frames.apply(truth, robot)
    image[:, axis] *= -1.0
    with pytest.raises(MirroredInputError):
        register_points(robot, image)


@SETTINGS
@given(
    data=st.data(),
    robot=clouds(),
    truth=rigid_transforms(),
    far=st.floats(min_value=200.0, max_value=5000.0),
    direction=arrays(np.float64, 3, elements=unit).filter(lambda v: np.linalg.norm(v) > 0.1),
)
def test_far_spurious_point_changes_nothing(
    data: st.DataObject, robot: F64, truth: F64, far: float, direction: F64
) -> None:
    image = frames.apply(truth, robot) + data.draw(noise(len(robot)), label="noise")
    base = register_points(robot, image)
    extra = image.mean(axis=0) + far * direction / np.linalg.norm(direction)
    more = register_points(robot, np.vstack([image, extra]))
    np.testing.assert_array_equal(more.robot_indices, base.robot_indices)
    np.testing.assert_array_equal(more.image_indices, base.image_indices)
    np.testing.assert_allclose(more.image_from_robot, base.image_from_robot, atol=1e-12)
    assert more.n_detected == base.n_detected + 1


@SETTINGS
@given(
    data=st.data(),
    robot=clouds(),
    truth=rigid_transforms(),
    motion_robot=rigid_transforms(),
    motion_image=rigid_transforms(),
)
def test_fre_unchanged_by_common_rigid_motion(
    data: st.DataObject, robot: F64, truth: F64, motion_robot: F64, motion_image: F64
) -> None:
    image = frames.apply(truth, robot) + data.draw(noise(len(robot)), label="noise")
    a = register_points(robot, image)
    b = register_points(frames.apply(motion_robot, robot), frames.apply(motion_image, image))
    assert abs(a.fre_mm - b.fre_mm) < 1e-9
    np.testing.assert_allclose(a.residuals_mm, b.residuals_mm, atol=1e-9)
