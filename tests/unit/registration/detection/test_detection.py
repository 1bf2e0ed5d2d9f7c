"""Sphere detection (registration/detection.py) on analytic partial-volume volumes.

The volumes here are built in the test (supersampled spheres, 0.7 mm PSF,
3071 HU clip, noise) so these tests need no simulator; the simulator-based
accuracy checks live in tests/accuracy/test_detection_accuracy.py.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy import ndimage

from registration.detection import (
    DetectionParams,
    DetectionResult,
    detect_spheres,
)
from registration.detection.cross_check import SliceCircle, fit_radius
from registration.detection.estimators.paper import _paper_depth
from registration.errors import DetectionError
from registration.imaging.volume import Volume

SPACING = (0.415, 0.415, 0.833)  # (i, j, k) mm: the commonly quoted O-arm grid
SHAPE = (40, 96, 96)  # (k, j, i)


def _add_sphere(vol: np.ndarray, c_ijk, r_mm: float, value: float, ss: int = 4) -> None:
    sx, sy, sz = SPACING
    hr = np.array([r_mm / sx, r_mm / sy, r_mm / sz]) + 2
    lo = [int(np.floor(c - h)) for c, h in zip(c_ijk, hr, strict=True)]
    hi = [int(np.ceil(c + h)) + 1 for c, h in zip(c_ijk, hr, strict=True)]
    off = (np.arange(ss) + 0.5) / ss - 0.5
    ii = (np.arange(lo[0], hi[0])[:, None] + off).ravel()
    jj = (np.arange(lo[1], hi[1])[:, None] + off).ravel()
    kk = (np.arange(lo[2], hi[2])[:, None] + off).ravel()
    d2 = (
        ((ii[None, None, :] - c_ijk[0]) * sx) ** 2
        + ((jj[None, :, None] - c_ijk[1]) * sy) ** 2
        + ((kk[:, None, None] - c_ijk[2]) * sz) ** 2
    )
    n = (hi[2] - lo[2], ss, hi[1] - lo[1], ss, hi[0] - lo[0], ss)
    occ = (d2 <= r_mm**2).reshape(n).mean(axis=(1, 3, 5))
    vol[lo[2] : hi[2], lo[1] : hi[1], lo[0] : hi[0]] += occ * value


def make_volume(
    centres_ijk: np.ndarray,
    *,
    rod: bool = False,
    bone: bool = False,
    seed: int = 0,
    affine: np.ndarray | None = None,
    r_mm: float = 1.25,
) -> Volume:
    """Steel spheres (15000 HU before clipping) in 100 HU plastic, blurred, noisy, clipped at 3071 HU."""
    pad = 8  # spheres may stick out of the volume (cut by its edge)
    vol = np.full(tuple(n + 2 * pad for n in SHAPE), 100.0)
    for c in centres_ijk:
        _add_sphere(vol, np.asarray(c) + pad, r_mm, 15000.0 - 100.0)
    vol = vol[pad:-pad, pad:-pad, pad:-pad]
    if rod:  # 5 mm steel bar through 25 slices
        vol[5:35, 8:20, 8:20] = 15000.0
    if bone:  # a large cortical-bone block edge: bright (1400 HU) but not metal
        vol[10:30, 70:90, 5:25] = 1400.0
        vol[18:21, 78:81, 12:15] = 2300.0  # a dense bone spot over the candidate threshold
    sig = 0.7 / 2.3548
    vol = ndimage.gaussian_filter(vol, (sig / SPACING[2], sig / SPACING[1], sig / SPACING[0]))
    vol += np.random.default_rng(seed).normal(0.0, 20.0, SHAPE)
    vox = np.clip(np.rint(vol), -1024, 3071).astype(np.int16)
    if affine is None:
        affine = np.diag([*SPACING, 1.0])
    return Volume(vox, affine, series_uid="1.2.826.0.1.3680043.2.1125.test")


def grid_truth(seed: int = 1) -> np.ndarray:
    rng = np.random.default_rng(seed)
    pts = [
        [a + rng.random(), b + rng.random(), rng.uniform(10, SHAPE[0] - 10)]
        for a in (30, 55, 80)
        for b in (30, 55, 80)
    ]
    return np.array(pts)


def _errors_mm(result: DetectionResult, truth_ijk: np.ndarray) -> np.ndarray:
    c = np.array([s.center_voxel for s in result.spheres])
    d = np.linalg.norm((c[:, None, :] - truth_ijk[None]) * SPACING, axis=2)
    assert np.all(d.min(axis=1) < 1.0), "a detection matches no sphere"
    assert len(set(d.argmin(axis=1))) == len(c), "two detections on one sphere"
    return d.min(axis=1)


@pytest.mark.parametrize("method", ["subvoxel", "paper"])
def test_finds_every_sphere_accurately(method: str) -> None:
    truth = grid_truth()
    result = detect_spheres(make_volume(truth), DetectionParams(method=method))
    assert len(result.spheres) == len(truth)
    err = _errors_mm(result, truth)
    limit = 0.1 if method == "subvoxel" else 0.2  # mm; measured 0.05 / 0.12 max on these volumes
    assert err.max() < limit, err
    assert not result.rejections
    for s in result.spheres:
        assert 1.0 < s.radius_mm < 2.2  # fitted apparent radius (blooming), never the nominal 1.25
        assert s.n_slices >= 2
        assert 0.0 < s.score <= 1.0


def test_subvoxel_is_more_accurate_than_paper() -> None:
    truth = grid_truth(seed=3)
    vol = make_volume(truth, seed=3)
    e_sub = _errors_mm(detect_spheres(vol, DetectionParams(method="subvoxel")), truth)
    e_pap = _errors_mm(detect_spheres(vol, DetectionParams(method="paper")), truth)
    assert e_sub.mean() < e_pap.mean()


def test_rod_is_rejected_with_reason() -> None:
    truth = grid_truth()[4:]
    result = detect_spheres(make_volume(truth, rod=True))
    assert len(result.spheres) == len(truth)
    assert any("rod" in r.reason for r in result.rejections)


def test_bone_spot_is_rejected_not_bright_enough() -> None:
    truth = grid_truth()[:3]
    result = detect_spheres(make_volume(truth, bone=True))
    assert len(result.spheres) == len(truth)
    assert any("not bright enough" in r.reason for r in result.rejections)


def test_sphere_cut_by_first_slice_is_rejected() -> None:
    truth = np.array([[40.3, 40.6, 0.9], [70.2, 60.1, 20.4]])  # first one: centre 0.75 mm from slice 0
    result = detect_spheres(make_volume(truth))
    assert len(result.spheres) == 1
    assert np.linalg.norm((result.spheres[0].center_voxel - truth[1]) * SPACING) < 0.15
    assert any("cut by the edge" in r.reason for r in result.rejections)


def test_sphere_cut_by_circular_fov_is_rejected() -> None:
    truth = np.array([[10.2, 20.3, 20.0], [48.3, 47.6, 20.4]])  # first: 19.3 mm off axis, FOV radius 19.9 mm
    vol = make_volume(truth)
    vox = vol.voxels.copy()
    jj, ii = np.mgrid[0 : SHAPE[1], 0 : SHAPE[2]]
    outside = np.hypot(ii - (SHAPE[2] - 1) / 2, jj - (SHAPE[1] - 1) / 2) > SHAPE[1] / 2
    vox[:, outside] = -1024
    result = detect_spheres(Volume(vox, vol.image_from_voxel))
    assert len(result.spheres) == 1
    assert any("circular field of view" in r.reason for r in result.rejections)


def test_wrong_size_blob_is_rejected() -> None:
    truth = grid_truth()[:2]
    vol = make_volume(np.vstack([truth, [[80.0, 80.0, 20.0]]]))
    big = make_volume(np.array([[80.0, 80.0, 20.0]]), r_mm=3.2)
    vox = vol.voxels.copy()
    vox[10:30, 65:95, 65:95] = big.voxels[10:30, 65:95, 65:95]
    result = detect_spheres(Volume(vox, vol.image_from_voxel))
    assert len(result.spheres) == 2
    assert any(("oversized" in r.reason) or ("volume" in r.reason) for r in result.rejections)


def test_empty_volume_gives_empty_result() -> None:
    vol = Volume(np.zeros((8, 32, 32), np.int16), np.eye(4))
    result = detect_spheres(vol)
    assert result.spheres == () and result.rejections == ()
    assert result.centres_image_mm.shape == (0, 3)


def test_orientation_variants_give_the_same_lps_centres() -> None:
    """Same physical spheres, voxel array flipped / reversed with the matching affine → same LPS centres."""
    truth = grid_truth(seed=5)
    base = make_volume(truth, seed=5)
    ref = detect_spheres(base).centres_image_mm
    a = base.image_from_voxel
    n_k, n_j, n_i = SHAPE
    variants = []
    # reversed slice order: k' = n_k − 1 − k
    flip_k = np.eye(4)
    flip_k[2, 2], flip_k[2, 3] = -1.0, n_k - 1
    variants.append(Volume(np.ascontiguousarray(base.voxels[::-1]), a @ flip_k))
    # in-plane flip (IOP (−1,0,0),(0,−1,0)): i' = n_i − 1 − i, j' = n_j − 1 − j
    flip_ij = np.eye(4)
    flip_ij[0, 0], flip_ij[0, 3] = -1.0, n_i - 1
    flip_ij[1, 1], flip_ij[1, 3] = -1.0, n_j - 1
    variants.append(Volume(np.ascontiguousarray(base.voxels[:, ::-1, ::-1]), a @ flip_ij))
    # unsigned-style storage converted back to float HU (loader output may be float32)
    variants.append(Volume(base.voxels.astype(np.float32), a))
    for v in variants:
        got = detect_spheres(v).centres_image_mm
        assert got.shape == ref.shape
        d = np.linalg.norm(got[:, None] - ref[None], axis=2).min(axis=1)
        assert d.max() < 1e-6


def test_grouping_keeps_neighbouring_spheres_apart() -> None:
    """Two spheres 6 mm apart (closer than the 15 mm pitch) stay two detections when the phantom
    allows spheres that close (``min_separation_mm`` below 6 mm; its default is half the pitch)."""
    truth = np.array([[40.2, 48.3, 20.2], [40.2 + 6.0 / 0.415, 48.1, 20.6]])
    result = detect_spheres(make_volume(truth), DetectionParams(min_separation_mm=5.0))
    assert len(result.spheres) == 2
    _errors_mm(result, truth)


def test_paper_depth_uses_the_radius_trend() -> None:
    """Known answer: sphere R = 1.9 mm at z0 = 10.3 slices, 0.833 mm slices; exact radii per slice."""
    dz, r, z0 = 0.833, 1.9, 10.3
    circles = [
        SliceCircle(0.0, 0.0, k, math.sqrt(r * r - ((k - z0) * dz) ** 2))
        for k in (9, 10, 11, 12)
        if abs(k - z0) * dz < r
    ]
    r_fit, z_fit = fit_radius(circles, dz)
    assert abs(r_fit - r) < 1e-9
    assert abs(z_fit / dz - z0) < 1e-9
    assert abs(_paper_depth(circles, r_fit, dz) - z0) < 1e-9


def test_params_validation() -> None:
    with pytest.raises(DetectionError, match="method"):
        DetectionParams(method="hough")
    with pytest.raises(DetectionError, match="diameter"):
        DetectionParams(sphere_diameter_mm=0.0)


def test_result_json_shape() -> None:
    result = detect_spheres(make_volume(grid_truth()[:2]))
    doc = result.to_dict(series_uid="1.2.3")
    assert doc["frame"] == "image" and doc["series_uid"] == "1.2.3" and doc["method"] == "subvoxel"
    assert len(doc["spheres"]) == 2
    assert set(doc["spheres"][0]) == {"center_mm", "radius_mm", "n_slices", "score"}
