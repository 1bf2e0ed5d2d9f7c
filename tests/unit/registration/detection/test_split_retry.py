"""The tungsten split retry (issue #43): a blob whose first split leaves no sphere-sized core is
split again with the wider ``split_retry_core_fraction`` opening before it is called oversized.

The volumes are built here (supersampled geometry, 15000 HU metal, 0.7 mm PSF, 3071 HU clip,
noise), as in test_detection.py, so no simulator is needed.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
import pytest
from numpy.typing import NDArray
from scipy import ndimage

from registration.detection import detect_spheres, params_for_spheres
from registration.imaging.volume import Volume

SP = (0.415, 0.415, 0.833)  # (i, j, k) mm: the commonly quoted O-arm grid
SHAPE = (24, 48, 48)  # (k, j, i)
R_MM = 1.25
B = NDArray[np.bool_]
Shape = Callable[[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]], B]


def _volume(centre_ijk: tuple[float, float, float], extra: Shape, ss: int = 4) -> Volume:
    """A saturated Ø2.5 mm ball at ``centre_ijk`` plus the metal ``extra`` (x, y, z mm from it)."""
    k, j, i = np.mgrid[0 : SHAPE[0], 0 : SHAPE[1], 0 : SHAPE[2]].astype(np.float64)
    off = (np.arange(ss) + 0.5) / ss - 0.5
    occ = np.zeros(SHAPE)
    for a in off:
        for b in off:
            for d in off:
                x = (i + a - centre_ijk[0]) * SP[0]
                y = (j + b - centre_ijk[1]) * SP[1]
                z = (k + d - centre_ijk[2]) * SP[2]
                occ += (x * x + y * y + z * z <= R_MM**2) | extra(x, y, z)
    vol = 100.0 + occ / ss**3 * 14900.0
    sig = 0.7 / 2.3548
    vol = ndimage.gaussian_filter(vol, (sig / SP[2], sig / SP[1], sig / SP[0]))
    vol += np.random.default_rng(0).normal(0.0, 20.0, SHAPE)
    vox = np.clip(np.rint(vol), -1024, 3071).astype(np.int16)
    return Volume(vox, np.diag([*SP, 1.0]), series_uid="1.2.826.0.1.3680043.2.1125.split")


def _streak_bar(x: NDArray[np.float64], y: NDArray[np.float64], z: NDArray[np.float64]) -> B:
    """A bright bar 7 mm long along the face (i), 2 mm thick across it (j), through the sphere's
    slices: the saturated streak of a tungsten-carbide row."""
    return np.asarray((np.abs(x) <= 3.5) & (np.abs(y) <= 1.0) & (np.abs(z) <= R_MM))


def _rod(x: NDArray[np.float64], y: NDArray[np.float64], z: NDArray[np.float64]) -> B:
    """A Ø3 mm rod 10 mm long through the ball: thicker than either opening."""
    return np.asarray((np.abs(x) <= 5.0) & (y * y + z * z <= 1.5**2))


CENTRE = (24.0, 23.6, 12.5)


@pytest.fixture(scope="module")
def streaked() -> Volume:
    return _volume(CENTRE, _streak_bar)


def test_a_sphere_in_a_thick_streak_is_found_by_the_retry(streaked: Volume) -> None:
    p = params_for_spheres("tungsten_carbide", 2.5)
    result = detect_spheres(streaked, p)
    assert len(result.spheres) == 1, [r.reason for r in result.rejections]
    err_mm = (result.spheres[0].center_voxel - np.array(CENTRE)) * np.array(SP)
    assert float(np.linalg.norm(err_mm)) < 0.1


def test_without_the_retry_the_first_split_calls_it_oversized(streaked: Volume) -> None:
    """The case the retry exists for: the 0.75 R opening keeps the 2 mm streak."""
    p = params_for_spheres("tungsten_carbide", 2.5, split_retry_core_fraction=0.75)
    result = detect_spheres(streaked, p)
    assert not result.spheres
    assert any("oversized" in r.reason for r in result.rejections)


def test_a_rod_is_still_rejected_after_the_retry() -> None:
    result = detect_spheres(_volume(CENTRE, _rod), params_for_spheres("tungsten_carbide", 2.5))
    assert not result.spheres
    assert any("connecting rod" in r.reason for r in result.rejections)
