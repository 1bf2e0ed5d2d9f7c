"""Closed-form rigid fit (Kabsch/Umeyama with the det fix), pre-registration (eq. 7) and ICP."""

from __future__ import annotations

import numpy as np
import pytest
from numpy.typing import NDArray
from scipy.spatial.transform import Rotation

from registration.errors import (
    DegenerateConfigurationError,
    MirroredInputError,
    PointSetError,
    PreregistrationError,
)
from registration.matching.icp import icp, unique_pairs
from registration.matching.prereg import preregister
from registration.matching.rigid import fit_rigid, fit_rigid_batch, nearest_rotation, rotation_difference_deg
from registration.model import frames

F64 = NDArray[np.float64]


def _transform(seed: int) -> F64:
    rng = np.random.default_rng(seed)
    return frames.make_transform(Rotation.random(random_state=seed).as_matrix(), rng.uniform(-100, 100, 3))


def _cloud(seed: int, n: int = 20) -> F64:
    return np.random.default_rng(seed).uniform(-50, 50, (n, 3))


# ---------------------------------------------------------------- fit_rigid


def test_fit_rigid_known_answer_90_deg_about_z() -> None:
    src = np.array([[0.0, 0, 0], [10, 0, 0], [0, 20, 0], [0, 0, 30]])
    rz = np.array([[0.0, -1, 0], [1, 0, 0], [0, 0, 1]])
    dst = src @ rz.T + [1.0, 2.0, 3.0]
    t = fit_rigid(src, dst)
    np.testing.assert_allclose(t[:3, :3], rz, atol=1e-12)
    np.testing.assert_allclose(t[:3, 3], [1.0, 2.0, 3.0], atol=1e-12)


def test_fit_rigid_recovers_random_transform() -> None:
    src = _cloud(1)
    truth = _transform(2)
    t = fit_rigid(src, frames.apply(truth, src))
    np.testing.assert_allclose(t, truth, atol=1e-10)


def test_fit_rigid_never_returns_a_reflection_on_mirrored_data() -> None:
    src = _cloud(3)
    mirrored = src * [1.0, 1.0, -1.0]  # a reflection: orthogonal Procrustes would return det -1
    t = fit_rigid(src, mirrored)
    assert np.linalg.det(t[:3, :3]) == pytest.approx(1.0, abs=1e-12)
    # and the mirror shows up as a large residual instead of a silent fit
    assert np.sqrt(np.mean(np.sum((frames.apply(t, src) - mirrored) ** 2, axis=1))) > 5.0


def test_fit_rigid_coplanar_points_give_proper_rotation() -> None:
    src = _cloud(4) * [1.0, 1.0, 0.0]
    truth = _transform(5)
    t = fit_rigid(src, frames.apply(truth, src))
    np.testing.assert_allclose(t, truth, atol=1e-9)


def test_fit_rigid_weights_ignore_zero_weight_outlier() -> None:
    src = _cloud(6)
    truth = _transform(7)
    dst = frames.apply(truth, src)
    dst[0] += 50.0
    w = np.ones(len(src))
    w[0] = 0.0
    np.testing.assert_allclose(fit_rigid(src, dst, w), truth, atol=1e-9)
    assert not np.allclose(fit_rigid(src, dst), truth, atol=1e-3)


def test_fit_rigid_rejects_unpaired_input() -> None:
    with pytest.raises(ValueError, match="paired"):
        fit_rigid(_cloud(1, 5), _cloud(1, 6))


def test_fit_rigid_rejects_too_few_points() -> None:
    with pytest.raises(ValueError, match="at least 3"):
        fit_rigid(_cloud(1, 2), _cloud(1, 2))


def test_fit_rigid_rejects_nan_with_the_typed_point_set_error() -> None:
    """The registration's one point-set check (a 4xx problem, not a 500): it names the rows."""
    a = _cloud(1, 5)
    a[2, 1] = np.nan
    with pytest.raises(PointSetError, match=r"source_mm: rows \[2\] contain NaN"):
        fit_rigid(a, _cloud(2, 5))


def test_fit_rigid_rejects_a_point_set_that_is_not_n_by_3_with_the_typed_error() -> None:
    with pytest.raises(PointSetError, match=r"target_mm: expected an \(N, 3\) array .* got shape \(5, 2\)"):
        fit_rigid(_cloud(1, 5), _cloud(2, 5)[:, :2])


def test_fit_rigid_rejects_bad_weights() -> None:
    with pytest.raises(ValueError, match="weights"):
        fit_rigid(_cloud(1, 5), _cloud(2, 5), weights=[1, 1, -1, 1, 1])


def test_fit_rigid_coincident_points_are_degenerate() -> None:
    with pytest.raises(DegenerateConfigurationError):
        fit_rigid(np.ones((4, 3)), _cloud(2, 4))


def test_fit_rigid_batch_matches_single_and_is_proper() -> None:
    rng = np.random.default_rng(8)
    src = rng.uniform(-40, 40, (3, 3))
    dst = rng.uniform(-40, 40, (50, 3, 3))  # arbitrary targets, many would be reflections
    batch = fit_rigid_batch(src, dst)
    assert np.allclose(np.linalg.det(batch[:, :3, :3]), 1.0)
    for h in range(0, 50, 7):
        np.testing.assert_allclose(batch[h], fit_rigid(src, dst[h]), atol=1e-9)


def test_nearest_rotation_of_scaled_rotation() -> None:
    r = Rotation.random(random_state=9).as_matrix()
    rot, s = nearest_rotation(1.02 * r)
    np.testing.assert_allclose(rot, r, atol=1e-12)
    np.testing.assert_allclose(s, 1.02, atol=1e-12)


def test_rotation_difference_deg() -> None:
    r = Rotation.from_euler("z", 30, degrees=True).as_matrix()
    assert rotation_difference_deg(r, np.eye(3)) == pytest.approx(30.0)


# ---------------------------------------------------------------- pre-registration (eq. 7)

MARKS = np.array([[35.0, 0.0, -30.0], [0.0, 35.0, 30.0], [-35.0, 0.0, 15.0], [0.0, -35.0, -15.0]])


def test_prereg_exact_marks_give_the_transform() -> None:
    truth = _transform(10)
    res = preregister(MARKS, frames.apply(truth, MARKS))
    np.testing.assert_allclose(res.image_from_robot, truth, atol=1e-9)
    np.testing.assert_allclose(res.affine, truth, atol=1e-9)
    assert res.nonrigidity < 1e-9
    assert res.rms_mm < 1e-9


def test_prereg_noisy_marks_report_nonrigidity_and_stay_rigid() -> None:
    truth = _transform(11)
    rng = np.random.default_rng(11)
    img = frames.apply(truth, MARKS) + rng.normal(0, 0.25, MARKS.shape)
    res = preregister(MARKS, img)
    assert np.linalg.det(res.image_from_robot[:3, :3]) == pytest.approx(1.0)
    assert 0.0 < res.nonrigidity < 0.05
    assert res.rms_mm > 0.0
    # the affine is exact at the marks (eq. 7 interpolates four points)
    np.testing.assert_allclose(frames.apply(res.affine, MARKS), img, atol=1e-9)
    assert rotation_difference_deg(res.image_from_robot[:3, :3], truth[:3, :3]) < 2.0


def test_prereg_refuses_coplanar_marks() -> None:
    flat = MARKS * [1.0, 1.0, 0.0]
    with pytest.raises(DegenerateConfigurationError, match="coplanar"):
        preregister(flat, flat)


def test_prereg_refuses_mirrored_marks() -> None:
    with pytest.raises(MirroredInputError, match="mirror"):
        preregister(MARKS, MARKS * [1.0, 1.0, -1.0])


def test_prereg_refuses_mislabelled_marks() -> None:
    swapped = MARKS[[1, 0, 2, 3]]
    # swapping two marks of a (nearly) symmetric tetrahedron yields a strongly non-rigid affine
    with pytest.raises((PreregistrationError, MirroredInputError)):
        preregister(MARKS, swapped)


# ---------------------------------------------------------------- ICP


def _grid(n: int = 4, pitch: float = 15.0) -> F64:
    g = (np.arange(n) - (n - 1) / 2) * pitch
    pts = np.stack(np.meshgrid(g, g, g, indexing="ij"), axis=-1).reshape(-1, 3)
    return pts[np.random.default_rng(0).permutation(len(pts))[:40]]


def test_icp_converges_from_small_error_with_spurious_points() -> None:
    robot = _grid()
    truth = _transform(12)
    rng = np.random.default_rng(12)
    image = frames.apply(truth, robot) + rng.normal(0, 0.05, robot.shape)
    image = np.vstack(
        [image[3:], frames.apply(truth, robot[:3] + np.array([3.0, 0.0, 0.0]))]
    )  # 3 missing, 3 spurious
    init = frames.make_transform(
        Rotation.from_euler("xyz", [2, -1, 1.5], degrees=True).as_matrix(), [1, -1, 1]
    )
    res = icp(robot, image, truth @ init)
    assert res.converged
    assert res.n_matched == len(robot) - 3
    assert set(res.robot_indices.tolist()) == set(range(3, len(robot)))
    np.testing.assert_array_equal(res.image_indices, res.robot_indices - 3)  # image rows 0.. = robot 3..
    assert res.final_gate_mm < 1.0
    assert rotation_difference_deg(res.image_from_robot[:3, :3], truth[:3, :3]) < 0.1


def test_icp_gate_excludes_far_points() -> None:
    robot = _grid()
    truth = _transform(13)
    image = frames.apply(truth, robot)
    image[0] += [20.0, 0.0, 0.0]  # beyond the 7.5 mm gate and more than half a pitch from any sphere
    res = icp(robot, image, truth)
    assert 0 not in res.robot_indices.tolist()
    np.testing.assert_allclose(res.image_from_robot, truth, atol=1e-9)


def test_unique_pairs_keeps_closest_claim() -> None:
    dist = np.array([0.5, 0.2, np.inf, 0.3])
    idx = np.array([7, 7, 1, 2])
    r, i = unique_pairs(dist, idx)
    assert r.tolist() == [1, 3]
    assert i.tolist() == [7, 2]
