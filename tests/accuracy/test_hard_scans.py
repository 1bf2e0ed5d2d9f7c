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

import numpy as np
import pytest

sim = pytest.importorskip("mocks.oarm.simulator", reason="needs the O-arm simulator (issue #2)")

from registration import frames  # noqa: E402
from registration.detection import (  # noqa: E402
    DetectionParams,
    DetectionResult,
    detect_spheres,
    method_for_material,
)
from registration.phantom import Phantom, load_phantom  # noqa: E402
from registration.register import register_points  # noqa: E402
from tests.conftest import CONFIGS  # noqa: E402

MAX_MATCH_MM = 1.0
"""A detection within this distance of a truth centre is a hit (spheres are ≥ 15 mm apart)."""


def _match(result: DetectionResult, truth: np.ndarray) -> tuple[np.ndarray, int, int]:
    c = result.centres_image_mm
    d = np.linalg.norm(c[:, None, :] - truth[None], axis=2)
    hit = d.min(axis=1) < MAX_MATCH_MM
    return d.min(axis=1)[hit], len(truth) - len(set(d.argmin(axis=1)[hit].tolist())), int((~hit).sum())


def _scan(phantom_file: str, pose: tuple[float, ...], **settings: float):  # type: ignore[no-untyped-def]
    phantom = load_phantom(CONFIGS / "phantoms" / phantom_file)
    kw = dict(
        rows=256, columns=256, pixel_mm=0.415, slice_spacing_mm=0.833, n_slices=120, n_views=240, seed=3
    )
    kw.update(settings)
    s = sim.AcquisitionSettings.preset("small-realistic", **kw)
    scan = sim.simulate_scan(phantom, frames.transform_from_xyz_rpy(pose[:3], pose[3:]), s)
    return phantom, scan


def _params(phantom: Phantom) -> DetectionParams:
    """Detection as the service runs it for this phantom: its sphere diameter and the centre
    estimator for its sphere material."""
    return DetectionParams(
        sphere_diameter_mm=phantom.sphere_diameter_mm, method=method_for_material(phantom.sphere_material)
    )


def _correct(phantom, scan, result, reg) -> bool:  # type: ignore[no-untyped-def]
    truth = frames.apply(scan.image_from_phantom, phantom.centres_phantom_mm)
    got = result.centres_image_mm
    return all(
        np.linalg.norm(truth[a] - got[b]) < MAX_MATCH_MM
        for a, b in zip(reg.robot_indices, reg.image_indices, strict=True)
    )


WC_MEAN_MM, WC_MAX_MM = 0.05, 0.15
"""Issue #11 Done-when: FLE mean / max for tungsten carbide with strong scatter."""
STEEL_MAX_MM = 0.12
"""Issue #11 Done-when: FLE max for steel."""
WRONG_TRE_FACTOR = 5.0
"""design.md §8: wrong if the error at a target exceeds this many times its predicted TRE."""
TARGETS_PHANTOM_MM = np.array([[0.0, 0.0, 0.0], [0.0, 0.0, 100.0]])


def _assert_tre_within_predicted(scan, reg) -> None:  # type: ignore[no-untyped-def]
    """design.md §8: not wrong — the error at the targets within WRONG_TRE_FACTOR × predicted TRE."""
    tre = np.linalg.norm(
        frames.apply(reg.image_from_robot, TARGETS_PHANTOM_MM)
        - frames.apply(scan.image_from_phantom, TARGETS_PHANTOM_MM),
        axis=1,
    )
    assert np.all(tre <= WRONG_TRE_FACTOR * reg.predicted_tre_mm), (tre, reg.predicted_tre_mm)


def _every_sphere_and_a_correct_registration(phantom, scan, result):  # type: ignore[no-untyped-def]
    """Every fully imaged sphere found and nothing else; the registration answers, every sphere on
    its own hole, TRE within the predicted bound (design.md §8).  Returns the registration."""
    _, misses, false_pos = _match(result, scan.spheres_image_mm)
    assert misses == 0, [r.reason for r in result.rejections]
    assert false_pos == 0
    reg = register_points(
        phantom.centres_phantom_mm,
        result.centres_image_mm,
        phantom=phantom,
        targets_robot_mm=TARGETS_PHANTOM_MM,
    )
    assert _correct(phantom, scan, result, reg)
    _assert_tre_within_predicted(scan, reg)
    return reg


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
    result = detect_spheres(sim.scan_to_volume(scan))
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
