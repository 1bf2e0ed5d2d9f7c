"""Header pass and pixel pass of :mod:`registration.dicom` on real files: where Pixel Data starts, what
a truncated compressed file gives, and the pydicom decoder path for compressed transfer syntaxes."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from pydicom.uid import JPEG2000Lossless, RLELossless

from registration.dicom import SliceHeader, load_series
from registration.dicom.headers import read_headers
from registration.dicom.pixels import decode_frame
from tests.helpers.dicom_factory import ramp_volume, write_series

N = 4


def _one_header(path: Path) -> SliceHeader:
    result = read_headers(path)
    assert isinstance(result, list), result
    (h,) = result
    return h


def test_pixel_offset_points_at_the_native_pixel_values(tmp_path: Path) -> None:
    vol = ramp_volume(N)
    paths = write_series(tmp_path, vol)
    h = _one_header(paths[2])
    data = paths[2].read_bytes()
    assert data[h.pixel_offset : h.pixel_offset + vol[2].nbytes] == vol[2].astype("<i2").tobytes()
    assert h.pixel_vr == "OW"
    np.testing.assert_array_equal(decode_frame(h), vol[2])


def test_truncated_compressed_file_is_skipped(tmp_path: Path) -> None:
    paths = write_series(tmp_path, ramp_volume(N + 1) - 500, compress_with=RLELossless)
    last = paths[-1]
    last.write_bytes(last.read_bytes()[:-20])  # the Sequence Delimitation Item and some data are gone
    skipped = read_headers(last)
    assert not isinstance(skipped, list)
    assert skipped.reason == "no PixelData (7FE0,0010): not an image, or truncated"
    v = load_series(tmp_path)
    assert v.shape[0] == N and "truncated" in dict(v.meta["skipped"])[str(last)]


def test_jpeg2000_lossless_series_decodes_through_pylibjpeg(tmp_path: Path) -> None:
    pytest.importorskip("openjpeg")  # pylibjpeg-openjpeg: encoder and decoder
    vol = ramp_volume(N, 64, 64) - 500  # openjpeg's default 6 resolutions need more than 16 x 16
    write_series(tmp_path / "raw", vol, intercept=-24.0)
    write_series(tmp_path / "j2k", vol, intercept=-24.0, compress_with=JPEG2000Lossless)
    raw, j2k = load_series(tmp_path / "raw"), load_series(tmp_path / "j2k")
    assert j2k.meta["transfer_syntax_uids"] == (JPEG2000Lossless,)
    np.testing.assert_array_equal(j2k.voxels, raw.voxels)
    np.testing.assert_array_equal(j2k.voxels, vol - 24)
