"""Known answers for the simulator's physics tables, chord kernels and FBP (mocks/oarm)."""

from __future__ import annotations

import numpy as np
import pytest

from mocks.oarm import physics
from mocks.oarm.simulator import (
    FBP_INTRINSIC_FWHM_PX,
    AcquisitionSettings,
    _Box,
    _Cylinder,
    _Projector,
    _Sphere,
    box_slice_polygon,
    fbp,
)
from registration.errors import ConfigError


def test_nist_values_at_table_energies() -> None:
    e = np.array([60.0, 100.0])
    assert np.allclose(physics.MATERIALS["water"].mu_rho_cm2_g(e), [0.2059, 0.1707])
    assert np.allclose(physics.MATERIALS["steel"].mu_rho_cm2_g(e), [1.205, 0.3717])


def test_mixture_rule_reproduces_water_from_h_and_o() -> None:
    water_mix = physics.Material("w", 1.0, (("H", 0.1119), ("O", 0.8881)))
    e = np.array([40.0, 60.0, 80.0])
    assert np.allclose(water_mix.mu_rho_cm2_g(e), physics.MATERIALS["water"].mu_rho_cm2_g(e), rtol=0.01)


def test_spectrum_has_at_least_four_bins_between_40_and_120_kev() -> None:
    s = physics.kramers_spectrum()
    assert len(s.energies_kev) >= 4
    assert s.energies_kev.min() >= 35.0 and s.energies_kev.max() <= 120.0
    assert np.isclose(s.weights.sum(), 1.0) and np.all(s.weights > 0)
    assert 55.0 < s.mean_energy_kev < 80.0


def test_steel_beam_hardens() -> None:
    """Effective μ (p / L) of steel falls with thickness: the polychromatic beam hardens."""
    s = physics.kramers_spectrum()
    mu = physics.MATERIALS["steel"].mu_per_mm(s.energies_kev)
    lengths = np.array([0.1, 1.0, 2.5, 5.0])
    p = -np.log(np.exp(-np.outer(lengths, mu)) @ s.weights)
    mu_eff = p / lengths
    assert np.all(np.diff(mu_eff) < 0)
    assert mu_eff[-1] < 0.6 * mu_eff[0]


def test_water_correction_linearises_water() -> None:
    s = physics.kramers_spectrum()
    wc = physics.water_correction(s)
    mu = physics.MATERIALS["water"].mu_per_mm(s.energies_kev)
    lengths = np.array([10.0, 100.0, 250.0])
    p = (-np.log(np.exp(-np.outer(lengths, mu)) @ s.weights)).astype(np.float32)
    assert np.allclose(wc.apply(p), wc.mu_ref_per_mm * lengths, rtol=1e-3)
    assert np.isclose(wc.apply(np.array([-0.01], np.float32))[0], -0.01, atol=1e-4)


def test_plastics_read_their_known_hu() -> None:
    s = physics.kramers_spectrum()
    wc = physics.water_correction(s)
    hu = {
        m: 1000 * (np.sum(s.weights * physics.MATERIALS[m].mu_per_mm(s.energies_kev)) / wc.mu_ref_per_mm - 1)
        for m in ("pmma", "pom", "bone_cortical")
    }
    assert 80 < hu["pmma"] < 140 and 280 < hu["pom"] < 380 and hu["bone_cortical"] > 1200


def test_axis_aligned_cube_cross_section_is_the_square() -> None:
    poly = box_slice_polygon(np.zeros(3), np.eye(3), np.array([35.0, 35.0, 40.0]), 10.0)
    assert len(poly) == 4
    assert np.allclose(sorted(np.abs(poly).ravel()), [35.0] * 8)
    assert len(box_slice_polygon(np.zeros(3), np.eye(3), np.array([35.0, 35.0, 40.0]), 41.0)) == 0


def test_tilted_cube_cross_section_is_a_stretched_rectangle() -> None:
    """A cube tilted 30° about x cut at z = 0: width 2a along x, 2a / cos 30° along y."""
    c, s = np.cos(np.radians(30)), np.sin(np.radians(30))
    rot = np.array([[1, 0, 0], [0, c, -s], [0, s, c]])
    poly = box_slice_polygon(np.zeros(3), rot, np.array([10.0, 10.0, 10.0]), 0.0)
    assert np.isclose(np.ptp(poly[:, 0]), 20.0)
    assert np.isclose(np.ptp(poly[:, 1]), 20.0 / c)


def test_polygon_chords_match_the_square() -> None:
    proj = _Projector(4, 101, 0.5)  # views at 0°, 45°, 90°, 135°
    out = np.zeros((5, 4, 101), np.float32)
    proj.add_box(out, _Box(np.zeros(3), np.eye(3), np.array([10.0, 10.0, 10.0]), ((1, 1.0),)), 0.0)
    t = proj.t_mm
    assert np.allclose(out[1, 0][np.abs(t) < 9.9], 20.0, atol=1e-4)  # view 0°: rays along y
    assert np.all(out[1, 0][np.abs(t) > 10.1] == 0)
    diag = np.clip(2 * (10 * np.sqrt(2) - np.abs(t)), 0, None)  # 45°: triangle profile
    assert np.allclose(out[1, 1], diag, atol=1e-3)


def test_sphere_chords_are_disk_chords() -> None:
    proj = _Projector(2, 201, 0.1)
    out = np.zeros((5, 2, 201), np.float32)
    proj.add_sphere(out, _Sphere(np.array([2.0, 0.0, 0.6]), 1.0, ((4, 1.0), (1, -1.0))), 0.0)
    r2 = 1.0 - 0.36
    expect = 2 * np.sqrt(np.clip(r2 - (proj.t_mm - 2.0) ** 2, 0, None))
    assert np.allclose(out[4, 0], expect, atol=1e-5)
    assert np.allclose(out[1, 0], -expect, atol=1e-5)


def test_cylinder_along_z_is_a_disk_and_stops_at_its_caps() -> None:
    proj = _Projector(3, 121, 0.1)
    cyl = _Cylinder(np.array([0.0, 0.0, 0.0]), np.array([0.0, 0.0, 1.0]), 50.0, 2.0, ((4, 1.0),))
    out = np.zeros((5, 3, 121), np.float32)
    proj.add_cylinder(out, cyl, 10.0)
    expect = 2 * np.sqrt(np.clip(4.0 - proj.t_mm**2, 0, None))
    assert np.allclose(out[4], expect[None], atol=1e-4)
    out[:] = 0
    proj.add_cylinder(out, cyl, -1.0)
    assert not out.any()


def test_cylinder_lying_in_the_plane_has_its_length_as_chord() -> None:
    proj = _Projector(2, 81, 0.5)  # view 0 has rays along +y, view 1 along -x
    cyl = _Cylinder(np.array([0.0, -15.0, 0.0]), np.array([0.0, 1.0, 0.0]), 30.0, 1.0, ((4, 1.0),))
    out = np.zeros((5, 2, 81), np.float32)
    proj.add_cylinder(out, cyl, 0.0)
    assert np.isclose(out[4, 0, 40], 30.0, atol=1e-4)  # ray along the axis
    assert np.isclose(out[4, 1].max(), 2.0, atol=1e-3)  # across the rod: its diameter


@pytest.mark.parametrize("window", ["shepp-logan", "hann"])
def test_fbp_scale_and_psf(window: str) -> None:
    """A uniform disk reconstructs to its μ; a thin wire to the documented FWHM."""
    v, d, det = 180, 161, 0.5
    proj = _Projector(v, d * 9, det / 9)
    out = np.zeros((5, v, d * 9), np.float32)
    proj.add_sphere(out, _Sphere(np.array([1.0, -2.0, 0.0]), 20.0, ((0, 0.02),)), 0.0)
    proj.add_sphere(out, _Sphere(np.array([-25.0, 15.0, 0.0]), 0.03, ((1, 1.0),)), 0.0)
    sino = out[:2].reshape(2, v, d, 9).mean(-1)
    pix = np.array([[1.0, -2.0], [5.0, 3.0]])
    mu = fbp(sino[:1].astype(np.float32), det, pix, window)
    assert np.allclose(mu[:, 0], 0.02, rtol=0.02)
    xs = -25.0 + (np.arange(81) - 40) * det / 8
    img = fbp(sino[1:].astype(np.float32), det, np.stack([xs, np.full_like(xs, 15.0)], 1), window)[:, 0]
    above = xs[img >= img.max() / 2]
    fwhm_px = (above[-1] - above[0] + det / 8) / det
    assert abs(fwhm_px - FBP_INTRINSIC_FWHM_PX[window]) < 0.25


def test_settings_validation() -> None:
    with pytest.raises(ConfigError, match="orientation"):
        AcquisitionSettings(orientation="sagittal-ish")
    with pytest.raises(ConfigError, match="preset"):
        AcquisitionSettings.preset("huge")
    with pytest.raises(ConfigError, match="unknown acquisition setting"):
        AcquisitionSettings.preset("small", pixels=3)
    assert AcquisitionSettings.preset("oarm").rows == 512


@pytest.mark.parametrize("orientation", ["axial", "axial-flipped", "axial-rot90", "oblique"])
def test_volume_centre_is_image_origin_and_affine_is_rigid_scaled(orientation: str) -> None:
    s = AcquisitionSettings.preset("small", orientation=orientation)
    a = s.image_from_voxel()
    centre = a @ np.array([(s.columns - 1) / 2, (s.rows - 1) / 2, (s.n_slices - 1) / 2, 1.0])
    assert np.allclose(centre[:3], 0.0, atol=1e-12)
    r = a[:3, :3] / np.array([s.pixel_mm, s.pixel_mm, s.slice_spacing_mm])
    assert np.allclose(r.T @ r, np.eye(3)) and np.isclose(np.linalg.det(r), 1.0)


# ---------------------------------------------------------------- issue #11: materials and scatter


def test_tungsten_values_and_k_edge_jump() -> None:
    """NIST Z = 74 rows are reproduced and the K edge at 69.525 keV is not interpolated across."""
    w = physics.Material("w", 19.3, (("W", 1.0),))
    assert np.allclose(w.mu_rho_cm2_g(np.array([60.0, 80.0, 100.0])), [3.713, 7.810, 4.438])
    below, above = w.mu_rho_cm2_g(np.array([physics.W_K_EDGE_KEV - 0.01, physics.W_K_EDGE_KEV + 0.01]))
    assert np.isclose(below, 2.552, rtol=1e-3) and np.isclose(above, 11.23, rtol=1e-3)


def test_tungsten_carbide_and_titanium_attenuation() -> None:
    """WC = 93.87 % W + 6.13 % C by mass at 15.63 g/cm³; Ti between plastic and steel."""
    e = np.array([50.0, 100.0])
    wc = physics.MATERIALS["tungsten_carbide"]
    expect = 0.9387 * np.array([5.949, 4.438]) + 0.0613 * np.array([0.1871, 0.1514])
    assert np.allclose(wc.mu_rho_cm2_g(e), expect, rtol=1e-6)
    assert np.isclose(wc.density_g_cm3, 15.63)
    mu = {m: physics.MATERIALS[m].mu_per_mm(e) for m in ("pmma", "titanium", "steel", "tungsten_carbide")}
    assert np.all(mu["pmma"] < mu["titanium"]) and np.all(mu["titanium"] < mu["steel"])
    assert np.all(mu["tungsten_carbide"] > 5 * mu["steel"])


def test_k_edge_spectrum_has_a_bin_edge_at_the_k_edge() -> None:
    s = physics.kramers_spectrum(bin_edges_kev=physics.K_EDGE_BIN_EDGES_KEV)
    assert physics.W_K_EDGE_KEV in physics.K_EDGE_BIN_EDGES_KEV and len(s.energies_kev) == 9
    with pytest.raises(ValueError, match="sphere material"):
        physics.attenuation_matrix_per_mm(s, "pmma", "gold")


def test_kernel_scatter_has_the_requested_spr_behind_the_object() -> None:
    from mocks.oarm.simulator import kernel_scatter

    k, v, d = 12, 3, 400
    t = (np.arange(d) - d / 2) * 0.4
    primary = np.ones((k, v, d), np.float32)
    primary[:, :, np.abs(t) < 30] = 0.2  # a 60 mm wide object
    for spr in (0.1, 0.3):
        s = kernel_scatter(primary, spr, 60.0, 0.4, 0.8)
        behind = primary < 0.98
        for view in range(v):
            ratio = s[:, view][behind[:, view]].sum() / primary[:, view][behind[:, view]].sum()
            assert np.isclose(ratio, spr, rtol=1e-4)
        # Broad and smooth: it peaks behind the object's centre and spills past its edges.
        prof = s[k // 2, 0]
        assert np.argmax(prof) in range(d // 2 - 10, d // 2 + 10)
        assert prof[np.searchsorted(t, 40.0)] > 0.2 * prof.max()
        assert np.all(np.abs(np.diff(prof)) < 0.01 * prof.max())


def test_scatter_cups_a_uniform_block() -> None:
    """Centre-minus-edge HU of the plastic cube drops as the scatter-to-primary ratio rises."""
    from mocks.oarm.simulator import SceneExtras, simulate_scan
    from registration.model.phantom import load_phantom
    from tests.helpers.paths import CONFIGS

    ph = load_phantom(CONFIGS / "phantoms" / "bai2018_cube.toml")
    extras = SceneExtras(sphere_material="plastic", empty_holes=False)
    cup = []
    for spr in (0.0, 0.1, 0.3):
        s = AcquisitionSettings.preset(
            "small", n_slices=6, noise=False, scatter_spr=spr, scatter_fraction=0.0
        )
        hu = simulate_scan(ph, np.eye(4), s, extras).hu[3].astype(float)
        centre = hu[75:85, 75:85].mean()
        edge = hu[76:84, 120:124].mean()  # 28–31 mm from the centre; the cube's half width is 35 mm
        cup.append(centre - edge)
    assert abs(cup[0]) < 15.0  # no scatter: water-corrected PMMA is flat
    assert cup[1] < cup[0] - 50.0 and cup[2] < cup[1] - 50.0


def test_scene_extras_material_and_tolerance_rules() -> None:
    from mocks.oarm.simulator import SceneExtras

    with pytest.raises(ConfigError, match="sphere_material"):
        SceneExtras(sphere_material="gold")
    with pytest.raises(ConfigError, match="hole_tolerance_mm"):
        SceneExtras(hole_tolerance_mm=-0.01)
    with pytest.raises(ConfigError, match="scatter_spr"):
        AcquisitionSettings(scatter_spr=3.0)


def test_hole_tolerance_moves_spheres_within_the_tolerance(phantom) -> None:
    from mocks.oarm.simulator import SceneExtras

    nominal = phantom.centres_phantom_mm
    a = SceneExtras(hole_tolerance_mm=0.02).actual_centres_phantom_mm(phantom)
    b = SceneExtras(hole_tolerance_mm=0.02).actual_centres_phantom_mm(phantom)
    d = a - nominal
    assert np.array_equal(a, b), "the phantom's machining errors must not change between scans"
    assert np.all(np.abs(d) <= 0.02) and np.abs(d).max() > 0.015 and np.std(d) > 0.005
    assert np.array_equal(SceneExtras().actual_centres_phantom_mm(phantom), nominal)


def test_imaged_spheres_splits_full_and_partial() -> None:
    from mocks.oarm.simulator import imaged_spheres

    s = AcquisitionSettings.preset("small")  # half extents 55.65 × 55.65 × 47.5 mm, FOV r 56 mm
    centres = np.array([[0, 0, 0], [0, 0, 46.8], [0, 0, 48.5], [55.5, 0, 0], [0, 0, 60.0], [42.0, 42.0, 0]])
    full, part = imaged_spheres(centres.astype(float), 1.25, s)
    assert full.tolist() == [0] and part.tolist() == [1, 2, 3]


def test_realistic_presets_keep_the_legacy_ones_unchanged() -> None:
    legacy = AcquisitionSettings.preset("demo")
    real = AcquisitionSettings.preset("demo-realistic")
    assert legacy.scatter_spr == 0.0 and legacy.energy_bin_edges_kev == physics.DEFAULT_BIN_EDGES_KEV
    assert 0.1 <= real.scatter_spr <= 0.3 and real.n_slices == legacy.n_slices
    assert AcquisitionSettings.preset("oarm-realistic").n_views == 196
