"""The ``core`` centre estimator (registration/core_centroid.py) and its selection by material."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from test_detection import SPACING, make_volume

from registration.detection import (
    METHOD_FOR_MATERIAL,
    METHODS,
    DetectionParams,
    detect_spheres,
    method_for_material,
)
from registration.detection.centroid import LINEAR_BACKGROUND_MIN_VOXELS
from registration.detection.estimators.core import core_edge_centre
from registration.detection.estimators.core_centroid import CoreParams, CoreWeights, core_centroid
from registration.detection.estimators.sphere_fit import blurred_ball
from registration.errors import DetectionError
from registration.model.phantom import SPHERE_MATERIALS

SAT_HU = 3071.0
RADIUS_MM = 1.25
INPLANE_TOL_MM, SLICE_TOL_MM = 0.07, 0.10
"""Bounds on the sampling error of one noise-free synthetic sphere (see the property test)."""
_D = DetectionParams()
WEIGHTS = CoreWeights(
    CoreParams(),
    _D.centroid_margin_hu,
    _D.background_shell_mm,
    LINEAR_BACKGROUND_MIN_VOXELS,
)


def _opaque_sphere(
    centre_mm: np.ndarray, contrast_hu: float, sigma_mm: float, bg_hu: float, grad_hu_mm: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Voxels (values, coords mm) within 4.25 mm of a grid point near ``centre_mm``: a blurred ball
    of ``contrast_hu`` on a plane background, clipped at 3071 HU like a 12-bit export."""
    spacing = np.asarray(SPACING)
    base = np.rint(centre_mm / spacing)
    half = np.ceil(4.25 / spacing).astype(int) + 1
    axes = [(base[a] + np.arange(-half[a], half[a] + 1)) * spacing[a] for a in range(3)]
    grid = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, 3)
    grid = grid[np.linalg.norm(grid - base * spacing, axis=1) <= 4.25]
    r = np.linalg.norm(grid - centre_mm, axis=1)
    values = bg_hu + (grid - centre_mm) @ grad_hu_mm + contrast_hu * blurred_ball(r, RADIUS_MM, sigma_mm)
    return np.minimum(values, SAT_HU), grid


@settings(max_examples=60, deadline=None)
@given(
    offset=st.tuples(*(st.floats(0.0, 1.0),) * 3),
    contrast_hu=st.floats(2.0e4, 2.0e5),
    sigma_mm=st.floats(0.25, 0.4),
    bg_hu=st.floats(-200.0, 400.0),
    grad=st.tuples(*(st.floats(-80.0, 80.0),) * 3),
)
def test_core_centroid_finds_a_clipped_opaque_sphere(
    offset: tuple[float, float, float],
    contrast_hu: float,
    sigma_mm: float,
    bg_hu: float,
    grad: tuple[float, float, float],
) -> None:
    centre = (np.array([40.0, 50.0, 30.0]) + np.asarray(offset)) * np.asarray(SPACING)
    values, coords = _opaque_sphere(centre, contrast_hu, sigma_mm, bg_hu, np.asarray(grad))
    start = centre + np.array([0.3, -0.25, 0.35])
    got = core_centroid(values, coords, start, RADIUS_MM, SAT_HU, WEIGHTS)
    assert got is not None
    # An exact blurred ball on a tilted plane: only the voxel sampling of the clipped core errs.
    # Over 300 random draws it erred at most 0.044 mm in-plane and 0.079 mm along the 0.833 mm
    # slices (one 85 % margin, 1.5 mm window: 0.060 / 0.081 mm; unwindowed 1.0 mm ball: 0.058 /
    # 0.084 mm; the default centroid's ball and margin: 0.042 / 0.073 mm), so these bounds catch a
    # wrong frame, a lost background or a diverging iteration, not that sampling bias.
    err = np.abs(got - centre)
    assert max(err[0], err[1]) <= INPLANE_TOL_MM and err[2] <= SLICE_TOL_MM, (got, centre)


def test_core_centroid_is_exact_on_a_symmetrically_sampled_sphere() -> None:
    centre = np.array([40.0, 50.0, 30.0]) * np.asarray(SPACING)
    values, coords = _opaque_sphere(centre, 1.0e5, 0.3, 100.0, np.zeros(3))
    start = centre + np.array([0.3, -0.25, 0.35])
    # The windowed re-centring converges geometrically to the exact centre: run to convergence it
    # is exact, and with the defaults it stops within its tolerance of it.
    converged = replace(WEIGHTS, core=CoreParams(max_iterations=200, tolerance_mm=0.0))
    got = core_centroid(values, coords, start, RADIUS_MM, SAT_HU, converged)
    assert got is not None
    np.testing.assert_allclose(got, centre, atol=1e-9)
    got = core_centroid(values, coords, start, RADIUS_MM, SAT_HU, WEIGHTS)
    assert got is not None
    assert float(np.linalg.norm(got - centre)) <= CoreParams().tolerance_mm


def test_core_centroid_without_a_core_gives_none() -> None:
    coords = np.stack(np.meshgrid(*(np.arange(-5.0, 5.0, 0.5),) * 3, indexing="ij"), axis=-1).reshape(-1, 3)
    values = np.full(len(coords), 100.0)
    assert core_centroid(values, coords, np.zeros(3), RADIUS_MM, np.inf, WEIGHTS) is None


def test_core_params_reach_the_patch() -> None:
    params = DetectionParams(method="core", core=CoreParams(bloom_mm=0.8))
    assert params.core.bloom_mm == 0.8


def test_core_method_finds_every_sphere_and_uses_the_edge_window_near_an_edge() -> None:
    # Spheres well inside, and one 1.9 mm inside the first slice (its patch reaches past the edge).
    centres = np.array([[40.0, 40.0, 24.0], [75.0, 55.0, 30.0], [60.0, 70.0, 2.3]])
    vol = make_volume(centres)
    sub = detect_spheres(vol, DetectionParams())
    core = detect_spheres(vol, DetectionParams(method="core"))
    assert len(core.spheres) == len(sub.spheres) == 3
    truth = centres * np.asarray(SPACING)
    params = DetectionParams(method="core")
    for s_sub, s_core in zip(sub.spheres, core.spheres, strict=True):
        err = np.linalg.norm(truth - s_core.center_image_mm, axis=1).min()
        if s_core.center_voxel[2] < 4.0:
            # Near the first slice: the core weights with the symmetric edge window, started from
            # the sub-voxel estimate.  This synthetic steel sphere (15000 HU, not opaque) errs
            # 0.093 mm along k there (the default weights: 0.066 mm).
            edge = core_edge_centre(vol.voxels, s_sub.center_voxel, np.asarray(SPACING), params, None)
            np.testing.assert_allclose(s_core.center_voxel, edge)
            assert err <= 0.15, err
        else:
            assert err <= 0.01, err


@pytest.mark.parametrize("material", SPHERE_MATERIALS)
def test_every_sphere_material_has_a_known_method(material: str) -> None:
    assert method_for_material(material) in METHODS
    assert set(METHOD_FOR_MATERIAL) <= set(SPHERE_MATERIALS)
    assert method_for_material("tungsten_carbide") == "core"
    assert method_for_material("steel") == "rays"
    assert method_for_material("titanium") == "rays"


def test_core_centroid_averages_its_levels() -> None:
    centre = (np.array([40.0, 50.0, 30.0]) + np.array([0.31, 0.62, 0.27])) * np.asarray(SPACING)
    values, coords = _opaque_sphere(centre, 5.0e4, 0.3, 100.0, np.array([20.0, -30.0, 10.0]))
    start = centre + np.array([0.3, -0.25, 0.35])
    levels = WEIGHTS.core.averaged_margin_fractions

    def at(*fractions: float) -> np.ndarray | None:
        w = replace(WEIGHTS, core=replace(WEIGHTS.core, averaged_margin_fractions=fractions))
        return core_centroid(values, coords, start, RADIUS_MM, SAT_HU, w)

    each = [at(f) for f in levels]
    assert all(c is not None for c in each)
    # Off-grid, the levels do not agree (else averaging them would change nothing).
    assert float(np.ptp(np.array(each), axis=0).max()) > 1e-4
    np.testing.assert_allclose(
        core_centroid(values, coords, start, RADIUS_MM, SAT_HU, WEIGHTS), np.mean(each, axis=0)
    )


@pytest.mark.parametrize(
    "kwargs",
    [{"averaged_margin_fractions": ()}, {"averaged_margin_fractions": (0.5, 1.2)}, {"margin_fraction": 0.0}],
)
def test_core_params_refuse_margins_outside_the_contrast(kwargs: dict[str, object]) -> None:
    with pytest.raises(DetectionError, match="fractions of the clipped contrast"):
        CoreParams(**kwargs)  # type: ignore[arg-type]


@pytest.mark.parametrize("fraction", [0.0, 1.0, 95.0])
def test_edge_plateau_fraction_must_be_a_fraction(fraction: float) -> None:
    with pytest.raises(DetectionError, match="edge_plateau_fraction"):
        DetectionParams(edge_plateau_fraction=fraction)
