"""Hypothesis-driven DICOM fuzzer against the loader (issue #13): every input ends in a typed refusal
(an :class:`~registration.errors.OarmRegError` subclass) or a volume; never a hang, a crash or an
untyped exception.

A valid 6-slice 8 x 8 series is written once; each example copies it and damages it: header fields
(Rows, Columns, BitsAllocated, BitsStored, PixelRepresentation, SamplesPerPixel, NumberOfFrames,
RescaleSlope / Intercept, ImagePositionPatient, ImageOrientationPatient, PixelSpacing, transfer
syntax, ImagesInAcquisition) set to hostile values on one or all slices, files truncated, random bytes
written at random offsets, files swapped for FIFOs, NUL-filled files, symlink loops.  Examples are
bounded (``max_examples``, derandomized: the same inputs every run) and each has a deadline.
"""

from __future__ import annotations

import contextlib
import os
import shutil
import warnings
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from registration.dicom import list_series, load_series
from registration.errors import OarmRegError
from tests.helpers.dicom_factory import ramp_volume, write_series

N_SLICES = 6

EXAMPLE_DEADLINE_MS = 5000
"""Per-example deadline: a decode of a 6 x 8 x 8 series takes milliseconds; a hang would blow this."""

INTS = st.one_of(
    st.sampled_from([0, 1, 2, 7, 8, 12, 15, 16, 17, 24, 32, 33, 64, 255, 65535]),
    st.integers(0, 65535),
)
DS = st.sampled_from(
    ["0", "-0", "1", "-1", "1e308", "-1e308", "nan", "NaN", "inf", "-inf", "", "abc", "1e-320", "3.5"]
)
TRANSFER_SYNTAXES = st.sampled_from(
    [
        "1.2.840.10008.1.2",  # implicit VR little endian
        "1.2.840.10008.1.2.1",
        "1.2.840.10008.1.2.2",  # explicit big endian (retired)
        "1.2.840.10008.1.2.5",  # RLE
        "1.2.840.10008.1.2.4.50",  # JPEG baseline
        "1.2.840.10008.1.2.4.90",  # JPEG 2000
        "1.2.840.10008.1.2.1.99",  # deflate
        "1.2.3.4.5.6",
        "",
    ]
)
FIELD_VALUES: dict[str, Any] = {
    "Rows": INTS,
    "Columns": INTS,
    "BitsAllocated": INTS,
    "BitsStored": INTS,
    "PixelRepresentation": st.sampled_from([0, 1, 2, 5, 65535]),
    "SamplesPerPixel": st.sampled_from([0, 1, 2, 3, 4]),
    "NumberOfFrames": st.sampled_from(["0", "1", "2", "100000", "-1", "x"]),
    "RescaleSlope": DS,
    "RescaleIntercept": DS,
    "ImagesInAcquisition": st.sampled_from(["0", "1", "5", "6", "7", "99999999", "-3", "x"]),
    "ImagePositionPatient": st.lists(DS, min_size=0, max_size=4),
    "ImageOrientationPatient": st.lists(DS, min_size=0, max_size=7),
    "PixelSpacing": st.lists(DS, min_size=0, max_size=3),
    "PhotometricInterpretation": st.sampled_from(["MONOCHROME1", "MONOCHROME2", "RGB", "PALETTE COLOR", ""]),
    "TransferSyntaxUID": TRANSFER_SYNTAXES,
}


@pytest.fixture(scope="module")
def valid_series(tmp_path_factory: pytest.TempPathFactory) -> Path:
    folder = tmp_path_factory.mktemp("fuzz-base") / "series"
    write_series(folder, ramp_volume(N_SLICES, 8, 8))
    return folder


@pytest.fixture(scope="module")
def scratch(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Path]:
    yield tmp_path_factory.mktemp("fuzz-scratch")


def _fresh(valid: Path, scratch: Path) -> Path:
    out = scratch / "case"
    if out.exists():
        shutil.rmtree(out)
    shutil.copytree(valid, out)
    return out


def _must_end_typed(folder: Path) -> None:
    """Load and list: a volume or an :class:`OarmRegError`, nothing else (any other exception fails)."""
    for call in (lambda: load_series(folder), lambda: list_series(folder)):
        try:
            result = call()
        except OarmRegError as e:
            assert str(e), "a refusal without a message"
            continue
        if hasattr(result, "voxels"):
            assert result.voxels.ndim == 3 and np.isfinite(result.image_from_voxel).all()


def _set_field(path: Path, keyword: str, value: Any) -> None:
    import pydicom

    ds = pydicom.dcmread(path)
    if keyword == "TransferSyntaxUID":
        ds.file_meta.TransferSyntaxUID = value
    else:
        setattr(ds, keyword, value)
    ds.save_as(path)


SETTINGS = settings(
    max_examples=70,
    deadline=EXAMPLE_DEADLINE_MS,
    suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow],
    derandomize=True,  # the same inputs every run: no order or luck dependence
    database=None,
)


@SETTINGS
@given(
    data=st.data(),
    fields=st.lists(st.sampled_from(sorted(FIELD_VALUES)), min_size=1, max_size=3, unique=True),
    all_slices=st.booleans(),
)
def test_damaged_header_fields_end_in_a_refusal_or_a_volume(
    valid_series: Path, scratch: Path, data: st.DataObject, fields: list[str], all_slices: bool
) -> None:
    folder = _fresh(valid_series, scratch)
    files = sorted(folder.iterdir())
    targets = files if all_slices else [files[data.draw(st.integers(0, len(files) - 1))]]
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # pydicom warns about the invalid values written on purpose
        for keyword in fields:
            value = data.draw(FIELD_VALUES[keyword], label=keyword)
            for p in targets:
                # pydicom may refuse to write a value; the file then keeps its old one
                with contextlib.suppress(ValueError, TypeError, OverflowError, AttributeError):
                    _set_field(p, keyword, value)
        _must_end_typed(folder)


@SETTINGS
@given(
    data=st.data(),
    n_edits=st.integers(1, 4),
    truncate=st.booleans(),
)
def test_random_bytes_and_truncations_end_in_a_refusal_or_a_volume(
    valid_series: Path, scratch: Path, data: st.DataObject, n_edits: int, truncate: bool
) -> None:
    folder = _fresh(valid_series, scratch)
    files = sorted(folder.iterdir())
    for _ in range(n_edits):
        p = files[data.draw(st.integers(0, len(files) - 1))]
        raw = bytearray(p.read_bytes())
        if not raw:
            continue
        at = data.draw(st.integers(0, len(raw) - 1))
        if truncate:
            raw = raw[:at]
        else:
            junk = data.draw(st.binary(min_size=1, max_size=16))
            raw[at : at + len(junk)] = junk
        p.write_bytes(bytes(raw))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        _must_end_typed(folder)


@SETTINGS
@given(
    kind=st.sampled_from(["fifo", "nul", "empty", "loop", "dangling", "outside", "dir-named-dcm"]),
    which=st.integers(0, N_SLICES - 1),
)
def test_hostile_files_are_never_opened_and_end_typed(
    valid_series: Path, scratch: Path, kind: str, which: int
) -> None:
    folder = _fresh(valid_series, scratch)
    p = sorted(folder.iterdir())[which]
    p.unlink()
    if kind == "fifo":
        os.mkfifo(p)  # opening it for reading would block forever (no writer): the deadline catches that
    elif kind == "nul":
        p.write_bytes(b"\0" * 4096)
    elif kind == "empty":
        p.write_bytes(b"")
    elif kind == "loop":
        os.symlink(p.name, p)
    elif kind == "dangling":
        os.symlink(folder / "nowhere", p)
    elif kind == "outside":
        os.symlink("/dev/zero", p)  # endless bytes: never read
    else:
        p.mkdir()
    _must_end_typed(folder)
    (summary,) = list_series(folder)  # the other five slices are still found, the hostile one skipped
    assert summary.n_files == N_SLICES - 1
