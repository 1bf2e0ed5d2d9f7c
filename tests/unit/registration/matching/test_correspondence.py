"""Click-free correspondence, the registration contract's refusals, and verification (eq. 10)."""

from __future__ import annotations

import numpy as np
import pytest
from numpy.typing import NDArray
from scipy.spatial.transform import Rotation

from registration.errors import (
    AccuracyGateError,
    AmbiguousMatchError,
    ConfigError,
    DegenerateConfigurationError,
    MirroredInputError,
    PointSetError,
    PriorMismatchError,
    TooFewSpheresError,
)
from registration.matching.correspondence import (
    choose_base_triples,
    exhaustive_runner_ups,
    find_hypotheses,
    pairwise_distances,
    same_pose,
)
from registration.matching.records import RegistrationParams
from registration.matching.register import (
    register_points,
)
from registration.matching.rigid import rotation_difference_deg
from registration.matching.verification import verify_registration
from registration.model import frames
from registration.model.phantom import Phantom
from tests.helpers.documents import REGISTRATION_DOC_KEYS

F64 = NDArray[np.float64]


def _pose(seed: int) -> F64:
    rng = np.random.default_rng(seed)
    return frames.make_transform(Rotation.random(random_state=seed).as_matrix(), rng.uniform(-200, 200, 3))


def _scene(phantom: Phantom, seed: int, *, sigma: float = 0.05, drop: int = 0, full: bool = False):  # type: ignore[no-untyped-def]
    """Robot points (phantom order) and shuffled image points with labels."""
    rng = np.random.default_rng(seed)
    pts = phantom.holes_phantom_mm if full else phantom.centres_phantom_mm
    robot = frames.apply(_pose(seed + 1000), pts)
    truth = _pose(seed)
    image = frames.apply(truth, robot) + rng.normal(0, sigma, robot.shape)
    labels = np.arange(len(robot))[drop:]
    image = image[drop:]
    perm = rng.permutation(len(image))
    return robot, image[perm], labels[perm], truth


# ---------------------------------------------------------------- correspondence


def test_find_hypotheses_best_is_truth(phantom: Phantom) -> None:
    robot, image, _, truth = _scene(phantom, 1, drop=3)
    hyps = find_hypotheses(robot, image, pair_tol_mm=1.0, gate_mm=1.5)
    assert hyps[0].n_inliers == len(robot) - 3
    assert rotation_difference_deg(hyps[0].image_from_robot[:3, :3], truth[:3, :3]) < 1.0
    assert all(np.linalg.det(h.image_from_robot[:3, :3]) == pytest.approx(1.0) for h in hyps)
    # sorted by inlier count, and distinct
    assert [h.n_inliers for h in hyps] == sorted((h.n_inliers for h in hyps), reverse=True)


def test_find_hypotheses_full_grid_returns_symmetric_twins(phantom: Phantom) -> None:
    robot, image, _, _ = _scene(phantom, 2, full=True)
    hyps = find_hypotheses(robot, image, pair_tol_mm=1.0, gate_mm=1.5)
    top = [h for h in hyps if h.n_inliers == 64]
    assert len(top) >= 2  # the 8 proper symmetries all fit every sphere
    angles = {
        round(rotation_difference_deg(top[0].image_from_robot[:3, :3], h.image_from_robot[:3, :3]))
        for h in top[1:]
    }
    assert angles <= {90, 180}


def test_find_hypotheses_empty_for_too_few_points(phantom: Phantom) -> None:
    robot, image, _, _ = _scene(phantom, 3)
    assert find_hypotheses(robot, image[:2], pair_tol_mm=1.0, gate_mm=1.5) == []


def test_exhaustive_runner_up_of_a_face_subset_is_the_90_degree_twin() -> None:
    """Known answer: one 4 × 4 face (15 mm pitch) with three holes empty; the image shows 9 of its
    13 spheres.  The 90° twin about the face normal lands exactly the robot spheres whose rotated
    grid cell is imaged; the search must report that count for the twin, and nothing above the
    best distinct pose's count."""
    cells = [(u, v) for u in range(4) for v in range(4) if (u, v) not in {(0, 0), (1, 2), (3, 1)}]
    robot = np.array([[0.0, 15.0 * u, 15.0 * v] for u, v in cells])
    imaged = [(0, 1), (0, 2), (0, 3), (1, 0), (1, 1), (2, 0), (2, 1), (2, 2), (3, 3)]
    truth = _pose(7)
    image = frames.apply(truth, np.array([[0.0, 15.0 * u, 15.0 * v] for u, v in imaged]))
    # the twin: 90° about the face normal (x) through the face centre, in the robot frame
    centre = np.array([0.0, 22.5, 22.5])
    rot = Rotation.from_euler("x", 90, degrees=True).as_matrix()
    twin = truth @ frames.make_transform(rot, centre - rot @ centre)
    turned = (robot - centre) @ rot.T + centre
    imaged_mm = np.array([[0.0, 15.0 * u, 15.0 * v] for u, v in imaged])
    expected = int((np.linalg.norm(turned[:, None] - imaged_mm[None], axis=2).min(axis=1) < 0.5).sum())
    assert 3 <= expected < len(imaged)
    hyps = exhaustive_runner_ups(robot, image, truth, pair_tol_mm=1.0, gate_mm=1.5)
    centroid = robot.mean(axis=0)
    assert all(not same_pose(h.image_from_robot, truth, centroid, 5.0, 3.0) for h in hyps)
    match = [h for h in hyps if same_pose(h.image_from_robot, twin, centroid, 5.0, 3.0)]
    assert len(match) == 1 and match[0].n_inliers == expected
    assert hyps[0].n_inliers == expected  # the twin is (one of) the best runner-ups
    assert [h.n_inliers for h in hyps] == sorted((h.n_inliers for h in hyps), reverse=True)


def test_base_triples_are_disjoint_and_long(phantom: Phantom) -> None:
    robot, image, _, _ = _scene(phantom, 4)
    d = pairwise_distances(image)
    pair_d = np.sort(d[np.triu_indices(len(image), 1)])
    triples = choose_base_triples(robot, pairwise_distances(robot), pair_d, 1.0, 6)
    assert len(triples) == 6
    flat = [i for t in triples for i in t]
    assert len(set(flat)) == len(flat)
    diameter = pairwise_distances(robot).max()
    for a, b, c in triples:
        assert (
            min(
                np.linalg.norm(robot[a] - robot[b]),
                np.linalg.norm(robot[a] - robot[c]),
                np.linalg.norm(robot[b] - robot[c]),
            )
            >= 0.45 * diameter
        )


# ---------------------------------------------------------------- register_points contract


def test_register_points_answers_and_reports(phantom: Phantom) -> None:
    robot, image, labels, _ = _scene(phantom, 5, drop=2)
    targets = frames.apply(np.eye(4), robot.mean(axis=0) + np.array([[150.0, 0, 0], [0, 0, 0]]))
    res = register_points(robot, image, targets_robot_mm=targets, phantom=phantom)
    assert res.n_expected == 28 and res.n_detected == 26 and res.n_matched == 26
    np.testing.assert_array_equal(labels[res.image_indices], res.robot_indices)
    assert res.rotation_det == pytest.approx(1.0)
    assert res.fle_mm == pytest.approx(res.fre_mm * np.sqrt(26 / 24))
    assert res.predicted_tre_mm.shape == (2,)
    assert res.predicted_tre_mm[0] > res.predicted_tre_mm[1]  # TRE grows away from the centroid
    assert res.symmetry_margin >= 3 and "symmetry" in res.runner_up_source
    d = res.to_dict()
    for key in REGISTRATION_DOC_KEYS:
        assert key in d
    assert set(d["spheres"][0]) >= {"index", "robot_mm", "image_mm", "residual_mm"}
    assert np.allclose(d["image_from_robot"], res.image_from_robot)


def test_full_grid_is_ambiguous_and_message_names_counts_and_rotation(phantom: Phantom) -> None:
    robot, image, _, _ = _scene(phantom, 6, full=True)
    with pytest.raises(AmbiguousMatchError, match=r"matches 64 spheres.*rotated (90|180)\.0°.*matches 64"):
        register_points(robot, image)


def test_prior_resolves_full_grid(phantom: Phantom) -> None:
    robot, image, labels, truth = _scene(phantom, 7, full=True)
    prior = Rotation.from_euler("xyz", [10, -15, 20], degrees=True).as_matrix() @ truth[:3, :3]
    res = register_points(robot, image, orientation_prior=prior, prior_tolerance_deg=40.0)
    np.testing.assert_array_equal(labels[res.image_indices], res.robot_indices)
    assert res.prior_angle_deg is not None and res.prior_angle_deg < 40.0


def test_prior_tolerance_must_be_below_45(phantom: Phantom) -> None:
    robot, image, _, truth = _scene(phantom, 8)
    with pytest.raises(ConfigError, match="45"):
        register_points(robot, image, orientation_prior=truth[:3, :3], prior_tolerance_deg=45.0)


def test_prior_must_be_a_rotation(phantom: Phantom) -> None:
    robot, image, _, _ = _scene(phantom, 8)
    with pytest.raises(ConfigError, match="proper rotation"):
        register_points(robot, image, orientation_prior=np.diag([1.0, 1.0, -1.0]))


def test_wrong_prior_is_refused(phantom: Phantom) -> None:
    robot, image, _, truth = _scene(phantom, 9)
    wrong = Rotation.from_euler("z", 90, degrees=True).as_matrix() @ truth[:3, :3]
    with pytest.raises(PriorMismatchError, match="away from the prior"):
        register_points(robot, image, orientation_prior=wrong, prior_tolerance_deg=20.0)


def test_mirrored_image_is_refused(phantom: Phantom) -> None:
    robot, image, _, _ = _scene(phantom, 10)
    with pytest.raises(MirroredInputError, match=r"mirror image.*slice order"):
        register_points(robot, image * [1.0, 1.0, -1.0], phantom=phantom)


def test_mirrored_along_another_axis_is_refused(phantom: Phantom) -> None:
    robot, image, _, _ = _scene(phantom, 11)
    with pytest.raises(MirroredInputError):
        register_points(robot, image * [-1.0, 1.0, 1.0])  # x flip = z flip ∘ a proper rotation


def test_too_few_spheres_message_has_counts(phantom: Phantom) -> None:
    robot, image, _, _ = _scene(phantom, 12)
    with pytest.raises(TooFewSpheresError, match=r"28 expected, 5 detected"):
        register_points(robot, image[:5])


def test_too_few_detections_at_all(phantom: Phantom) -> None:
    robot, image, _, _ = _scene(phantom, 12)
    with pytest.raises(TooFewSpheresError, match="2 sphere"):
        register_points(robot, image[:2])


def test_unrelated_points_are_refused(phantom: Phantom) -> None:
    robot, _, _, _ = _scene(phantom, 13)
    noise = np.random.default_rng(13).uniform(-60, 60, (30, 3))
    with pytest.raises((TooFewSpheresError, AmbiguousMatchError)):
        register_points(robot, noise)


def test_collinear_robot_points_refused() -> None:
    line = np.outer(np.arange(10.0), [1.0, 2.0, 3.0])
    with pytest.raises(DegenerateConfigurationError, match="collinear"):
        register_points(line, line)


def test_coplanar_robot_points_refused() -> None:
    plane = np.random.default_rng(14).uniform(-50, 50, (12, 3)) * [1.0, 1.0, 0.0]
    with pytest.raises(DegenerateConfigurationError, match="coplanar"):
        register_points(plane, plane)


def test_fre_gate(phantom: Phantom) -> None:
    robot, image, _, _ = _scene(phantom, 15, sigma=0.4)
    with pytest.raises(AccuracyGateError, match="FRE"):
        register_points(robot, image, params=RegistrationParams(max_fre_mm=0.2))


def test_bad_point_array_shape() -> None:
    with pytest.raises(PointSetError, match=r"\(N, 3\)"):
        register_points(np.zeros((5, 2)), np.zeros((5, 3)))


def test_prereg_path_matches_global_answer(phantom: Phantom) -> None:
    robot, image, labels, _ = _scene(phantom, 16, drop=1)
    where = {int(lab): k for k, lab in enumerate(labels)}
    # four marks on different faces (indices into phantom order), pairs (robot index, image index)
    marks = [1, 8, 15, 24]
    res = register_points(robot, image, prereg_pairs=[(r, where[r]) for r in marks], phantom=phantom)
    assert res.method == "prereg+icp" and res.prereg is not None
    np.testing.assert_array_equal(labels[res.image_indices], res.robot_indices)
    assert res.prereg.nonrigidity < 0.05
    glob = register_points(robot, image, phantom=phantom)
    np.testing.assert_allclose(res.image_from_robot, glob.image_from_robot, atol=1e-9)


def test_prereg_resolves_full_grid(phantom: Phantom) -> None:
    robot, image, labels, _ = _scene(phantom, 17, full=True)
    where = {int(lab): k for k, lab in enumerate(labels)}
    marks = [0, 21, 38, 60]
    res = register_points(robot, image, prereg_pairs=[(r, where[r]) for r in marks])
    np.testing.assert_array_equal(labels[res.image_indices], res.robot_indices)
    assert res.n_matched == 64


def test_prereg_pairs_validated(phantom: Phantom) -> None:
    robot, image, _, _ = _scene(phantom, 18)
    with pytest.raises(PointSetError, match="exactly 4"):
        register_points(robot, image, prereg_pairs=[(0, 0), (1, 1), (2, 2)])
    with pytest.raises(PointSetError, match="only once"):
        register_points(robot, image, prereg_pairs=[(0, 0), (0, 1), (2, 2), (3, 3)])
    with pytest.raises(PointSetError, match="indices"):
        register_points(robot, image, prereg_pairs=[(0, 0), (1, 1), (2, 2), (99, 3)])


# ---------------------------------------------------------------- verification (eq. 10)


def test_verification_errors_and_counts(phantom: Phantom) -> None:
    robot, image, labels, truth = _scene(phantom, 19, sigma=0.0, drop=2)
    image = np.vstack([image, image[0] + [4.0, 0, 0]])  # a spurious detection 4 mm from a sphere
    off = truth.copy()
    off[:3, 3] += [0.3, 0.0, 0.4]  # registration off by 0.5 mm
    res = verify_registration(off, robot, image)
    assert res.n_expected == 28 and res.n_detected == 27 and res.n_matched == 26
    np.testing.assert_allclose(res.errors_mm, 0.5, atol=1e-9)
    assert res.mean_mm == pytest.approx(0.5) and res.rms_mm == pytest.approx(0.5)
    assert res.max_mm == pytest.approx(0.5) and res.p95_mm == pytest.approx(0.5)
    np.testing.assert_array_equal(labels[res.image_indices], res.robot_indices)
    d = res.to_dict()
    assert d["n_matched"] == 26 and len(d["spheres"]) == 26


def test_verification_refuses_when_registration_is_far_off(phantom: Phantom) -> None:
    robot, image, _, truth = _scene(phantom, 20)
    off = truth.copy()
    off[:3, 3] += [7.0, 6.0, 0.0]
    with pytest.raises(TooFewSpheresError, match="verification"):
        verify_registration(off, robot, image)


def test_verification_rejects_non_rigid_matrix(phantom: Phantom) -> None:
    robot, image, _, truth = _scene(phantom, 21)
    bad = truth.copy()
    bad[:3, :3] *= 1.1
    with pytest.raises(Exception, match="not a proper rotation"):
        verify_registration(bad, robot, image)
