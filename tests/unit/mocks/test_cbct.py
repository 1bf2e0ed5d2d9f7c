"""Cone-beam simulator (issue #11): geometry and FDK against RTK, centroid accuracy.

The RTK comparisons are skipped, with the reason, when itk-rtk is not installed
(``pip install 'oarmreg[cbct]'``); the simulator itself needs only numpy, scipy and OpenCV.
"""

from __future__ import annotations

import dataclasses
import math
from typing import Any

import numpy as np
import pytest

from mocks.oarm import cbct
from mocks.oarm.cbct import ConeBeamSettings, projection_matrix, simulate_cbct_mu
from mocks.oarm.simulator import HU_MAX, HU_MIN, SceneExtras, image_from_scanner
from registration.model import frames

CENTROID_TOL_MM = 0.01
"""Issue #11: noise-free spheres at and 35 mm off the central plane, centroids within 0.01 mm."""

MONO_KEV = 70.0
"""Validation energy (keV), near the mean of the 120 kVp / 4 mm Al spectrum."""

IDEAL: dict[str, Any] = {
    "noise": False,
    "scatter_spr": 0.0,
    "light_spread_fwhm_mm": 0.0,
    "lag_components": (),
    "lag_correction_model": (),
    "monochromatic_kev": MONO_KEV,
    "n_views": 120,
    "det_cols": 512,
    "det_rows": 384,
    "det_pitch_mm": 0.776,
    "subrays": 3,
}
"""Geometry-only acquisition: no noise, scatter, light spread, lag or beam hardening."""

POSE_0 = frames.transform_from_xyz_rpy([0.0, 0.0, 7.5], [0.0, 0.0, 20.0])  # sphere rows at z = 0, 15, 30
POSE_35 = frames.transform_from_xyz_rpy([0.0, 0.0, 12.5], [0.0, 0.0, 20.0])  # top row at z = 35 mm


def _rtk_from_image(s: ConeBeamSettings) -> np.ndarray:
    return cbct.RTK_FROM_SCANNER @ frames.invert(image_from_scanner(s.orientation))


def _centroid(vol: np.ndarray, fraction: float = 0.3) -> np.ndarray:
    """Intensity-weighted centroid [z, y, x] (voxels) above ``fraction`` of the maximum."""
    w = np.clip(vol - fraction * vol.max(), 0.0, None)
    grids = np.mgrid[0 : vol.shape[0], 0 : vol.shape[1], 0 : vol.shape[2]]
    return np.array([(w * g).sum() for g in grids]) / w.sum()


def _roi_mu(
    phantom: Any, pose: np.ndarray, s: ConeBeamSettings, extras: SceneExtras, centres_rtk: np.ndarray
):  # type: ignore[no-untyped-def]
    """μ on a 28³ grid of 0.15 mm voxels around each centre (RTK frame), from one set of views."""
    rtk_from_image = _rtk_from_image(s)
    views, _, _ = cbct.project_scan(phantom, rtk_from_image @ pose, s, extras, rtk_from_image)
    filtered = cbct.filter_projections(views, s)
    n, vox = 28, 0.15
    return [
        cbct.backproject_grid(filtered, s, c - (n - 1) / 2.0 * vox, (n, n, n), (vox, vox, vox))
        for c in centres_rtk
    ], vox


def _targets(phantom: Any, pose: np.ndarray, z_mm: float) -> np.ndarray:
    """The two filled spheres nearest the axial plane z (image frame, mm)."""
    centres = frames.apply(pose, phantom.centres_phantom_mm)
    return centres[np.argsort(np.abs(centres[:, 2] - z_mm), kind="stable")[:2]]


def test_projection_matrices_match_rtk() -> None:
    pytest.importorskip("itk", reason="itk-rtk not installed: pip install 'oarmreg[cbct]'")
    import itk
    from itk import RTK as rtk

    s = ConeBeamSettings.preset("cbct-ci")
    g = rtk.ThreeDCircularProjectionGeometry.New()
    for deg in (0.0, 37.0, 90.0, 211.0):
        g.AddProjection(s.sid_mm, s.sdd_mm, deg)
    for i, deg in enumerate((0.0, 37.0, 90.0, 211.0)):
        ours = projection_matrix(s, math.radians(deg))
        theirs = np.asarray(itk.array_from_matrix(g.GetMatrix(i)))
        assert np.allclose(ours, theirs, atol=1e-9)


def test_numpy_fdk_equals_rtk_fdk() -> None:
    """The numpy/OpenCV FDK reproduces RTK's FDKConeBeamReconstructionFilter voxel for voxel."""
    pytest.importorskip("itk", reason="itk-rtk not installed: pip install 'oarmreg[cbct]'")
    s = ConeBeamSettings.preset(
        "cbct-ci",
        n_views=40,
        det_cols=128,
        det_rows=96,
        det_pitch_mm=3.1,
        **{k: v for k, v in IDEAL.items() if k not in ("n_views", "det_cols", "det_rows", "det_pitch_mm")},
    )
    rng = np.random.default_rng(3)
    axes = np.linalg.qr(rng.normal(size=(3, 3)))[0]
    sl = {m: i for i, m in enumerate(cbct.physics.SCENE_MATERIALS)}
    ball = cbct._Ball(np.array([20.0, 30.0, -10.0]), 3.0, ((sl["sphere"], 1.0), (sl["plastic"], -1.0)))
    box = cbct._Box3(np.array([5.0, 10.0, 0.0]), axes, np.array([30.0, 30.0, 30.0]), ((sl["plastic"], 1.0),))
    scene = cbct._Scene([box], [], [ball])
    mu = cbct.physics.attenuation_matrix_per_mm(cbct._spectrum(s), "pmma", "steel")
    views = np.stack(
        [
            cbct.project_view(s, scene, math.radians(i * 360.0 / s.n_views), mu, np.ones(1), 6)
            for i in range(s.n_views)
        ]
    )
    li = -np.log(views)
    origin = ball.centre_rtk_mm - np.array([10.0, 12.0, 14.0])
    grid = ((21, 25, 29), (1.0, 1.0, 1.0))
    for cut in (0.0, 1.0, 0.6):
        sc = dataclasses.replace(s, hann_cut=cut)
        ours = cbct.fdk_numpy(li.copy(), sc, origin, *grid)
        theirs = cbct.fdk_rtk(li.copy(), sc, origin, *grid)
        assert np.abs(ours - theirs).max() < 1e-4 * np.abs(theirs).max(), cut
        assert np.allclose(_centroid(ours), _centroid(theirs), atol=1e-4)
        assert np.abs(theirs).max() > 0.05  # the steel ball is there (μ in 1/mm)


def test_cylinder_chords() -> None:
    cyl = cbct._Cylinder3(np.zeros(3), np.array([0.0, 0.0, 1.0]), 50.0, 5.0, ())
    o = np.array([-100.0, 0.0, 10.0])
    d = np.array([[1.0, 0.0, 0.0], [1.0, 0.0, 0.0]])
    d[1] = [100.0, 3.0, 0.0]
    d[1] /= np.linalg.norm(d[1])
    got = cbct._cylinder_chords(o, d, cyl)
    assert got[0] == pytest.approx(10.0)
    assert got[1] == pytest.approx(
        2.0 * math.sqrt(25.0 - (3.0 * 100.0 / math.hypot(100.0, 3.0)) ** 2), rel=1e-6
    )
    along = cbct._cylinder_chords(np.array([1.0, 1.0, -20.0]), np.array([[0.0, 0.0, 1.0]]), cyl)
    assert along[0] == pytest.approx(50.0)  # through both end caps
    assert cbct._cylinder_chords(np.array([0.0, 0.0, 60.0]), np.array([[1.0, 0.0, 0.0]]), cyl)[0] == 0.0


def test_isolated_sphere_centroids_in_air() -> None:
    """Geometry alone: a monochromatic steel ball in air, at the isocentre, off-axis and 35 mm
    off-plane (RTK y is the rotation axis), comes back where it was put."""
    s = ConeBeamSettings.preset("cbct-ci", **IDEAL)
    mu = cbct.physics.attenuation_matrix_per_mm(cbct._spectrum(s), "pmma", "steel")
    sl = cbct.physics.SCENE_MATERIALS.index("sphere")
    n, vox = 28, 0.15
    for centre in ([0.0, 0.0, 0.0], [30.0, 0.0, -12.0], [20.0, 35.0, -15.0]):
        c = np.asarray(centre)
        scene = cbct._Scene([], [], [cbct._Ball(c, 1.25, ((sl, 1.0),))])
        views = np.stack(
            [
                cbct.project_view(s, scene, math.radians(i * 360.0 / s.n_views), mu, np.ones(1), 6)
                for i in range(s.n_views)
            ]
        )
        vol = cbct.fdk_numpy(-np.log(views), s, c - (n - 1) / 2.0 * vox, (n, n, n), (vox, vox, vox))
        found = c - (n - 1) / 2.0 * vox + _centroid(vol)[::-1] * vox
        assert np.linalg.norm(found - c) < CENTROID_TOL_MM / 2, (centre, found - c)


def test_fdk_centroids_at_and_off_the_central_plane(phantom) -> None:  # type: ignore[no-untyped-def]
    """Issue #11: the cube's flush steel spheres nearest z = 0 and z = 35 mm, 0.15 mm ROI voxels,
    noise-free and monochromatic, 391 views (the O-arm's standard count): centroids within 0.01 mm
    (measured 0.0018-0.0024 mm; polychromatic 0.0005-0.0016 mm).

    At 120 views the other 27 spheres' view-aliasing streaks shift one of them by 0.012 mm.  The
    stored HU saturate at 3071: thresholded at 1500 HU the sphere is a flat plateau whose weights
    sit in the edge ring, brighter on the plastic side, so that centroid moves 0.01-0.017 mm towards
    the cube.  (The 0.13-0.18 mm inward bias this test once recorded as xfail was a projector bug:
    a ball's sub-ray window ignored balls far away in 3-D whose shadows overlapped it, and erased
    their shadows in the views where they did.)
    """
    s = ConeBeamSettings.preset("cbct-ci", **{**IDEAL, "n_views": 391})
    extras = SceneExtras(empty_holes=False)
    mu_ref = cbct.physics.water_correction(cbct._spectrum(s)).mu_ref_per_mm
    for pose, z_mm in ((POSE_0, 0.0), (POSE_35, 35.0)):
        targets = _targets(phantom, pose, z_mm)
        assert np.all(np.abs(targets[:, 2] - z_mm) < 1.3)
        centres = frames.apply(_rtk_from_image(s), targets)
        cube_rtk = frames.apply(_rtk_from_image(s), pose[:3, 3][None])[0]
        vols, vox = _roi_mu(phantom, pose, s, extras, centres)
        for c, mu in zip(centres, vols, strict=True):
            found = c - 27 / 2.0 * vox + _centroid(mu)[::-1] * vox
            assert np.linalg.norm(found - c) < CENTROID_TOL_MM, (z_mm, found - c)
            stored = np.clip((mu / mu_ref - 1.0) * 1000.0, HU_MIN, HU_MAX) - 1500.0
            clipped = c - 27 / 2.0 * vox + _centroid(stored, 0.0)[::-1] * vox
            outward = (c - cube_rtk) * np.array([1.0, 0.0, 1.0])
            assert (clipped - c) @ outward / np.linalg.norm(outward) < -0.005  # towards the plastic


def test_volume_frame_and_truth(phantom) -> None:  # type: ignore[no-untyped-def]
    """The HU volume's voxel → image mapping and the truth agree (cbct-ci grid, twin subtracted)."""
    s = ConeBeamSettings.preset(
        "cbct-ci", **{**IDEAL, "det_cols": 256, "det_rows": 192, "det_pitch_mm": 1.552}
    )
    s = dataclasses.replace(s, subrays=2)
    twin = SceneExtras(empty_holes=False, sphere_material="plastic")
    hu, scan = simulate_cbct_mu(phantom, POSE_0, s, dataclasses.replace(twin, sphere_material=None))
    hu0, _ = simulate_cbct_mu(phantom, POSE_0, s, twin)
    diff = hu - hu0
    assert len(scan.sphere_indices) >= 4
    ijk = np.linalg.solve(
        scan.image_from_voxel, np.c_[scan.spheres_image_mm, np.ones(len(scan.spheres_image_mm))].T
    )
    for centre, (i, j, k, _) in zip(scan.spheres_image_mm, ijk.T, strict=True):
        lo = np.rint([k, j, i]).astype(int) - 3
        patch = diff[lo[0] : lo[0] + 7, lo[1] : lo[1] + 7, lo[2] : lo[2] + 7]
        found = frames.apply(scan.image_from_voxel, (lo + _centroid(patch))[::-1][None])[0]
        assert (
            np.linalg.norm(found - centre) < 0.5
        )  # 1.6 mm slices sample a 2.5 mm ball coarsely; a frame error is mm


def test_rod_and_vertebra_in_the_cone_beam_scene(phantom) -> None:  # type: ignore[no-untyped-def]
    """The steel rod (leaving the cube's +z face) and the bone block (cortical shell, cancellous
    core, 72 mm off in y) reconstruct with their materials' HU; scatter off so PMMA reads true."""
    s = ConeBeamSettings.preset(
        "cbct-ci",
        n_views=40,
        noise=False,
        scatter_spr=0.0,
        rows=32,
        columns=12,
        n_slices=18,
        pixel_mm=3.2,
        slice_spacing_mm=4.0,
        roi_centre_mm=(0.0, 40.0, 25.0),
    )
    hu, scan = simulate_cbct_mu(phantom, np.eye(4), s, SceneExtras(rod=True, vertebra=True))
    inv = np.linalg.inv(scan.image_from_voxel)

    def at(x: float, y: float, z: float) -> float:
        i, j, k, _ = np.rint(inv @ np.array([x, y, z, 1.0])).astype(int)
        return float(hu[k, j, i])

    assert at(0.0, 0.0, 56.0) > 5000.0  # steel rod axis, 16 mm above the cube
    assert 100.0 < at(0.0, 72.0, 0.0) < 400.0  # cancellous core (20 % cortical bone in water)
    assert 60.0 < at(0.0, 20.0, 0.0) < 200.0  # PMMA
    assert at(12.0, 85.0, 25.0) < -800.0  # air beyond the vertebra
    without, _ = simulate_cbct_mu(phantom, np.eye(4), s, SceneExtras())
    i, j, k, _ = np.rint(inv @ np.array([0.0, 0.0, 56.0, 1.0])).astype(int)
    assert without[k, j, i] < -800.0  # no rod, air


def test_only_the_fov_cylinder_is_reconstructed(phantom) -> None:  # type: ignore[no-untyped-def]
    """Voxels beyond the radius every view sees are air; the cube inside is plastic."""
    s = ConeBeamSettings.preset(
        "cbct-ci", n_views=16, det_cols=64, det_rows=48, det_pitch_mm=6.2, noise=False, scatter_spr=0.0
    )
    s = dataclasses.replace(s, rows=16, columns=16, n_slices=4, pixel_mm=16.0, slice_spacing_mm=8.0)
    r_fov = cbct.fov_radius_rtk_mm(s)
    assert 100.0 < r_fov < 120.0  # 64 · 6.2 mm panel at SDD 1150, SID 650
    hu, _ = simulate_cbct_mu(phantom, np.eye(4), s, SceneExtras(empty_holes=False))
    xy = (np.arange(16) - 7.5) * 16.0
    outside = np.hypot(*np.meshgrid(xy, xy)) > r_fov
    assert np.all(hu[:, outside] == HU_MIN) and np.count_nonzero(outside) >= 8
    assert -300.0 < hu[2, 7, 7] < 400.0  # PMMA at the centre (coarse voxels, 16 views)


def _step_off(model: cbct.LagModel, n_on: int = 300, n_off: int = 300) -> np.ndarray:
    """Detector reading of a pixel exposed (1.0) for ``n_on`` frames, then dark."""
    x = np.zeros((n_on + n_off, 1), np.float32)
    x[:n_on] = 1.0
    return cbct.apply_lag(x, model)[:, 0]


def test_detector_lag_is_a_charge_conserving_multi_exponential() -> None:
    """First-frame lag Σ w_n (3.6 %), 50th-frame lag of tenths of a per cent (a-Si panels), and
    the impulse response sums to 1 (trapped charge is released, none is lost)."""
    y = _step_off(cbct.DETECTOR_LAG)
    assert y[300] == pytest.approx(sum(w for w, _ in cbct.DETECTOR_LAG), rel=0.05)
    assert 0.0005 < y[349] < 0.005
    impulse = np.zeros((2000, 1), np.float32)
    impulse[0] = 1.0
    assert float(cbct.apply_lag(impulse, cbct.DETECTOR_LAG).sum()) == pytest.approx(1.0, abs=1e-4)


def test_lag_correction_inverts_its_own_model_and_leaves_a_residual_of_the_true_lag() -> None:
    """Hsieh's recursive deconvolution is exact for its model; the scanner's calibrated model is
    not the panel's, so a residual remains, an order of magnitude below the uncorrected lag."""
    rng = np.random.default_rng(3)
    frames_in = rng.uniform(0.1, 1.0, (200, 4, 5)).astype(np.float32)
    lagged = cbct.apply_lag(frames_in.copy(), cbct.DETECTOR_LAG)
    exact = cbct.correct_lag(lagged.copy(), cbct.DETECTOR_LAG)
    np.testing.assert_allclose(exact, frames_in, atol=2e-5)
    y = _step_off(cbct.DETECTOR_LAG)
    y_fix = cbct.correct_lag(y[:, None].copy(), cbct.SCANNER_LAG_MODEL)[:, 0]
    assert 1e-4 < abs(float(y_fix[300])) < 0.1 * float(y[300])


def test_slab_filter_averages_rows_over_the_projected_slice_thickness() -> None:
    """0.833 mm at the isocentre is 1.90 panel rows (0.776 mm, magnification 1.77): a unit row
    spreads to [0.45, 1, 0.45] / 1.90 and the sum is kept; thickness 0 leaves the views alone."""
    s = ConeBeamSettings.preset("oarm-cbct", slice_thickness_mm=0.833)
    views = np.zeros((2, 21, 3), np.float32)
    views[:, 10] = 1.0
    out = cbct.slab_filter_rows(views.copy(), s)[0, :, 0]
    width = 0.833 * s.magnification / s.det_pitch_mm
    np.testing.assert_allclose(
        out[9:12], np.array([0.5 * (width - 1.0), 1.0, 0.5 * (width - 1.0)]) / width, rtol=1e-5
    )
    assert float(out.sum()) == pytest.approx(1.0, abs=1e-6)
    point = dataclasses.replace(s, slice_thickness_mm=0.0)
    np.testing.assert_array_equal(cbct.slab_filter_rows(views.copy(), point), views)


SHADOW_CENTRE_TOL_MM = 0.025
"""Largest per-view error (mm on the panel) of an opaque ball's shadow centre, with the hard
sweep's tungsten-carbide sub-ray count, against 32 × 32 rays per pixel.  Measured on 20 random
sub-pixel positions: 2 / 3 / 4 / 8 rays per axis err 0.077 / 0.025 / 0.016 / 0.006 mm."""


def test_the_wc_sweep_resolves_the_pixel_aperture_of_an_opaque_ball() -> None:
    """A tungsten-carbide ball transmits ~0 through its middle, so an edge pixel's transmission is
    its area fraction outside the shadow; too few sub-rays quantise it, a view-dependent shift of
    the shadow that FDK turns into a centre error (benchmarks/bench_detection.py ``WC_SUBRAYS``)."""
    from benchmarks.bench_detection import WC_SUBRAYS
    from mocks.oarm import physics

    s = ConeBeamSettings.preset("oarm-cbct", det_cols=64, det_rows=48, monochromatic_kev=MONO_KEV)
    spectrum = cbct._spectrum(s)
    mu = physics.attenuation_matrix_per_mm(spectrum, sphere="tungsten_carbide")
    slot = physics.SCENE_MATERIALS.index("sphere")
    u_mm = np.arange(s.det_cols) * s.det_pitch_mm

    def shadow_centre_mm(scene: Any, subrays: int) -> float:
        t = cbct.project_view(
            dataclasses.replace(s, subrays=subrays),
            scene,
            0.3,
            mu,
            spectrum.weights,
            len(physics.SCENE_MATERIALS),
        )
        w = (1.0 - t).sum(axis=0)
        return float((w * u_mm).sum() / w.sum())

    rng = np.random.default_rng(1)
    errs = []
    for c in rng.uniform(-0.2, 0.2, (20, 3)):
        scene = cbct._Scene([], [], [cbct._Ball(c, 1.25, ((slot, 1.0),))])
        errs.append(abs(shadow_centre_mm(scene, WC_SUBRAYS) - shadow_centre_mm(scene, 32)))
    assert max(errs) <= SHADOW_CENTRE_TOL_MM, max(errs)


O_ARM_PSF_FWHM_MM = (0.65, 0.80)
"""The O-arm's measured PSF FWHM with and without view-dependent geometric calibration (Uneri et
al., Med Phys 45:4857 (2018), research note image-side.md §2); the simulated scanner's geometry
is exact, so its PSF should sit at the calibrated end."""

PSF_MEASUREMENT_TOL_MM = 0.02
"""A 0.2 mm ball's image on a 0.05 mm grid, its FWHM per axis and position measured to about this
(the spread over subrays 4 / 8 and the ball's own width)."""


def _fwhm_mm(profile: np.ndarray, step_mm: float) -> float:
    p = profile - np.median([profile[0], profile[-1]])
    half = p.max() / 2.0
    idx = np.flatnonzero(p >= half)
    i0, i1 = idx[0], idx[-1]
    left = i0 - 1 + (half - p[i0 - 1]) / (p[i0] - p[i0 - 1])
    right = i1 + (p[i1] - half) / (p[i1] - p[i1 + 1])
    return float((right - left) * step_mm)


def test_the_cone_beam_psf_is_the_o_arms() -> None:
    """The full detection chain (light spread, log, FDK) of the O-arm presets, noise-free: a
    0.2 mm titanium ball at the isocentre and 32–38 mm off it is imaged with an in-plane FWHM
    within the O-arm's published range (before: 0.61 mm with a 0.6 mm light spread)."""
    from mocks.oarm import physics

    s = ConeBeamSettings.preset(
        "oarm-cbct-roi",
        noise=False,
        scatter_spr=0.0,
        lag_components=(),
        lag_correction_model=(),
        monochromatic_kev=MONO_KEV,
        subrays=8,
    )
    spectrum = cbct._spectrum(s)
    mu = physics.attenuation_matrix_per_mm(spectrum, "pmma", "titanium")
    slot = physics.SCENE_MATERIALS.index("sphere")
    wcorr = physics.water_correction(spectrum)
    n, step = 41, 0.05
    inplane = []
    for centre in ([0.3, 0.1, 0.2], [30.0, 5.0, -12.0], [-20.0, -10.0, 25.0], [10.0, 20.0, 35.0]):
        c = np.asarray(centre)
        scene = cbct._Scene([], [], [cbct._Ball(c, 0.1, ((slot, 1.0),))])
        views = np.stack(
            [
                cbct.project_view(s, scene, math.radians(i * 360.0 / s.n_views), mu, spectrum.weights, 6)
                for i in range(s.n_views)
            ]
        )
        line_integrals = cbct._detect_views(views, s, wcorr)
        vol = cbct.fdk_numpy(line_integrals, s, c - (n - 1) / 2.0 * step, (n, n, n), (step, step, step))
        k = np.unravel_index(np.argmax(vol), vol.shape)
        inplane += [_fwhm_mm(vol[:, k[1], k[2]], step), _fwhm_mm(vol[k[0], k[1], :], step)]  # RTK z, x
    mean = float(np.mean(inplane))
    lo, hi = O_ARM_PSF_FWHM_MM
    assert lo - PSF_MEASUREMENT_TOL_MM <= mean <= hi, (mean, inplane)
