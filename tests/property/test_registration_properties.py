"""Hypothesis properties of the registration (style.md "Tests": tests/property)."""

from __future__ import annotations

import numpy as np
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from numpy.typing import NDArray
from scipy.spatial.transform import Rotation

from registration import frames
from registration.errors import MirroredInputError
from registration.register import register_points

F64 = NDArray[np.float64]
SETTINGS = settings(max_examples=25, deadline=None, suppress_health_check=[HealthCheck.too_slow])


def _cloud(seed: int, n: int) -> F64:
    """A random, well-spread (non-coplanar, asymmetric) point set in a 70 × 70 × 80 mm box."""
    rng = np.random.default_rng(seed)
    while True:
        pts = rng.uniform(-1.0, 1.0, (n, 3)) * [35.0, 35.0, 40.0]
        d = np.linalg.norm(pts[:, None] - pts[None], axis=2) + np.eye(n) * 1e9
        if d.min() > 6.0:  # spheres at least 6 mm apart, like holes on a grid
            return pts


def _transform(seed: int) -> F64:
    rng = np.random.default_rng(seed)
    return frames.make_transform(Rotation.random(random_state=seed).as_matrix(), rng.uniform(-500, 500, 3))


seeds = st.integers(min_value=0, max_value=2**31 - 1)
sizes = st.integers(min_value=8, max_value=30)


@SETTINGS
@given(seed=seeds, n=sizes)
def test_random_rigid_transform_recovered_in_any_order(seed: int, n: int) -> None:
    robot = _cloud(seed, n)
    truth = _transform(seed + 1)
    perm = np.random.default_rng(seed + 2).permutation(n)
    image = frames.apply(truth, robot)[perm]
    res = register_points(robot, image)
    assert res.n_matched == n
    np.testing.assert_array_equal(perm[res.image_indices], res.robot_indices)
    err = np.linalg.norm(frames.apply(res.image_from_robot, robot) - frames.apply(truth, robot), axis=1)
    assert err.max() < 1e-9
    assert abs(res.rotation_det - 1.0) < 1e-12


@SETTINGS
@given(seed=seeds, n=sizes, axis=st.integers(min_value=0, max_value=2))
def test_mirrored_input_refused(seed: int, n: int, axis: int) -> None:
    robot = _cloud(seed, n)
    image = frames.apply(_transform(seed + 1), robot)
    image[:, axis] *= -1.0
    try:
        register_points(robot, image)
    except MirroredInputError:
        return
    raise AssertionError("mirrored input was fitted")


@SETTINGS
@given(seed=seeds, n=sizes, far=st.floats(min_value=200.0, max_value=5000.0))
def test_far_spurious_point_changes_nothing(seed: int, n: int, far: float) -> None:
    robot = _cloud(seed, n)
    rng = np.random.default_rng(seed + 3)
    image = frames.apply(_transform(seed + 1), robot) + rng.normal(0, 0.05, robot.shape)
    base = register_points(robot, image)
    direction = rng.normal(size=3)
    extra = image.mean(axis=0) + far * direction / np.linalg.norm(direction)
    more = register_points(robot, np.vstack([image, extra]))
    np.testing.assert_array_equal(more.robot_indices, base.robot_indices)
    np.testing.assert_array_equal(more.image_indices, base.image_indices)
    np.testing.assert_allclose(more.image_from_robot, base.image_from_robot, atol=1e-12)
    assert more.n_detected == base.n_detected + 1


@SETTINGS
@given(seed=seeds, n=sizes)
def test_fre_unchanged_by_common_rigid_motion(seed: int, n: int) -> None:
    robot = _cloud(seed, n)
    rng = np.random.default_rng(seed + 4)
    image = frames.apply(_transform(seed + 1), robot) + rng.normal(0, 0.05, robot.shape)
    motion_r, motion_i = _transform(seed + 5), _transform(seed + 6)
    a = register_points(robot, image)
    b = register_points(frames.apply(motion_r, robot), frames.apply(motion_i, image))
    assert abs(a.fre_mm - b.fre_mm) < 1e-9
    np.testing.assert_allclose(a.residuals_mm, b.residuals_mm, atol=1e-9)
