"""Decode-on-arrival (service.intake.series_accumulator): the assembled volume is the loader's, whatever the
arrival order, worker count, growth or replacements; a slice the loader refuses is refused the same.

Small real series from ``dicom_factory`` (16 x 16 slices); the reference is
:func:`registration.dicom.load_series` on the same folder.
"""

from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import numpy as np
import pydicom
import pytest

import service.intake.series_accumulator as acc_mod
from registration.dicom import InconsistentImageSizeError, load_series
from registration.imaging.volume import Volume
from service.intake.recording import scan_instances_from_files
from service.intake.series_accumulator import SeriesAccumulator
from tests.helpers.dicom_factory import ramp_volume, write_series


def _assembled(folder: Path, arrival: list[Path], *, workers: int = 1) -> Volume:
    with ThreadPoolExecutor(workers) as ex:
        acc = SeriesAccumulator(folder, ex)
        for p in arrival:
            acc.add(p, "stored")
        return acc.assemble(str(pydicom.dcmread(arrival[0]).SeriesInstanceUID))


def _assert_loader_equal(vol: Volume, folder: Path) -> None:
    ref = load_series(folder, series_uid=vol.series_uid)
    assert vol.meta.get("decoded_on_arrival")  # not the fallback: the accumulator's own assembly
    np.testing.assert_array_equal(vol.voxels, ref.voxels)
    assert vol.voxels.dtype == ref.voxels.dtype
    np.testing.assert_array_equal(vol.image_from_voxel, ref.image_from_voxel)
    assert vol.meta["files"] == ref.meta["files"]
    assert vol.frame_of_reference_uid == ref.frame_of_reference_uid


def test_in_order_arrival_is_the_loaders_volume_read_only(tmp_path: Path) -> None:
    paths = write_series(tmp_path / "s", ramp_volume(7))
    vol = _assembled(tmp_path / "s", paths)
    _assert_loader_equal(vol, tmp_path / "s")
    assert not vol.voxels.flags.writeable  # a view of rows written once: nobody may change them
    want = [(str(d.SOPInstanceUID), str(d.SOPClassUID)) for d in map(pydicom.dcmread, paths)]
    assert list(vol.meta["sop_uids"]) == want


@pytest.mark.parametrize("workers", [1, 2])
def test_reverse_and_shuffled_arrival_give_the_loaders_volume(tmp_path: Path, workers: int) -> None:
    paths = write_series(tmp_path / "s", ramp_volume(9))
    rng = np.random.default_rng(3)
    for name, arrival in (("rev", paths[::-1]), ("shuffled", [paths[i] for i in rng.permutation(9)])):
        vol = _assembled(tmp_path / "s", arrival, workers=workers)
        _assert_loader_equal(vol, tmp_path / "s")
        assert name and not vol.voxels.flags.writeable


def test_growth_past_the_initial_capacity(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(acc_mod, "INITIAL_CAPACITY_FRAMES", 2)
    paths = write_series(tmp_path / "s", ramp_volume(11))
    _assert_loader_equal(_assembled(tmp_path / "s", paths, workers=2), tmp_path / "s")


def test_float_rescale_on_one_slice_makes_the_volume_float_as_the_loader_does(tmp_path: Path) -> None:
    paths = write_series(tmp_path / "s", ramp_volume(6), overrides={4: {"RescaleSlope": "0.5"}})
    vol = _assembled(tmp_path / "s", paths)
    assert vol.voxels.dtype == np.float32
    _assert_loader_equal(vol, tmp_path / "s")


def test_a_replaced_instance_serves_its_new_pixels(tmp_path: Path) -> None:
    stored = ramp_volume(6)
    paths = write_series(tmp_path / "s", stored)
    with ThreadPoolExecutor(1) as ex:
        acc = SeriesAccumulator(tmp_path / "s", ex)
        for p in paths:
            acc.add(p, "stored")
        ds = pydicom.dcmread(paths[2])
        ds.PixelData = (stored[2] + 7).astype(np.int16).tobytes()
        ds.save_as(paths[2], enforce_file_format=True)  # the SCP replaced it (same SOP Instance UID)
        acc.add(paths[2], "replaced")
        vol = acc.assemble(str(ds.SeriesInstanceUID))
    _assert_loader_equal(vol, tmp_path / "s")
    np.testing.assert_array_equal(vol.voxels[2], stored[2] + 7)


def test_a_slice_of_another_size_is_the_loaders_refusal(tmp_path: Path) -> None:
    small = np.zeros((8, 8), dtype=np.int16)
    paths = write_series(tmp_path / "s", ramp_volume(6), overrides={3: {"stored": small}})
    with pytest.raises(InconsistentImageSizeError):
        load_series(tmp_path / "s")
    with pytest.raises(InconsistentImageSizeError):
        _assembled(tmp_path / "s", paths)


def test_instance_uids_from_the_header_pass_equal_reading_every_file(tmp_path: Path) -> None:
    paths = write_series(tmp_path / "s", ramp_volume(5), file_order=[4, 2, 0, 1, 3])
    vol = _assembled(tmp_path / "s", paths)
    files = [Path(f) for f in vol.meta["files"]]
    fast = scan_instances_from_files(vol.series_uid, files, sop_uids=vol.meta["sop_uids"])
    assert fast == scan_instances_from_files(vol.series_uid, files)
