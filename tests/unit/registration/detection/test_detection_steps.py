"""The steps of :func:`registration.detection.detect_spheres` (issue #9 item 3)."""

from __future__ import annotations

import math
from collections.abc import Iterator
from typing import Any

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp
from numpy.typing import NDArray
from test_detection import SPACING, make_volume

from registration import detection
from registration.detection import (
    METHODS,
    TIMED_STAGES,
    DetectionParams,
    StageTimer,
)
from registration.detection.candidates import Blob, find_blobs, group_hits, threshold_hits
from registration.detection.cross_check import SliceCircle, slice_circles, sphere_score
from registration.detection.detect import _checked_spacing
from registration.detection.estimators.base import centre_estimator
from registration.detection.estimators.paper import ESTIMATOR as PAPER
from registration.detection.estimators.paper import PaperCircles
from registration.detection.fov import edge_reject_reason, fov_reject_reason
from registration.detection.rejections import SizeLimits, blob_reject_reason
from registration.errors import DetectionError
from registration.imaging.mar import reduce_metal_artifacts
from registration.imaging.volume import Volume

F64 = NDArray[np.float64]
SP = np.array(SPACING)
SETTINGS = settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.too_slow])
P = DetectionParams()


# ----------------------------------------------------------------------------- stage timer


@pytest.fixture
def fake_clock(monkeypatch: pytest.MonkeyPatch) -> Iterator[list[float]]:
    """time.perf_counter as seen by registration.detection.timing returns these values in turn."""
    ticks: list[float] = []
    monkeypatch.setattr("registration.detection.timing.time.perf_counter", lambda: ticks.pop(0))
    yield ticks


def test_stage_timer_sums_blocks_per_stage_and_keeps_declared_order(fake_clock: list[float]) -> None:
    fake_clock.extend([10.0, 10.5, 20.0, 20.25, 30.0, 31.0])
    timer = StageTimer(("a_s", "b_s", "never_s"))
    with timer.stage("b_s"):
        pass
    with timer.stage("b_s"):
        pass
    with pytest.raises(RuntimeError), timer.stage("a_s"):
        raise RuntimeError("a failing stage still counts")
    assert list(timer.seconds) == ["a_s", "b_s", "never_s"]
    assert timer.seconds == {"a_s": 1.0, "b_s": 0.75, "never_s": 0.0}


def test_detect_spheres_reports_every_stage() -> None:
    res = detection.detect_spheres(Volume(np.zeros((4, 16, 16), np.int16), np.eye(4)))
    assert list(res.timings_s) == [*TIMED_STAGES, "total_s"]


# ----------------------------------------------------------------------------- candidates


@SETTINGS
@given(
    vox=hnp.arrays(np.int16, (3, 5, 7), elements=st.integers(-1024, 3071)),
    threshold_hu=st.floats(-1100.0, 40000.0, allow_nan=False),
)
def test_threshold_hits_on_integer_volumes(vox: NDArray[np.int16], threshold_hu: float) -> None:
    flat, thr = threshold_hits(vox, threshold_hu)
    np.testing.assert_array_equal(flat, np.flatnonzero(vox.astype(np.float64) >= threshold_hu))
    assert thr == math.ceil(threshold_hu)


@SETTINGS
@given(
    vox=hnp.arrays(np.float32, (2, 4, 4), elements=st.floats(-1000, 3000, width=32)),
    threshold_hu=st.floats(-1000.0, 3000.0),
)
def test_threshold_hits_on_float_volumes(vox: NDArray[np.float32], threshold_hu: float) -> None:
    flat, thr = threshold_hits(vox, threshold_hu)
    np.testing.assert_array_equal(flat, np.flatnonzero(vox >= np.float32(threshold_hu)))
    assert thr == threshold_hu


def test_find_blobs_measures_and_orders_components() -> None:
    vox = np.zeros((12, 20, 20), np.int16)
    vox[6:9, 12:14, 2:4] = 3000  # second in (k, j, i) order
    vox[1:3, 3:5, 10:14] = 2500
    vox[1, 3, 10] = 3071
    flat, thr = threshold_hits(vox, 2000.0)
    blobs = find_blobs(vox, group_hits(flat, (12, 20, 20)), thr, SP, P.crop_margin_mm)
    assert [b.n_voxels for b in blobs] == [16, 12]
    assert [b.peak_hu for b in blobs] == [3071.0, 3000.0]
    np.testing.assert_allclose(blobs[0].centroid_voxel, [11.5, 3.5, 1.5])
    np.testing.assert_allclose(blobs[1].extent_mm, np.array([2, 2, 3]) * SP)


# ----------------------------------------------------------------------------- reject reasons


def _blob(extent_mm: tuple[float, float, float], n_voxels: int, peak_hu: float = 3071.0) -> Blob:
    return Blob((slice(0, 5), slice(0, 5), slice(0, 5)), n_voxels, peak_hu, np.zeros(3), np.array(extent_mm))


def test_blob_reject_reasons() -> None:
    limits = SizeLimits.of(P, SP)
    sphere_voxels = int(limits.v_nominal_mm3 * 2.0 / limits.voxel_mm3)  # bloomed sphere, ≈ 2 × nominal
    assert blob_reject_reason(_blob((3.5, 3.5, 3.5), sphere_voxels), limits, P) is None
    rod = blob_reject_reason(_blob((3.5, 3.5, 25.0), sphere_voxels), limits, P)
    assert rod is not None and "connecting rod" in rod
    big = blob_reject_reason(_blob((6.0, 6.0, 6.0), int(2 * limits.v_max_mm3 / limits.voxel_mm3)), limits, P)
    assert big is not None and "wrong size" in big
    dim = blob_reject_reason(_blob((3.5, 3.5, 3.5), sphere_voxels, peak_hu=2300.0), limits, P)
    assert dim is not None and "peak 2300 HU < 2500 HU" in dim
    small = blob_reject_reason(_blob((0.8, 3.0, 3.0), sphere_voxels), limits, P)
    assert small is not None and "too small" in small


@SETTINGS
@given(
    axis=st.integers(0, 2),
    room_mm=st.floats(0.0, 5.0),
    radius_mm=st.floats(0.5, 3.0),
)
def test_edge_reject_iff_the_sphere_leaves_the_sampled_volume(
    axis: int, room_mm: float, radius_mm: float
) -> None:
    shape = (40, 96, 96)  # (k, j, i)
    centre = np.array([48.0, 48.0, 20.0])  # (i, j, k), far from every edge
    centre[axis] = room_mm / SP[axis]
    reason = edge_reject_reason(centre, shape, SP, radius_mm)
    if abs(room_mm - radius_mm) > 1e-9:
        assert (reason is not None) == (room_mm < radius_mm)
    if reason is not None:
        assert "cut by the edge" in reason


@SETTINGS
@given(
    off_axis_mm=st.floats(0.0, 25.0),
    angle=st.floats(0.0, 2 * math.pi),
    fov_radius_mm=st.floats(5.0, 20.0),
)
def test_fov_reject_iff_the_sphere_crosses_the_fov_circle(
    off_axis_mm: float, angle: float, fov_radius_mm: float
) -> None:
    shape = (40, 97, 97)
    centre_px = np.array([48.0, 48.0])
    centre = np.array(
        [
            centre_px[0] + off_axis_mm * math.cos(angle) / SP[0],
            centre_px[1] + off_axis_mm * math.sin(angle) / SP[1],
            20.0,
        ]
    )
    r = 1.25
    reason = fov_reject_reason(centre, fov_radius_mm, shape, SP, r)
    if abs(off_axis_mm + r - fov_radius_mm) > 1e-6:
        assert (reason is not None) == (off_axis_mm + r > fov_radius_mm)
    assert fov_reject_reason(centre, None, shape, SP, r) is None


def test_checked_spacing_refuses_bad_volumes() -> None:
    with pytest.raises(DetectionError, match="expected a 3-D volume"):
        _checked_spacing(Volume(np.zeros((4, 4), np.int16), np.eye(4)))
    with pytest.raises(DetectionError, match="not positive"):
        _checked_spacing(Volume(np.zeros((2, 4, 4), np.int16), np.diag([1.0, 0.0, 1.0, 1.0])))
    np.testing.assert_allclose(_checked_spacing(Volume(np.zeros((2, 4, 4)), np.diag([*SPACING, 1.0]))), SP)


# ----------------------------------------------------------------------------- slice circles


@pytest.mark.parametrize(("method", "use_mar"), [("subvoxel", True), ("subvoxel", False), ("paper", True)])
def test_slice_circles_find_the_sphere_in_its_slices(
    method: str, use_mar: bool, monkeypatch: pytest.MonkeyPatch
) -> None:
    centre = np.array([48.3, 47.6, 20.4])
    vol = make_volume(centre[None])
    params = DetectionParams(method=method, use_mar=use_mar)
    mar_calls: list[int] = []

    def counting_mar(*args: Any, **kwargs: Any) -> Any:
        mar_calls.append(1)
        return reduce_metal_artifacts(*args, **kwargs)

    monkeypatch.setattr("registration.detection.cross_check.reduce_metal_artifacts", counting_mar)
    slices = range(17, 24)
    circles = slice_circles(
        vol.voxels,
        slices,
        centre,
        params,
        float(SP[0]),
        StageTimer(TIMED_STAGES),
        mar_every_patch=centre_estimator(method).circles_are_the_measurement,
    )
    assert len(circles) >= 3 and all(17 <= c.k < 24 for c in circles)
    for c in circles:
        assert math.hypot((c.i - centre[0]) * SP[0], (c.j - centre[1]) * SP[1]) < 0.2
    if method == "paper":
        assert len(mar_calls) == len(slices)  # Bai 2018: MAR on every patch
    elif use_mar:
        assert len(mar_calls) < len(slices)  # only where the raw cross-section fails
    else:
        assert mar_calls == []


# ----------------------------------------------------------------------------- centres and score


def _circles_of(centre_ijk: F64, radius_mm: float, ks: range, dz_mm: float) -> list[SliceCircle]:
    out = []
    for k in ks:
        dz = (k - centre_ijk[2]) * dz_mm
        if abs(dz) < radius_mm:
            out.append(
                SliceCircle(float(centre_ijk[0]), float(centre_ijk[1]), k, math.sqrt(radius_mm**2 - dz**2))
            )
    return out


def test_every_method_names_an_estimator_and_an_unknown_one_is_refused() -> None:
    for method in METHODS:
        est = centre_estimator(method)
        assert callable(est.prepare) and callable(est.estimate)
        assert est.circles_are_the_measurement == (method == "paper")
    with pytest.raises(DetectionError, match="unknown detection method 'nope'"):
        centre_estimator("nope")


@SETTINGS
@given(
    i=st.floats(10.0, 80.0),
    j=st.floats(10.0, 80.0),
    k=st.floats(10.0, 30.0),
    radius_mm=st.floats(1.5, 2.5),
)
def test_paper_estimator_recovers_an_exact_sphere(i: float, j: float, k: float, radius_mm: float) -> None:
    dz = float(SP[2])
    truth = np.array([i, j, k])
    circles = _circles_of(truth, radius_mm, range(0, 40), dz)
    centre, reason = PAPER.estimate(PaperCircles(circles, radius_mm, dz))
    assert reason == "" and centre is not None
    np.testing.assert_allclose(centre, truth, atol=1e-6)


def test_paper_estimator_refuses_a_single_slice() -> None:
    one = [SliceCircle(10.0, 10.0, 5, 1.5)]
    centre, reason = PAPER.estimate(PaperCircles(one, math.nan, 0.8))
    assert centre is None and "needs ≥ 2 slices" in reason


@SETTINGS
@given(n_circles=st.integers(1, 8), extra_slices=st.integers(0, 8), offset_fraction=st.floats(0.0, 1.5))
def test_sphere_score(n_circles: int, extra_slices: int, offset_fraction: float) -> None:
    r = 1.25
    centre = np.array([20.0, 20.0, 5.0])
    circles = [SliceCircle(20.0 + offset_fraction * r / SP[0], 20.0, k, 1.5) for k in range(n_circles)]
    score = sphere_score(circles, centre, SP, n_circles + extra_slices, r)
    expected = n_circles / (n_circles + extra_slices) * max(0.0, 1.0 - offset_fraction)
    assert score == pytest.approx(expected)
