"""The simulator's hole models (issue #43): the tight fit, the drilled hole and the no-cube control,
by their path lengths along known rays in the slice-wise and the cone-beam scene."""

from __future__ import annotations

import math
from typing import Any

import numpy as np
import pytest

from mocks.oarm import cbct, physics
from mocks.oarm.simulator import SceneExtras, _build_scene, _Projector, _trace_plane, _z_range
from registration.errors import ConfigError

SLOT = {m: i for i, m in enumerate(physics.SCENE_MATERIALS)}
R = 1.25
OFF_AXIS_MM = 1.0  # the ray passes this far beside the hole axes


def _ray_target(phantom: Any) -> tuple[float, float, int]:
    """(x, z) of a ±y hole pair's axis and how many of the pair hold a sphere."""
    holes, axes = phantom.holes_phantom_mm, phantom.hole_axes_phantom
    on_y = np.flatnonzero(np.abs(axes[:, 1]) > 0.5)
    h = holes[on_y[0]]
    pair = [i for i in on_y if np.allclose(holes[i, [0, 2]], h[[0, 2]])]
    assert len(pair) == 2
    return float(h[0]), float(h[2]), int(phantom.filled[pair].sum())


def _slice_paths(phantom: Any, extras: SceneExtras) -> np.ndarray:
    """(n_slots,) path lengths of the ray along +y, OFF_AXIS_MM beside a ±y hole pair's axis
    (slice-wise projector, phantom frame = scanner frame)."""
    x, z, _ = _ray_target(phantom)
    objs = _build_scene(phantom, np.eye(4), extras, np.eye(4), np.eye(4))
    det_mm, n_det = 0.5, 401
    proj = _Projector(2, n_det, det_mm)  # view 0: rays along +y at x = t
    plane = np.zeros((len(SLOT), 2, n_det), np.float32)
    _trace_plane(plane, objs, [_z_range(o) for o in objs], proj, z)
    return plane[:, 0, round((x + OFF_AXIS_MM) / det_mm + (n_det - 1) / 2)]


def _cone_paths(phantom: Any, extras: SceneExtras) -> np.ndarray:
    """The same ray through the cone-beam scene."""
    x, z, _ = _ray_target(phantom)
    scene = cbct._build(phantom, np.eye(4), extras, np.eye(4))
    o, d = np.array([x + OFF_AXIS_MM, -500.0, z]), np.array([[0.0, 1.0, 0.0]])
    paths = np.zeros((len(SLOT), 1), np.float32)
    cbct._add_extended(paths, scene, o, d)
    for obj, chords in [(h, cbct._cylinder_chords) for h in scene.holes] + [
        (b, cbct._sphere_chords) for b in scene.balls
    ]:
        c = chords(o, d, obj)
        for slot, sign in obj.paths:
            paths[slot] += sign * c
    return paths[:, 0]


@pytest.mark.parametrize("paths_of", [_slice_paths, _cone_paths], ids=["slice-wise", "cone-beam"])
def test_drilled_holes_leave_air_around_the_sphere(phantom: Any, paths_of: Any) -> None:
    """Beside the axis, a tight hole removes the sphere's chord of plastic, a drilled one its whole
    depth (air gaps); the metal is the sphere's chord in both."""
    _, _, n_metal = _ray_target(phantom)
    sphere_chord = 2.0 * math.sqrt(R**2 - OFF_AXIS_MM**2)
    width = float(phantom.size_mm[1])
    tight = paths_of(phantom, SceneExtras(hole_model="tight"))
    drilled = paths_of(phantom, SceneExtras(hole_model="drilled"))
    assert tight[SLOT["plastic"]] == pytest.approx(width - 2 * sphere_chord, abs=2e-3)
    assert drilled[SLOT["plastic"]] == pytest.approx(width - 2 * 2.5, abs=2e-3)
    for p in (tight, drilled):
        assert p[SLOT["sphere"]] == pytest.approx(n_metal * sphere_chord, abs=2e-3)


@pytest.mark.parametrize("paths_of", [_slice_paths, _cone_paths], ids=["slice-wise", "cone-beam"])
def test_the_control_has_the_spheres_and_no_plastic(phantom: Any, paths_of: Any) -> None:
    _, _, n_metal = _ray_target(phantom)
    p = paths_of(phantom, SceneExtras(cube=False))
    assert p[SLOT["plastic"]] == pytest.approx(0.0, abs=1e-6)
    assert p[SLOT["sphere"]] == pytest.approx(n_metal * 2.0 * math.sqrt(R**2 - OFF_AXIS_MM**2), abs=2e-3)


def test_a_sphere_is_seated_on_the_bottom_of_its_drilled_hole(phantom: Any) -> None:
    """Nominal centre 1.25 mm below the face: a 2.5 mm deep hole holds the Ø2.5 mm sphere there,
    a 3.0 mm deep one 0.5 mm deeper (along the hole's outward axis)."""
    nominal = phantom.centres_phantom_mm
    same = SceneExtras(hole_model="drilled").actual_centres_phantom_mm(phantom)
    deeper = SceneExtras(hole_model="drilled", hole_depth_mm=3.0).actual_centres_phantom_mm(phantom)
    assert np.allclose(same, nominal)
    assert np.allclose(deeper, nominal - 0.5 * phantom.axes_phantom)


def test_hole_model_rules(phantom: Any) -> None:
    with pytest.raises(ConfigError, match="hole_model"):
        SceneExtras(hole_model="press-fit")
    with pytest.raises(ConfigError, match="cannot hold"):
        SceneExtras(hole_model="drilled", hole_diameter_mm=2.0).actual_centres_phantom_mm(phantom)
