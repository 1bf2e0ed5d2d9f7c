"""The O-arm simulator end to end: DICOM export, geometry round trip and metal-artefact physics.

Issue #2 "Done when": tests that would fail for a toy simulator (bright balls on noise).  All scans
use the ``small`` preset; the scene is the default phantom rotated 30° about the scanner axis so a
row of adjacent filled holes (+x-r1c1, +x-r1c2, +x-r1c3, 15 mm apart) lies in one slice.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np
import pydicom
import pytest
from scipy import ndimage

from mocks.oarm.dicom_export import CT_IMAGE_STORAGE, write_dicom_series
from mocks.oarm.simulator import (
    HU_MAX,
    AcquisitionSettings,
    SceneExtras,
    SimulatedScan,
    scan_to_volume,
    simulate_scan,
)
from registration.errors import ConfigError
from registration.model import frames

POSE = frames.transform_from_xyz_rpy([0.0, 0.0, 0.0], [0.0, 0.0, 30.0])
ROW = ("+x-r1c1", "+x-r1c2", "+x-r1c3")
GEOMETRY_TOL_MM = 1e-6
"""Issue #2: the tag geometry must reproduce the simulator's to 1e-6 mm."""


def _scan(phantom: Any, **kw: Any) -> SimulatedScan:
    extras = SceneExtras(sphere_material=kw.pop("sphere_material", "steel"))
    pose = kw.pop("pose", POSE)
    return simulate_scan(phantom, pose, AcquisitionSettings.preset("small", **kw), extras)


@pytest.fixture(scope="module")
def steel(phantom: Any) -> SimulatedScan:
    return _scan(phantom, seed=1)


@pytest.fixture(scope="module")
def metal_free(phantom: Any) -> SimulatedScan:
    return _scan(phantom, seed=1, sphere_material="plastic")


@pytest.fixture(scope="module")
def series(steel: SimulatedScan, tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Any]:
    out = tmp_path_factory.mktemp("series")
    res = write_dicom_series(steel, out)
    return out, res


def _read_series(folder: Path) -> tuple[np.ndarray, np.ndarray, list[pydicom.Dataset]]:
    """Read a folder with plain pydicom; return (HU volume sorted along the normal, affine, datasets)."""
    dss = [pydicom.dcmread(p) for p in sorted(folder.glob("*.dcm"))]
    iop = np.array(dss[0].ImageOrientationPatient, dtype=float)
    normal = np.cross(iop[:3], iop[3:])
    dss.sort(key=lambda d: float(np.dot(np.array(d.ImagePositionPatient, dtype=float), normal)))
    ipp = np.array([d.ImagePositionPatient for d in dss], dtype=float)
    row_mm, col_mm = (float(v) for v in dss[0].PixelSpacing)
    a = np.eye(4)
    a[:3, 0] = iop[:3] * col_mm  # along a row: column index i, spacing = PixelSpacing[1]
    a[:3, 1] = iop[3:] * row_mm
    a[:3, 2] = (ipp[-1] - ipp[0]) / (len(dss) - 1)
    a[:3, 3] = ipp[0]
    vol = np.stack([d.pixel_array * float(d.RescaleSlope) + float(d.RescaleIntercept) for d in dss])
    return vol, a, dss


def _centroid_voxel(vol: np.ndarray, ijk: np.ndarray, floor_hu: float = 1500.0) -> np.ndarray:
    """HU-weighted centroid (above ``floor_hu``) in a window around voxel ``ijk`` → (i, j, k)."""
    i, j, k = np.rint(ijk).astype(int)
    sl = (slice(k - 3, k + 4), slice(j - 4, j + 5), slice(i - 4, i + 5))
    w = np.clip(vol[sl].astype(float) - floor_hu, 0.0, None)
    kk, jj, ii = np.mgrid[sl]
    return np.array([(w * ii).sum(), (w * jj).sum(), (w * kk).sum()]) / w.sum()


def _row_spheres(scan: SimulatedScan, phantom: Any) -> np.ndarray:
    """Voxel (i, j, k) of the three adjacent row spheres."""
    ids = list(phantom.filled_ids)
    pos = {int(h): n for n, h in enumerate(scan.sphere_indices)}
    rows = [pos[ids.index(h)] for h in ROW]
    return frames.apply(np.linalg.inv(scan.image_from_voxel), scan.spheres_image_mm[rows])


def _segment_hu(scan: SimulatedScan, a: np.ndarray, b: np.ndarray, margin_mm: float = 2.0) -> np.ndarray:
    """HU sampled (linear) along the segment a → b (voxel coords), skipping ``margin_mm`` at each end."""
    ts = np.linspace(0.0, 1.0, 200)
    length_mm = float(np.linalg.norm((b - a)[:2])) * scan.settings.pixel_mm
    keep = (ts * length_mm > margin_mm) & ((1 - ts) * length_mm > margin_mm)
    pts = a[None] + ts[keep, None] * (b - a)[None]
    return ndimage.map_coordinates(scan.hu.astype(float), [pts[:, 2], pts[:, 1], pts[:, 0]], order=1)


# ---------------------------------------------------------------- DICOM read-back and geometry


def test_series_files_are_valid_ct_image_storage(series: tuple[Path, Any], steel: SimulatedScan) -> None:
    out, res = series
    files = sorted(out.glob("*.dcm"))
    assert len(files) == steel.hu.shape[0] == len(res.paths)
    assert not list(out.glob(".*.part")), "temporary files left behind"
    sop_uids = set()
    for p in files[:: max(1, len(files) // 8)]:
        ds = pydicom.dcmread(p)
        assert ds.file_meta.TransferSyntaxUID == pydicom.uid.ExplicitVRLittleEndian
        assert ds.SOPClassUID == CT_IMAGE_STORAGE and ds.Modality == "CT"
        for uid in (ds.SOPInstanceUID, ds.SeriesInstanceUID, ds.StudyInstanceUID, ds.FrameOfReferenceUID):
            assert pydicom.uid.UID(uid).is_valid
        assert ds.SeriesInstanceUID == res.series_uid
        assert ds.FrameOfReferenceUID == res.frame_of_reference_uid
        assert ds.BitsAllocated == 16 and ds.PixelRepresentation == 1
        assert float(ds.SliceThickness) == float(ds.SpacingBetweenSlices) == steel.settings.slice_spacing_mm
        assert ds.AcquisitionDate and ds.AcquisitionTime and ds.PatientID
        sop_uids.add(ds.SOPInstanceUID)
    assert len(sop_uids) == len(files[:: max(1, len(files) // 8)])
    truth = json.loads((out / "truth.json").read_text())
    assert truth["series_uid"] == res.series_uid
    assert np.allclose(truth["spheres_image_mm"], steel.spheres_image_mm)


def test_a_placement_frame_of_reference_is_written_once_into_every_file_and_the_truth(
    steel: SimulatedScan, tmp_path: Path
) -> None:
    """Scans of one O-arm placement share a FrameOfReferenceUID, written with the slices (not by
    reading and rewriting every file afterwards, which doubled the export time) and in truth.json."""
    uid = "1.2.826.0.1.3680043.8.498.4242"
    res = write_dicom_series(steel, tmp_path, frame_of_reference_uid=uid)
    assert res.frame_of_reference_uid == uid
    assert {pydicom.dcmread(p, stop_before_pixels=True).FrameOfReferenceUID for p in res.paths} == {uid}
    assert json.loads((tmp_path / "truth.json").read_text())["frame_of_reference_uid"] == uid


def test_geometry_round_trip_is_exact(series: tuple[Path, Any], steel: SimulatedScan) -> None:
    out, _ = series
    vol, a, _ = _read_series(out)
    assert np.array_equal(vol.astype(np.int16), steel.hu)
    via_tags = frames.apply(np.linalg.inv(a), steel.spheres_image_mm)
    via_sim = frames.apply(np.linalg.inv(steel.image_from_voxel), steel.spheres_image_mm)
    spacing = np.array([steel.settings.pixel_mm] * 2 + [steel.settings.slice_spacing_mm])
    assert np.max(np.abs(via_tags - via_sim) * spacing) < GEOMETRY_TOL_MM


def test_every_truth_sphere_is_where_the_intensity_peaks(
    series: tuple[Path, Any], steel: SimulatedScan
) -> None:
    out, _ = series
    vol, a, _ = _read_series(out)
    assert len(steel.spheres_image_mm) >= 20, "small preset should hold most of the phantom"
    ijk = frames.apply(np.linalg.inv(a), steel.spheres_image_mm)
    for p in ijk:
        i, j, k = np.rint(p).astype(int)
        assert vol[k, j, i] == HU_MAX  # the sphere core is saturated
        err = _centroid_voxel(vol, p) - p
        assert np.all(np.abs(err) < 0.6), f"centroid off by {err} voxels at {p}"


def test_scan_to_volume_matches_the_scan(steel: SimulatedScan) -> None:
    vol = scan_to_volume(steel)
    assert vol.voxels is steel.hu or np.array_equal(vol.voxels, steel.hu)
    assert np.allclose(vol.voxel_to_image(np.zeros((1, 3))), steel.image_from_voxel[:3, 3])


# ---------------------------------------------------------------- physics


def test_values_saturate_at_3071_with_a_plateau_inside_spheres(steel: SimulatedScan, phantom: Any) -> None:
    assert steel.hu.max() == HU_MAX
    for p in _row_spheres(steel, phantom):
        i, j, k = np.rint(p).astype(int)
        assert np.all(steel.hu[k, j - 1 : j + 2, i - 1 : i + 2] == HU_MAX)


def test_metal_free_twin_has_no_metal(metal_free: SimulatedScan) -> None:
    assert metal_free.hu.max() < 1000


def test_dark_band_between_adjacent_spheres(
    steel: SimulatedScan, metal_free: SimulatedScan, phantom: Any
) -> None:
    s1, s2, _ = _row_spheres(steel, phantom)
    band = _segment_hu(steel, s1, s2).mean()
    plastic = _segment_hu(metal_free, s1, s2).mean()
    assert 50.0 < plastic < 200.0, "PMMA should read ≈ +100 HU"
    # Beam hardening + non-linear partial volume: rays through both spheres are under-estimated.
    assert band < plastic - 300.0, f"band {band:.0f} HU vs plastic {plastic:.0f} HU"


def test_streaks_make_the_line_between_spheres_noisy(
    steel: SimulatedScan, metal_free: SimulatedScan, phantom: Any
) -> None:
    s1, _, s3 = _row_spheres(steel, phantom)
    var_metal = _segment_hu(steel, s1, s3).var()
    var_free = _segment_hu(metal_free, s1, s3).var()
    assert var_metal > 20.0 * var_free, f"variance {var_metal:.0f} vs metal-free {var_free:.0f} HU²"


def test_noise_falls_as_one_over_sqrt_dose(metal_free: SimulatedScan, phantom: Any) -> None:
    base = metal_free.settings.photons_per_ray
    high = _scan(phantom, seed=2, sphere_material="plastic", photons_per_ray=4.0 * base)

    def sd(scan: SimulatedScan) -> float:
        n_k, n_j, n_i = scan.hu.shape
        region = scan.hu[
            n_k // 2 - 8 : n_k // 2 + 8, n_j // 2 - 6 : n_j // 2 + 6, n_i // 2 - 6 : n_i // 2 + 6
        ]
        r = region.astype(float)
        return float((r - r.mean(axis=(1, 2), keepdims=True)).std())

    sd1, sd4 = sd(metal_free), sd(high)
    assert sd1 > 10.0, "the base dose should show visible noise"
    assert 0.4 < sd4 / sd1 < 0.62, f"SD {sd1:.1f} → {sd4:.1f} HU at 4× dose"


# ---------------------------------------------------------------- export options


def test_reverse_unsigned_12bit_export(steel: SimulatedScan, tmp_path: Path) -> None:
    res = write_dicom_series(steel, tmp_path, reverse_order=True, unsigned=True, bits_stored=12)
    vol, a, dss = _read_series(tmp_path)
    assert np.array_equal(vol.astype(np.int16), steel.hu)
    assert np.allclose(a, steel.image_from_voxel, atol=1e-9)
    inst = [int(d.InstanceNumber) for d in dss]  # in increasing-position order
    assert inst == list(range(len(dss), 0, -1))
    d0 = dss[0]
    assert d0.PixelRepresentation == 0 and d0.BitsStored == 12 and d0.HighBit == 11
    assert float(d0.RescaleIntercept) == -1024.0
    assert max(int(d.pixel_array.max()) for d in dss) == 4095
    assert res.paths[0].name.endswith("0001.dcm")  # instance 1 = the highest slice, written first
    assert np.isclose(
        float(pydicom.dcmread(res.paths[0]).ImagePositionPatient[2]), a[2, 3] + a[2, 2] * (len(dss) - 1)
    )


def test_signed_12_bit_is_refused(steel: SimulatedScan, tmp_path: Path) -> None:
    with pytest.raises(ConfigError, match="unsigned"):
        write_dicom_series(steel, tmp_path, bits_stored=12)


@pytest.mark.parametrize("orientation", ["axial-flipped", "oblique"])
def test_other_orientations_give_the_same_lps_centres(
    orientation: str, steel: SimulatedScan, phantom: Any, tmp_path: Path
) -> None:
    scan = _scan(phantom, seed=3, orientation=orientation, n_views=120)
    write_dicom_series(scan, tmp_path)
    vol, a, dss = _read_series(tmp_path)
    iop = np.array(dss[0].ImageOrientationPatient, dtype=float)
    assert not np.allclose(iop, [1, 0, 0, 0, 1, 0])
    # Same pose, same patient frame: truth centres agree with the axial scan's.
    common = np.intersect1d(scan.sphere_indices, steel.sphere_indices)
    assert len(common) >= 15
    ours = scan.spheres_image_mm[np.searchsorted(scan.sphere_indices, common)]
    axial = steel.spheres_image_mm[np.searchsorted(steel.sphere_indices, common)]
    assert np.allclose(ours, axial, atol=1e-9)
    # ... and the reconstructed metal is at those centres in this orientation's voxel grid.
    ijk = frames.apply(np.linalg.inv(a), scan.spheres_image_mm)
    for p in ijk:
        assert np.all(np.abs(_centroid_voxel(vol, p) - p) < 0.6)


def test_cli_writes_a_series_and_truth(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    from service.cli.main import main

    rc = main(
        [
            "simulate",
            "--out",
            str(tmp_path),
            "--preset",
            "small",
            "--views",
            "60",
            "--slices",
            "40",
            "--reverse-order",
            "--unsigned",
            "--png",
            str(tmp_path / "s.png"),
        ]
    )
    assert rc == 0
    out = capsys.readouterr().out
    assert "truth.json" in out and str(tmp_path.resolve()) in out
    truth = json.loads((tmp_path / "truth.json").read_text())
    assert truth["settings"]["n_slices"] == 40 and len(list(tmp_path.glob("*.dcm"))) == 40
    assert (tmp_path / "s_bone_window.png").stat().st_size > 1000
    assert (tmp_path / "s_soft_window.png").exists() and (tmp_path / "s_zoom_bone_window.png").exists()


# ------------------------------------------------------------ issue #11: partial imaging, tungsten carbide


def test_phantom_half_outside_the_slab_and_fov(phantom: Any, tmp_path: Path) -> None:
    """Shifted 40 mm along the axis and 28 mm sideways: >= 6 spheres fully imaged, the truth says which.

    Every fully imaged sphere is where the metal peaks; no partly imaged one is listed as a truth
    centre; truth.json flags the same spheres.
    """
    pose = frames.transform_from_xyz_rpy([28.0, 0.0, 40.0], [0.0, 0.0, 30.0])
    s = AcquisitionSettings.preset("small-realistic", n_views=120)
    scan = simulate_scan(phantom, pose, s, SceneExtras(hole_tolerance_mm=0.02))
    n_full = len(scan.sphere_indices)
    assert 6 <= n_full <= phantom.n_spheres // 2 and len(scan.partial_indices) >= 1
    assert not set(scan.sphere_indices) & set(scan.partial_indices)
    ijk = frames.apply(np.linalg.inv(scan.image_from_voxel), scan.spheres_image_mm)
    for p in ijk:
        assert np.all(np.abs(_centroid_voxel(scan.hu, p) - p) < 0.6)
    # Truth centres are the machined positions: within ±0.02 mm per axis of the drawing, not on it.
    d = scan.spheres_image_mm - scan.nominal_spheres_image_mm
    assert np.all(np.linalg.norm(d, axis=1) <= 0.02 * np.sqrt(3) + 1e-9) and np.abs(d).max() > 0.005
    res = write_dicom_series(scan, tmp_path)
    assert res.truth_path is not None
    truth = json.loads(res.truth_path.read_text())
    assert np.flatnonzero(truth["fully_imaged"]).tolist() == scan.sphere_indices.tolist()
    assert truth["sphere_material"] == "steel" and truth["sphere_diameter_mm"] == 2.5


def test_tungsten_carbide_neighbours_streak_harder_than_steel(phantom: Any) -> None:
    """With kernel scatter, WC starves the rays between neighbours: a darker band than steel (mean HU)."""
    s = AcquisitionSettings.preset("small-realistic", n_views=120, noise=False)
    depth = {}
    for material in ("steel", "tungsten_carbide"):
        scan = simulate_scan(phantom, POSE, s, SceneExtras(sphere_material=material))
        a, b, _ = _row_spheres(scan, phantom)
        depth[material] = float(np.mean(_segment_hu(scan, a, b)))
    assert depth["tungsten_carbide"] < depth["steel"] - 100.0, depth
