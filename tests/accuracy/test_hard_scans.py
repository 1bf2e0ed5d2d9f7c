"""Hard scans of issue #11 (CI subset): tungsten carbide under strong scatter, and partial imaging.

O-arm pixels (0.415 × 0.833 mm) on a 256 × 256 matrix with the ``small-realistic`` physics
(kernel scatter, 0.8 mm PSF, 10⁴ photons), so each scan simulates in ~15 s.

* ``wc_rows40``: 40 tungsten-carbide spheres, neighbours in rows, SPR 0.3.  Before the blob split
  29 of 40 were rejected as "elongated or oversized metal" (streak tails) and registration refused.
  Every fully imaged sphere found, nothing else, registration answers and is not wrong (design.md
  §8: every sphere on its own hole, TRE ≤ 5 × predicted).  The issue's FLE target for WC under
  strong scatter (mean ≤ 0.05, max ≤ 0.15 mm): with the default ``subvoxel`` centroid this scan
  measured 0.063 / 0.318 mm; with the ``core`` estimator chosen for tungsten carbide
  (registration/core_centroid.py) 0.049 / 0.116 mm, with its window 0.044 / 0.092 mm (2 rays per
  detector bin as here; 0.041 / 0.070 mm with the hard sweep's 4, ``WC_SUBRAYS``).
* partial FOV: ``bai2018_cube`` shifted 40 mm off axis, 60 slices (11 of 28 spheres fully imaged).
  Before the image-side base triples, correspondence matched 0 and refused.  Every imaged sphere
  found and matched to its own hole; steel FLE max ≤ 0.12 mm (issue target).
* partial FOV, tungsten carbide: ``wc_rows40`` 45 mm off axis, 50 slices, SPR 0.3.  Before the
  symmetric edge re-measurement, spheres cut by the FOV circle were reported (2 false positives
  on each of 2 sweep scans).  Every imaged sphere found, nothing else; WC FLE target.
"""

from __future__ import annotations

import pytest

from mocks.oarm import simulator as sim
from registration.detection import detect_spheres
from registration.matching.register import register_points
from tests.helpers.accuracy import (
    STEEL_MAX_MM,
    WC_MAX_MM,
    WC_MEAN_MM,
    _correct,
    _every_sphere_and_a_correct_registration,
    _match,
    _params,
    _scan,
)


@pytest.fixture(scope="module")
def wc_scan():  # type: ignore[no-untyped-def]
    phantom, scan = _scan("wc_rows40.toml", (2, -3, 1, 5, -4, 30), scatter_spr=0.3)
    result = detect_spheres(sim.scan_to_volume(scan), _params(phantom))
    return phantom, scan, result


def test_tungsten_carbide_strong_scatter_neighbouring_spheres(wc_scan) -> None:  # type: ignore[no-untyped-def]
    phantom, scan, result = wc_scan
    assert len(scan.spheres_image_mm) == 40
    reg = _every_sphere_and_a_correct_registration(phantom, scan, result)
    assert reg.n_matched >= 38


def test_tungsten_carbide_strong_scatter_meets_the_fle_target(wc_scan) -> None:  # type: ignore[no-untyped-def]
    _, scan, result = wc_scan
    err, _, _ = _match(result, scan.spheres_image_mm)
    assert err.mean() <= WC_MEAN_MM and err.max() <= WC_MAX_MM, err


def test_partial_fov_answered_on_the_imaged_subset() -> None:
    phantom, scan = _scan("bai2018_cube.toml", (40, -3, 1, 5, -4, 30), n_slices=60, scatter_spr=0.2)
    truth = scan.spheres_image_mm
    assert 6 <= len(truth) < phantom.n_spheres
    result = detect_spheres(sim.scan_to_volume(scan), _params(phantom))
    err, misses, false_pos = _match(result, truth)
    assert misses == 0 and false_pos == 0
    assert err.max() <= STEEL_MAX_MM, err
    reg = register_points(phantom.centres_phantom_mm, result.centres_image_mm, phantom=phantom)
    assert reg.n_matched == len(truth)
    assert _correct(phantom, scan, result, reg)


def test_tungsten_carbide_partial_fov_reports_only_whole_spheres() -> None:
    phantom, scan = _scan("wc_rows40.toml", (45, -3, 1, 5, -4, 30), n_slices=50, scatter_spr=0.3)
    truth = scan.spheres_image_mm
    assert 6 <= len(truth) < phantom.n_spheres
    result = detect_spheres(sim.scan_to_volume(scan), _params(phantom))
    err, misses, false_pos = _match(result, truth)
    assert misses == 0 and false_pos == 0, [r.reason for r in result.rejections if "cut" in r.reason]
    assert err.mean() <= WC_MEAN_MM and err.max() <= WC_MAX_MM, err
