"""Series loading (issue #3 item 1): one test per refusal rule on real malformed folders, plus known answers.

Every folder is written with pydicom by ``dicom_factory`` (16 x 16 slices), broken
in exactly one way, and read back through the public API.
"""

from __future__ import annotations

import logging
import os
from pathlib import Path

import numpy as np
import pytest
from pydicom.uid import RLELossless, SecondaryCaptureImageStorage, generate_uid

from registration.dicom import (
    AmbiguousSeriesError,
    DuplicatePositionError,
    GantryTiltError,
    InconsistentImageSizeError,
    MissingGeometryError,
    MissingSliceError,
    MixedFrameOfReferenceError,
    MixedOrientationError,
    NoCtSeriesError,
    SeriesNotFoundError,
    SingleSliceError,
    UnevenSpacingError,
    list_series,
    load_series,
    read_series_headers,
)
from registration.errors import DicomSeriesError
from service.error_map import EXIT_INPUT, exit_code_of
from tests.helpers.dicom_factory import ct_dataset, ramp_volume, write_series

N = 6  # slices per test series
SPACING = 0.8  # mm, the factory's default slice step


def _z_positions(zs: list[float]) -> list[tuple[float, float, float]]:
    return [(-10.0, -20.0, z) for z in zs]


def _good(folder: Path, **kwargs: object) -> list[Path]:
    return write_series(folder, ramp_volume(N), **kwargs)  # type: ignore[arg-type]


# --------------------------------------------------------------------------- known answers


def test_loads_voxels_and_affine_known_answer(tmp_path: Path) -> None:
    vol = ramp_volume(N)
    write_series(tmp_path, vol, origin_mm=(-10.0, -20.0, 30.0), pixel_spacing_mm=(0.6, 0.4))
    v = load_series(tmp_path)
    assert v.voxels.dtype == np.int16
    np.testing.assert_array_equal(v.voxels, vol)
    # i along the row cosine x PixelSpacing[1] (0.4), j along the column cosine x PixelSpacing[0] (0.6),
    # k = IPP step (0.8 along z), origin = first IPP; SliceThickness (written as 99) is ignored.
    expected = np.array(
        [[0.4, 0.0, 0.0, -10.0], [0.0, 0.6, 0.0, -20.0], [0.0, 0.0, 0.8, 30.0], [0.0, 0.0, 0.0, 1.0]]
    )
    np.testing.assert_allclose(v.image_from_voxel, expected, atol=1e-9)
    assert v.meta["slice_spacing_mm"] == pytest.approx(0.8)
    assert v.frame_of_reference_uid and v.series_uid


def test_reversed_file_and_instance_order_gives_same_volume(tmp_path: Path) -> None:
    vol = ramp_volume(N)
    write_series(tmp_path / "fwd", vol)
    write_series(tmp_path / "rev", vol, file_order=list(range(N))[::-1])  # InstanceNumber against z
    a, b = load_series(tmp_path / "fwd"), load_series(tmp_path / "rev")
    np.testing.assert_array_equal(a.voxels, b.voxels)
    np.testing.assert_allclose(a.image_from_voxel, b.image_from_voxel, atol=1e-12)
    assert b.meta["instance_numbers"] == tuple(range(N, 0, -1))


def test_flipped_orientation_maps_bright_voxel_to_known_lps(tmp_path: Path) -> None:
    # IOP (-1,0,0, 0,-1,0): i runs towards -x (right), j towards -y (anterior), normal +z.
    stored = np.zeros((N, 16, 16), dtype=np.int16)
    stored[2, 5, 3] = 3000  # slice 2, row 5, column 3
    write_series(
        tmp_path,
        stored,
        origin_mm=(10.0, 20.0, 30.0),
        orientation=(-1.0, 0.0, 0.0, 0.0, -1.0, 0.0),
        pixel_spacing_mm=(0.5, 0.25),
        file_order=[3, 0, 5, 1, 4, 2],
    )
    v = load_series(tmp_path)
    k, j, i = np.unravel_index(int(np.argmax(v.voxels)), v.voxels.shape)
    lps = v.voxel_to_image(np.array([[i, j, k]], dtype=np.float64))[0]
    # by hand: x = 10 - 3 * 0.25, y = 20 - 5 * 0.5, z = 30 + 2 * 0.8
    np.testing.assert_allclose(lps, [9.25, 17.5, 31.6], atol=1e-9)
    assert np.linalg.det(v.image_from_voxel[:3, :3]) > 0


def test_unsigned_pixels_with_intercept_give_hu(tmp_path: Path) -> None:
    hu = ramp_volume(N) - 1024
    stored = (hu + 1024).astype(np.uint16)
    write_series(tmp_path, stored, intercept=-1024.0)
    v = load_series(tmp_path)
    assert v.voxels.dtype == np.int16
    np.testing.assert_array_equal(v.voxels, hu)
    assert v.voxels[0, 0, 0] == -1024


def test_unsigned_12_bit_ignores_high_bits(tmp_path: Path) -> None:
    stored = (ramp_volume(N) % 4096).astype(np.uint16)
    noisy = stored | np.uint16(0xF000)  # garbage above BitsStored must not reach the HU
    write_series(tmp_path, noisy, intercept=-1024.0, bits_stored=12)
    v = load_series(tmp_path)
    np.testing.assert_array_equal(v.voxels, stored.astype(np.int32) - 1024)


def test_fractional_slope_gives_float32(tmp_path: Path) -> None:
    stored = ramp_volume(N).astype(np.uint16)
    write_series(tmp_path, stored, slope=0.5, intercept=-1024.0)
    v = load_series(tmp_path)
    assert v.voxels.dtype == np.float32
    np.testing.assert_allclose(v.voxels, stored * 0.5 - 1024.0)


def test_hu_outside_int16_falls_back_to_float32(tmp_path: Path) -> None:
    stored = ramp_volume(N)
    stored[3, 0, 0] = -32000  # -32000 - 1024 does not fit int16
    write_series(tmp_path, stored, intercept=-1024.0)
    v = load_series(tmp_path)
    assert v.voxels.dtype == np.float32
    np.testing.assert_array_equal(v.voxels, stored.astype(np.float32) - 1024.0)


def test_rle_compressed_series_decodes_to_same_values(tmp_path: Path) -> None:
    vol = ramp_volume(N) - 500
    write_series(tmp_path / "raw", vol)
    write_series(tmp_path / "rle", vol, compress_with=RLELossless)
    raw, rle = load_series(tmp_path / "raw"), load_series(tmp_path / "rle")
    assert rle.meta["transfer_syntax_uids"] == (RLELossless,)
    np.testing.assert_array_equal(rle.voxels, raw.voxels)
    np.testing.assert_allclose(rle.image_from_voxel, raw.image_from_voxel)


def test_dicomdir_file_set_is_read(tmp_path: Path) -> None:
    from pydicom import dcmread
    from pydicom.fileset import FileSet

    vol = ramp_volume(N)
    paths = write_series(tmp_path / "src", vol, file_order=[2, 5, 0, 4, 1, 3])
    fs = FileSet()
    for p in paths:
        fs.add(dcmread(p))
    fs.write(tmp_path / "media")
    by_file = load_series(tmp_path / "media" / "DICOMDIR")
    by_folder = load_series(tmp_path / "media")
    np.testing.assert_array_equal(by_file.voxels, vol)
    np.testing.assert_array_equal(by_folder.voxels, vol)
    assert all("DICOMDIR" not in f for f in by_file.meta["files"])


# --------------------------------------------------------------------------- files that are skipped


def test_truncated_file_is_skipped_and_rest_loads(tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    paths = _good(tmp_path)
    last = paths[-1]
    data = last.read_bytes()
    last.write_bytes(data[: len(data) - 100])  # export interrupted: end of PixelData missing
    with caplog.at_level(logging.INFO, logger="registration.dicom"):
        v = load_series(tmp_path)
    assert v.shape[0] == N - 1
    skipped = dict(v.meta["skipped"])
    assert "truncated" in skipped[str(last)]
    assert any(str(last) in r.getMessage() and "truncated" in r.getMessage() for r in caplog.records)


def test_truncated_file_inside_stack_is_a_missing_slice(tmp_path: Path) -> None:
    paths = _good(tmp_path)
    middle = paths[2]
    middle.write_bytes(middle.read_bytes()[:-10])
    with pytest.raises(MissingSliceError) as err:
        load_series(tmp_path)
    assert str(paths[1]) in str(err.value) and str(paths[3]) in str(err.value)
    # the refusal also names the file that caused the gap, and why it was not used
    assert f"{middle}: truncated" in str(err.value) and middle in err.value.files


def test_localizer_is_skipped(tmp_path: Path) -> None:
    series_uid = generate_uid()
    _good(tmp_path, series_uid=series_uid)
    scout = ct_dataset(
        np.zeros((16, 16), np.int16),
        position_mm=(0.0, 0.0, 0.0),
        orientation=(0.0, 1.0, 0.0, 0.0, 0.0, -1.0),  # sagittal: would be "mixed orientation" if kept
        series_uid=series_uid,
        frame_of_reference_uid=generate_uid(),
        study_uid=generate_uid(),
        image_type=("ORIGINAL", "PRIMARY", "LOCALIZER"),
    )
    scout.save_as(tmp_path / "scout.dcm", enforce_file_format=True)
    v = load_series(tmp_path)
    assert v.shape[0] == N
    assert "localizer" in dict(v.meta["skipped"])[str(tmp_path / "scout.dcm")]


def test_non_dicom_files_and_secondary_capture_are_skipped(tmp_path: Path) -> None:
    _good(tmp_path / "series")
    (tmp_path / "README.txt").write_text("exported by the O-arm\n")
    (tmp_path / "series" / "junk.bin").write_bytes(os.urandom(2000))
    sc = ct_dataset(
        np.zeros((16, 16), np.int16),
        position_mm=(0.0, 0.0, 0.0),
        series_uid=generate_uid(),
        frame_of_reference_uid=generate_uid(),
        study_uid=generate_uid(),
        sop_class_uid=SecondaryCaptureImageStorage,
    )
    sc.save_as(tmp_path / "screenshot.dcm", enforce_file_format=True)
    v = load_series(tmp_path)
    skipped = dict(v.meta["skipped"])
    assert v.shape[0] == N
    assert "not a DICOM" in skipped[str(tmp_path / "README.txt")]
    assert "not a DICOM" in skipped[str(tmp_path / "series" / "junk.bin")]
    assert "Secondary Capture" in skipped[str(tmp_path / "screenshot.dcm")]


def test_part_file_is_skipped(tmp_path: Path) -> None:
    paths = write_series(tmp_path, ramp_volume(N + 1))
    partial = paths[-1].with_name(f".{paths[-1].name}.part")  # the next slice, still being written
    os.replace(paths[-1], partial)
    scan = read_series_headers(tmp_path)
    reasons = [s.reason for s in scan.skipped if s.path == partial]
    assert reasons == ["temporary file still being written (*.part)"]
    v = load_series(tmp_path)
    assert v.shape[0] == N


def test_only_junk_is_refused_naming_the_files(tmp_path: Path) -> None:
    (tmp_path / "notes.txt").write_text("hello")
    (tmp_path / ".IM0001.dcm.part").write_bytes(b"\0" * 300)
    with pytest.raises(NoCtSeriesError) as err:
        load_series(tmp_path)
    msg = str(err.value)
    assert "no CT image series" in msg
    assert "notes.txt" in msg and "not a DICOM" in msg and ".IM0001.dcm.part" in msg
    assert "O-arm export" in msg  # what to do
    assert exit_code_of(err.value) == EXIT_INPUT and isinstance(err.value, DicomSeriesError)


def test_missing_path_is_refused(tmp_path: Path) -> None:
    with pytest.raises(NoCtSeriesError, match="no such file or folder"):
        load_series(tmp_path / "nope")


# --------------------------------------------------------------------------- refusals, one per rule


def test_mixed_orientation_is_refused(tmp_path: Path) -> None:
    paths = _good(tmp_path, overrides={3: {"orientation": (1.0, 0.0, 0.0, 0.0, 0.0, -1.0)}})
    with pytest.raises(MixedOrientationError) as err:
        load_series(tmp_path)
    msg = str(err.value)
    assert "ImageOrientationPatient" in msg and str(paths[3]) in msg and "re-export" in msg
    assert err.value.files == (paths[3],)


def test_uneven_spacing_is_refused(tmp_path: Path) -> None:
    zs = [0.0, 0.8, 1.6, 2.5, 3.3, 4.1]  # one step of 0.9 mm
    paths = _good(tmp_path, positions_mm=_z_positions(zs))
    with pytest.raises(UnevenSpacingError) as err:
        load_series(tmp_path)
    msg = str(err.value)
    assert not isinstance(err.value, MissingSliceError)
    assert "uneven slice spacing" in msg and "0.9000 mm" in msg
    assert str(paths[2]) in msg and str(paths[3]) in msg and "re-export" in msg


def test_drift_off_the_uniform_grid_is_refused(tmp_path: Path) -> None:
    # every step within 0.01 mm of the 0.8 mm median, but the middle slice ends up 0.024 mm off the grid
    steps = [0.808, 0.808, 0.808, 0.792, 0.792, 0.792]
    zs = np.concatenate([[0.0], np.cumsum(steps)]).tolist()
    paths = write_series(tmp_path, ramp_volume(7), positions_mm=_z_positions(zs))
    with pytest.raises(UnevenSpacingError) as err:
        load_series(tmp_path)
    assert "0.0240 mm off the uniform grid" in str(err.value) and str(paths[3]) in str(err.value)


def test_gantry_tilt_is_refused(tmp_path: Path) -> None:
    tilt = np.tan(np.radians(5.0))
    positions = [(-10.0, -20.0 + k * SPACING * tilt, k * SPACING) for k in range(N)]
    _good(tmp_path, positions_mm=positions)
    with pytest.raises(GantryTiltError) as err:
        load_series(tmp_path)
    msg = str(err.value)
    assert "gantry tilt of about 5.00°" in msg and "sideways" in msg and "IM0000.dcm" in msg


def test_missing_slice_is_refused(tmp_path: Path) -> None:
    zs = [0.0, 0.8, 1.6, 3.2, 4.0, 4.8]  # the slice at 2.4 mm is missing
    paths = _good(tmp_path, positions_mm=_z_positions(zs))
    with pytest.raises(MissingSliceError) as err:
        load_series(tmp_path)
    msg = str(err.value)
    assert "1 missing between" in msg and str(paths[2]) in msg and str(paths[3]) in msg
    assert "incomplete" in msg


def test_duplicate_position_is_refused(tmp_path: Path) -> None:
    zs = [0.0, 0.8, 1.6, 1.6, 2.4, 3.2]
    paths = _good(tmp_path, positions_mm=_z_positions(zs))
    with pytest.raises(DuplicatePositionError) as err:
        load_series(tmp_path)
    msg = str(err.value)
    assert "share a position" in msg and str(paths[2]) in msg and str(paths[3]) in msg
    assert set(err.value.files) == {paths[2], paths[3]}


def test_inconsistent_rows_columns_is_refused(tmp_path: Path) -> None:
    paths = _good(tmp_path, overrides={4: {"stored": np.zeros((16, 20), np.int16)}})
    with pytest.raises(InconsistentImageSizeError) as err:
        load_series(tmp_path)
    msg = str(err.value)
    assert "Rows x Columns" in msg and "(16, 20): 1 file(s)" in msg and str(paths[4]) in msg


def test_inconsistent_pixel_spacing_is_refused(tmp_path: Path) -> None:
    paths = _good(tmp_path, overrides={1: {"pixel_spacing_mm": (0.5, 0.52)}})
    with pytest.raises(InconsistentImageSizeError) as err:
        load_series(tmp_path)
    assert "PixelSpacing" in str(err.value) and str(paths[1]) in str(err.value)


def test_mixed_frame_of_reference_is_refused(tmp_path: Path) -> None:
    paths = _good(tmp_path, overrides={0: {"frame_of_reference_uid": "1.2.3.4"}})
    with pytest.raises(MixedFrameOfReferenceError) as err:
        load_series(tmp_path)
    msg = str(err.value)
    assert "FrameOfReferenceUID" in msg and "1.2.3.4" in msg and str(paths[0]) in msg
    assert "coordinate system" in msg


def test_single_slice_is_refused(tmp_path: Path) -> None:
    paths = write_series(tmp_path, ramp_volume(1))
    with pytest.raises(SingleSliceError) as err:
        load_series(tmp_path)
    assert str(paths[0]) in str(err.value) and "at least 2" in str(err.value)


def test_missing_position_is_refused(tmp_path: Path) -> None:
    from pydicom import dcmread

    paths = _good(tmp_path)
    ds = dcmread(paths[2])
    del ds.ImagePositionPatient
    ds.save_as(paths[2], enforce_file_format=True)
    with pytest.raises(MissingGeometryError) as err:
        load_series(tmp_path)
    assert "ImagePositionPatient" in str(err.value) and str(paths[2]) in str(err.value)


# --------------------------------------------------------------------------- series selection


def _two_series(tmp_path: Path) -> tuple[str, str]:
    small, large = generate_uid(), generate_uid()
    write_series(tmp_path / "a", ramp_volume(4), series_uid=small)
    write_series(tmp_path / "b", ramp_volume(7), series_uid=large, origin_mm=(0.0, 0.0, 100.0))
    return small, large


def test_largest_series_is_picked_and_uid_selects(tmp_path: Path) -> None:
    small, large = _two_series(tmp_path)
    assert load_series(tmp_path).series_uid == large
    v = load_series(tmp_path, series_uid=small)
    assert v.series_uid == small and v.shape[0] == 4


def test_unknown_series_uid_is_refused_listing_available(tmp_path: Path) -> None:
    small, large = _two_series(tmp_path)
    with pytest.raises(SeriesNotFoundError) as err:
        load_series(tmp_path, series_uid="1.2.3.999")
    msg = str(err.value)
    assert "1.2.3.999" in msg and small in msg and large in msg and "Pass one of these UIDs" in msg


def test_largest_consistent_series_wins_over_a_larger_broken_one(tmp_path: Path) -> None:
    good_uid, bad_uid = generate_uid(), generate_uid()
    write_series(tmp_path / "good", ramp_volume(4), series_uid=good_uid)
    zs = [0.0, 0.8, 1.6, 3.2, 4.0, 4.8, 5.6]
    write_series(tmp_path / "bad", ramp_volume(7), series_uid=bad_uid, positions_mm=_z_positions(zs))
    assert load_series(tmp_path).series_uid == good_uid
    with pytest.raises(MissingSliceError):
        load_series(tmp_path, series_uid=bad_uid)


def test_tie_between_series_is_refused(tmp_path: Path) -> None:
    a, b = generate_uid(), generate_uid()
    write_series(tmp_path / "a", ramp_volume(5), series_uid=a)
    write_series(tmp_path / "b", ramp_volume(5), series_uid=b)
    with pytest.raises(AmbiguousSeriesError) as err:
        load_series(tmp_path)
    assert a in str(err.value) and b in str(err.value) and "pass the series UID" in str(err.value)


def test_list_series_is_header_only_and_reports_problems(tmp_path: Path) -> None:
    good_uid, bad_uid = generate_uid(), generate_uid()
    write_series(tmp_path / "good", ramp_volume(5), series_uid=good_uid)
    zs = [0.0, 0.8, 1.6, 2.5, 3.3]
    write_series(tmp_path / "bad", ramp_volume(5), series_uid=bad_uid, positions_mm=_z_positions(zs))
    (tmp_path / "x.txt").write_text("x")
    summaries = {s.series_uid: s for s in list_series(tmp_path)}
    good, bad = summaries[good_uid], summaries[bad_uid]
    assert good.consistent and good.n_files == 5 and (good.rows, good.columns) == (16, 16)
    assert good.slice_spacing_mm == pytest.approx(0.8) and good.is_axial
    assert good.first_position_mm == pytest.approx((-10.0, -20.0, 30.0))
    assert not bad.consistent and bad.problem_type == "UnevenSpacingError" and "uneven" in bad.problem
    assert [s.path.name for s in read_series_headers(tmp_path).skipped] == ["x.txt"]


# --------------------------------------------------------------------------- Enhanced CT (multi-frame)


def test_enhanced_ct_multiframe_matches_single_frame(tmp_path: Path) -> None:
    from pydicom.dataset import Dataset, FileMetaDataset
    from pydicom.uid import EnhancedCTImageStorage, ExplicitVRLittleEndian

    vol = ramp_volume(N)
    write_series(tmp_path / "single", vol)
    order = [3, 1, 5, 0, 2, 4]  # frames stored out of geometric order

    def item(**values: object) -> Dataset:
        d = Dataset()
        for k, v in values.items():
            setattr(d, k, v)
        return d

    ds = Dataset()
    ds.file_meta = FileMetaDataset()
    ds.file_meta.MediaStorageSOPClassUID = EnhancedCTImageStorage
    ds.file_meta.MediaStorageSOPInstanceUID = generate_uid()
    ds.file_meta.TransferSyntaxUID = ExplicitVRLittleEndian
    ds.SOPClassUID = EnhancedCTImageStorage
    ds.SOPInstanceUID = ds.file_meta.MediaStorageSOPInstanceUID
    ds.Modality = "CT"
    ds.ImageType = ["ORIGINAL", "PRIMARY", "VOLUME", "NONE"]
    ds.StudyInstanceUID, ds.SeriesInstanceUID, ds.FrameOfReferenceUID = (generate_uid() for _ in range(3))
    ds.NumberOfFrames = N
    ds.Rows, ds.Columns = 16, 16
    ds.SamplesPerPixel, ds.PhotometricInterpretation = 1, "MONOCHROME2"
    ds.BitsAllocated, ds.BitsStored, ds.HighBit, ds.PixelRepresentation = 16, 16, 15, 1
    ds.SharedFunctionalGroupsSequence = [
        item(
            PlaneOrientationSequence=[item(ImageOrientationPatient=[1, 0, 0, 0, 1, 0])],
            PixelMeasuresSequence=[item(PixelSpacing=[0.5, 0.5], SliceThickness=99)],
            PixelValueTransformationSequence=[item(RescaleSlope=1, RescaleIntercept=0, RescaleType="HU")],
        )
    ]
    ds.PerFrameFunctionalGroupsSequence = [
        item(PlanePositionSequence=[item(ImagePositionPatient=[-10.0, -20.0, 30.0 + 0.8 * k])]) for k in order
    ]
    ds.PixelData = vol[order].tobytes()
    (tmp_path / "enhanced").mkdir()
    ds.save_as(tmp_path / "enhanced" / "ct.dcm", enforce_file_format=True)
    single, multi = load_series(tmp_path / "single"), load_series(tmp_path / "enhanced")
    np.testing.assert_array_equal(multi.voxels, single.voxels)
    np.testing.assert_allclose(multi.image_from_voxel, single.image_from_voxel, atol=1e-9)
    assert multi.meta["frames"] == tuple(order.index(k) for k in range(N))


# --------------------------------------------------------------------------- the simulator's export


@pytest.mark.parametrize(
    ("orientation", "reverse", "unsigned"),
    [
        ("axial", False, False),
        ("axial-flipped", True, True),
        ("oblique", True, False),
        ("axial-rot90", False, True),
    ],
)
def test_simulator_export_round_trips(
    tmp_path: Path, orientation: str, reverse: bool, unsigned: bool
) -> None:
    """The O-arm simulator's export reads back to its own voxels and geometry (truth maps to same voxels)."""
    from mocks.oarm import dicom_export as export
    from mocks.oarm import simulator as sim

    settings = sim.AcquisitionSettings(
        rows=16, columns=20, n_slices=7, pixel_mm=0.415, slice_spacing_mm=0.833, orientation=orientation
    )
    hu = (ramp_volume(7, 16, 20) % 4000 - 1024).astype(np.int16)
    image_from_voxel = settings.image_from_voxel()
    truth_ijk = np.array([[3.0, 5.0, 2.0], [17.25, 9.5, 5.75]])
    truth_mm = (image_from_voxel @ np.c_[truth_ijk, np.ones(2)].T).T[:, :3]
    scan = sim.SimulatedScan(
        hu=hu,
        image_from_voxel=image_from_voxel,
        image_from_phantom=np.eye(4),
        spheres_image_mm=truth_mm,
        sphere_indices=np.arange(2),
        settings=settings,
    )
    result = export.write_dicom_series(scan, tmp_path, reverse_order=reverse, unsigned=unsigned)
    v = load_series(tmp_path)
    assert v.series_uid == result.series_uid
    np.testing.assert_array_equal(v.voxels, hu)
    # The loader normalises the direction cosines (PS3.3 C.7.6.2.1.1: unit vectors).  The simulator's
    # "oblique" column cosine has norm 1.0000137, so its own affine differs by 1.4e-5 relative along j:
    # 1.3e-4 voxel at j = 9.5 here, 0.007 voxel (0.003 mm) at the edge of a 512 matrix.
    atol = 1e-3 if orientation == "oblique" else 1e-9
    np.testing.assert_allclose(v.image_from_voxel, image_from_voxel, atol=atol)
    np.testing.assert_allclose(v.image_to_voxel(truth_mm), truth_ijk, atol=atol)


# --------------------------------------------------------------------------- encoding variants


def _variant(path: Path, variant: str) -> None:
    """Rewrite one factory file as an encoding variant the header pass must read like the original."""
    from pydicom import dcmread
    from pydicom.dataset import Dataset
    from pydicom.sequence import Sequence
    from pydicom.uid import ImplicitVRLittleEndian

    ds = dcmread(path)
    if variant in ("sequences", "implicit-sequences"):
        inner = Dataset()
        inner.ReferencedSOPClassUID = "1.2.840.10008.5.1.4.1.1.2"
        inner.ReferencedSOPInstanceUID = generate_uid()
        inner.is_undefined_length_sequence_item = True
        outer = Dataset()
        outer.CodeValue = "X"
        outer.ReferencedImageSequence = Sequence([inner])
        outer["ReferencedImageSequence"].is_undefined_length = True
        outer.is_undefined_length_sequence_item = True
        ds.SourceImageSequence = Sequence([outer, Dataset()])
        ds["SourceImageSequence"].is_undefined_length = True
        ds.add_new(0x00091010, "LO", "private value")
    if variant in ("implicit", "implicit-sequences"):
        ds.file_meta.TransferSyntaxUID = ImplicitVRLittleEndian
    if variant == "long-header":
        ds.add_new(0x00091010, "LO", "private")
        ds.add_new(0x00091011, "OB", b"\0" * 70_000)  # a deferred value before PixelData
    ds.save_as(path, enforce_file_format=True)


@pytest.mark.parametrize(
    "variant", ["explicit", "implicit", "sequences", "implicit-sequences", "long-header"]
)
def test_encoding_variants_give_the_same_headers_and_voxels(tmp_path: Path, variant: str) -> None:
    vol = ramp_volume(N)
    write_series(tmp_path / "plain", vol, intercept=-7.0)
    paths = write_series(tmp_path / "variant", vol, intercept=-7.0)
    for p in paths:
        _variant(p, variant)
    (plain,), (varied,) = list_series(tmp_path / "plain"), list_series(tmp_path / "variant")
    assert varied.consistent, varied.problem
    same = "n_slices rows columns pixel_spacing_mm orientation slice_spacing_mm first_position_mm modality"
    for attr in same.split():
        assert getattr(varied, attr) == getattr(plain, attr), attr
    v = load_series(tmp_path / "variant")
    np.testing.assert_array_equal(v.voxels, vol - 7)
    assert v.meta["rescale"] == ((1.0, -7.0),)
    assert v.meta["files"] == tuple(str(p) for p in paths)
