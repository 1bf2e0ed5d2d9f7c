"""The face-offset fit (issue #43): c_i = R (p_i + β n_i) + t with one β per scan."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

from registration.detection import DetectedSphere, DetectionResult
from registration.errors import FaceOffsetError, PointSetError, RegistrationError
from registration.matching.face_offset import MAX_FACE_OFFSET_MM, check_face_offset, fit_face_offset
from registration.matching.face_offset_grid import grid_face_offset
from registration.matching.records import RegistrationParams
from registration.matching.register import register_points
from registration.model.phantom import load_phantom

PHANTOM = load_phantom(Path(__file__).parents[4] / "configs" / "phantoms" / "bai2018_cube.toml")


def _scan(beta_mm: float, seed: int, noise_mm: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    rot = Rotation.random(random_state=rng).as_matrix()
    t = rng.uniform(-100.0, 100.0, 3)
    p, n = PHANTOM.centres_phantom_mm, PHANTOM.axes_phantom
    c = (p + beta_mm * n) @ rot.T + t + rng.normal(0.0, noise_mm, p.shape)
    return c, rot, t


@settings(max_examples=30, deadline=None)
@given(beta_mm=st.floats(-0.2, 0.2), seed=st.integers(0, 2**31))
def test_recovers_beta_and_pose_without_noise(beta_mm: float, seed: int) -> None:
    c, rot, t = _scan(beta_mm, seed, 0.0)
    fit = fit_face_offset(PHANTOM.centres_phantom_mm, PHANTOM.axes_phantom, c)
    assert fit.beta_mm == pytest.approx(beta_mm, abs=1e-9)
    assert np.allclose(fit.image_from_model[:3, :3], rot, atol=1e-9)
    assert np.allclose(fit.image_from_model[:3, 3], t, atol=1e-7)
    truth = PHANTOM.centres_phantom_mm @ rot.T + t
    assert np.max(np.abs(fit.centres_image_mm - truth)) < 1e-7
    assert float(np.max(fit.residuals_mm)) < 1e-7


def test_standard_error_matches_the_scatter_of_beta() -> None:
    """With 0.02 mm per-axis noise, β over 200 scans scatters as the fit's standard error says."""
    betas, ses = [], []
    for seed in range(200):
        c, _, _ = _scan(-0.02, seed, 0.02)
        fit = fit_face_offset(PHANTOM.centres_phantom_mm, PHANTOM.axes_phantom, c)
        betas.append(fit.beta_mm)
        ses.append(fit.beta_se_mm)
    assert abs(np.mean(betas) + 0.02) < 3 * np.std(betas) / np.sqrt(len(betas))
    assert np.std(betas) == pytest.approx(np.mean(ses), rel=0.2)


def test_malformed_input_is_refused() -> None:
    p, n = PHANTOM.centres_phantom_mm, PHANTOM.axes_phantom
    with pytest.raises(PointSetError):
        fit_face_offset(p[:2], n[:2], p[:2])
    with pytest.raises(PointSetError):
        fit_face_offset(p, n[:-1], p)


def test_an_offset_over_the_bound_is_refused_naming_the_holes() -> None:
    c, _, _ = _scan(-2 * MAX_FACE_OFFSET_MM, 3, 0.0)
    fit = fit_face_offset(PHANTOM.centres_phantom_mm, PHANTOM.axes_phantom, c)
    with pytest.raises(FaceOffsetError) as e:
        check_face_offset(fit, PHANTOM.filled_ids)
    assert isinstance(e.value, RegistrationError)
    assert PHANTOM.filled_ids[0] in str(e.value) and "deeper" in str(e.value)
    check_face_offset(
        fit_face_offset(PHANTOM.centres_phantom_mm, PHANTOM.axes_phantom, _scan(0.1, 3, 0)[0]), ()
    )


def test_hole_axes_are_the_face_normals() -> None:
    axes = PHANTOM.hole_axes_phantom
    assert np.allclose(np.linalg.norm(axes, axis=1), 1.0)
    # every hole sits on its face: its centre's component along its axis is the largest
    proj = np.einsum("ij,ij->i", PHANTOM.holes_phantom_mm, axes)
    assert np.all(proj > np.max(np.abs(PHANTOM.holes_phantom_mm[:, :2]), axis=1) - 1e-9)


def _detections(centres: np.ndarray) -> DetectionResult:
    spheres = tuple(DetectedSphere(c, float("nan"), 0, 0.0) for c in centres)
    return DetectionResult(spheres, (), "subvoxel", {})


def test_register_points_fits_beta_when_the_phantom_is_given() -> None:
    """The pull shared along the hole axes leaves residuals in a rigid fit; with the phantom the
    7-parameter fit removes it and the pose is the true one."""
    c, rot, t = _scan(-0.03, 11, 0.0)
    rng = np.random.default_rng(5)
    robot_from_phantom = np.eye(4)
    robot_from_phantom[:3, :3] = Rotation.random(random_state=rng).as_matrix()
    robot_from_phantom[:3, 3] = [400.0, -50.0, 300.0]
    robot = PHANTOM.centres_phantom_mm @ robot_from_phantom[:3, :3].T + robot_from_phantom[:3, 3]
    image_from_phantom = np.eye(4)
    image_from_phantom[:3, :3], image_from_phantom[:3, 3] = rot, t
    truth = image_from_phantom @ np.linalg.inv(robot_from_phantom)
    order = rng.permutation(len(c))
    plain = register_points(robot, c[order])
    assert plain.face_offset_mm is None and plain.fre_mm > 0.01
    res = register_points(robot, c[order], phantom=PHANTOM)
    assert res.face_offset_mm == pytest.approx(-0.03, abs=1e-9)
    assert res.fre_mm < 1e-7
    assert np.allclose(res.image_from_robot, truth, atol=1e-7)
    assert res.to_dict()["face_offset_mm"] == pytest.approx(-0.03, abs=1e-9)
    with pytest.raises(FaceOffsetError):
        register_points(robot, c[order], phantom=PHANTOM, params=RegistrationParams(max_face_offset_mm=0.02))


def test_detect_fits_beta_over_the_hole_grid() -> None:
    """``detect`` has no robot points: the detections pair with the phantom's holes."""
    c, rot, t = _scan(0.02, 17, 0.0)
    det = grid_face_offset(_detections(c[::-1]), PHANTOM)
    assert det.face_offset is not None
    assert det.face_offset.beta_mm == pytest.approx(0.02, abs=1e-9)
    truth = (PHANTOM.centres_phantom_mm @ rot.T + t)[::-1]
    assert np.max(np.abs(det.face_offset.centres_image_mm - truth)) < 1e-7
    doc = det.to_dict()
    assert doc["face_offset_mm"] == pytest.approx(0.02, abs=1e-9)
    assert doc["spheres"][0]["center_corrected_mm"] == pytest.approx(list(truth[0]), abs=1e-7)


def test_every_symmetric_twin_of_the_grid_gives_the_same_beta() -> None:
    """Faces map onto faces under the grid's symmetries (hole axes with them), so a pairing with
    any twin of the holes measures the same β: the grid fit needs no unique pairing."""
    c, _, _ = _scan(-0.025, 23, 0.01)
    holes, axes = PHANTOM.holes_phantom_mm, PHANTOM.hole_axes_phantom
    ref = fit_face_offset(PHANTOM.centres_phantom_mm, PHANTOM.axes_phantom, c).beta_mm
    syms = PHANTOM.symmetries()
    assert syms
    for sym in syms:
        twin = sym.hole_permutation[PHANTOM.filled]
        assert fit_face_offset(holes[twin], axes[twin], c).beta_mm == pytest.approx(ref, abs=1e-9)


def test_detect_without_a_pairing_says_why() -> None:
    det = grid_face_offset(_detections(PHANTOM.centres_phantom_mm[:2]), PHANTOM)
    assert det.face_offset is None and "sphere" in det.face_offset_reason
    assert det.to_dict()["face_offset_mm"] is None
