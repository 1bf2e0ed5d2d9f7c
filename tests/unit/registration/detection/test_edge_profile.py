"""registration.detection.fov: padding never leaks into a profile, crossings are where they are."""

from __future__ import annotations

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from registration.detection.fov import DataRegion, first_crossing, plateau_reaches_edge, sample_trilinear

SHAPE = (6, 40, 40)  # (k, j, i)
SPACING = np.array([0.415, 0.415, 0.833])


def _fov_filled(value: float) -> tuple[np.ndarray, DataRegion]:
    """``value`` inside the FOV circle inscribed in the matrix, −1024 padding outside."""
    region = DataRegion(SHAPE, SPACING, SHAPE[1] / 2.0 * SPACING[0])
    kk, jj, ii = np.meshgrid(*(np.arange(n) for n in SHAPE), indexing="ij")
    ijk = np.stack([ii.ravel(), jj.ravel(), kk.ravel()], axis=1).astype(np.float64)
    vox = np.where(region.contains(ijk), value, -1024.0).reshape(SHAPE).astype(np.int16)
    return vox, region


@settings(max_examples=50, deadline=None)
@given(
    pts=st.lists(
        st.tuples(st.floats(-2.0, 41.0), st.floats(-2.0, 41.0), st.floats(-1.0, 6.0)), min_size=1, max_size=40
    )
)
def test_samples_near_the_fov_edge_never_see_the_padding(pts: list[tuple[float, float, float]]) -> None:
    """Any position, however close to or past the circle: a sample is the image value or NaN."""
    vox, region = _fov_filled(1000.0)
    s = sample_trilinear(vox, np.array(pts), region)
    ok = ~np.isnan(s)
    np.testing.assert_allclose(s[ok], 1000.0)
    # a sample is kept where its nearest voxel is image data (it reaches the last image voxel)
    assert ok.tolist() == region.contains(np.rint(np.array(pts))).tolist()


@given(edge=st.floats(1.0, 2.7), level=st.floats(100.0, 900.0))
def test_first_crossing_of_a_linear_ramp(edge: float, level: float) -> None:
    """A ramp from 1000 at ``edge`` − 1 down to 0 at ``edge`` crosses ``level`` at edge − level/1000."""
    t = np.arange(-3.0, 3.0001, 0.05)
    prof = np.clip((edge - t) * 1000.0, 0.0, 1000.0)
    got = first_crossing(t, prof, level, +1)
    assert got is not None and abs(got - (edge - level / 1000.0)) < 1e-6
    prof_nan = prof.copy()
    prof_nan[t > edge - 1.0 + 0.01] = np.nan  # the data end on the plateau: no crossing
    assert first_crossing(t, prof_nan, level, +1) is None
    assert first_crossing(t, prof, 1001.0, +1) is None  # not above the level where it starts


def _ball_volume(centre_ijk: np.ndarray, radius_mm: float) -> tuple[np.ndarray, DataRegion]:
    """A clipped 3000 HU ball on 0 HU, no FOV circle (the array's faces are the only edge)."""
    shape = (12, 40, 40)
    region = DataRegion(shape, SPACING, None)
    kk, jj, ii = np.meshgrid(*(np.arange(n) for n in shape), indexing="ij")
    r = np.sqrt(
        ((ii - centre_ijk[0]) * SPACING[0]) ** 2
        + ((jj - centre_ijk[1]) * SPACING[1]) ** 2
        + ((kk - centre_ijk[2]) * SPACING[2]) ** 2
    )
    return np.where(r <= radius_mm, 3000, 0).astype(np.int16), region


@given(dist_mm=st.floats(0.0, 0.6))
def test_plateau_reaches_edge_refuses_a_cut_ball_and_keeps_a_whole_one(dist_mm: float) -> None:
    """Along +i: a ball whose plateau runs into the array's last column is refused; the same ball
    with ≥ 2 mm of background to that column is not; an estimate off the plateau is refused."""
    u = np.array([1.0, 0.0, 0.0])
    args = (1.25, 2.75, 1.5)  # radius, ball, shell (mm)
    cut_c = np.array([39.0 - dist_mm / SPACING[0], 20.0, 6.0])  # centre ≤ 0.6 mm from the last column
    vox, region = _ball_volume(cut_c, 1.25)
    assert plateau_reaches_edge(vox, cut_c, SPACING, u, *args, region, 0.9)
    whole_c = np.array([20.0 + dist_mm / SPACING[0], 20.0, 6.0])
    vox, region = _ball_volume(whole_c, 1.25)
    assert not plateau_reaches_edge(vox, whole_c, SPACING, u, *args, region, 0.9)
    off_plateau = whole_c + np.array([2.0 / SPACING[0], 0.0, 0.0])  # 2 mm from the centre: background
    assert plateau_reaches_edge(vox, off_plateau, SPACING, u, *args, region, 0.9)
