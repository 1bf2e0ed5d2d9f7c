"""Issue #21: series selection skips hidden folders, virtual environments and package trees, and a
command-line load of a folder with several loadable CT series refuses unless one is named.

Every series is written with pydicom by ``dicom_factory`` (8 x 8 slices)."""

from __future__ import annotations

from pathlib import Path

import pytest

from registration.dicom import load_series, read_series_headers
from registration.dicom.errors import AmbiguousSeriesError
from tests.helpers.dicom_factory import ramp_volume, write_series

UID_SCAN = "1.2.826.0.1.3680043.8.498.2101"
UID_OTHER = "1.2.826.0.1.3680043.8.498.2102"


def _series(folder: Path, uid: str, n: int) -> list[Path]:
    return write_series(folder, ramp_volume(n, 8, 8), series_uid=uid)


@pytest.mark.parametrize(
    "junk",
    [".venv/lib/python3.11/site-packages/pydicom/data", "venv/lib/pydicom", ".git/objects",
     "node_modules/x", "tools/site-packages/pkg", "__pycache__"],
)  # fmt: skip
def test_software_and_hidden_folders_are_not_searched(tmp_path: Path, junk: str) -> None:
    _series(tmp_path / "scan", UID_SCAN, 6)
    (tmp_path / "venv").mkdir()
    (tmp_path / "venv" / "pyvenv.cfg").write_text("home = /usr/bin\n")
    _series(tmp_path / junk, UID_OTHER, 9)  # larger: picked if it were searched
    found = {s.series_uid for s in read_series_headers(tmp_path).series}
    assert found == {UID_SCAN}
    vol = load_series(tmp_path, unique=True)
    assert vol.series_uid == UID_SCAN and vol.voxels.shape[0] == 6


def test_a_hidden_folder_named_as_the_root_is_searched(tmp_path: Path) -> None:
    _series(tmp_path / ".export", UID_SCAN, 5)
    assert load_series(tmp_path / ".export").series_uid == UID_SCAN


def test_several_loadable_series_refused_on_the_command_line_unless_named(tmp_path: Path) -> None:
    _series(tmp_path / "a", UID_SCAN, 6)
    _series(tmp_path / "b", UID_OTHER, 7)
    assert load_series(tmp_path).series_uid == UID_OTHER  # the library default: the largest stack
    with pytest.raises(AmbiguousSeriesError) as e:
        load_series(tmp_path, unique=True)
    assert UID_SCAN in str(e.value) and UID_OTHER in str(e.value) and "--series-uid" in str(e.value)
    assert load_series(tmp_path, series_uid=UID_SCAN, unique=True).voxels.shape[0] == 6


def test_cli_detect_refuses_a_folder_of_two_scans_with_exit_4(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    from service.cli.main import main

    _series(tmp_path / "a", UID_SCAN, 6)
    _series(tmp_path / "b", UID_OTHER, 7)
    assert main(["detect", str(tmp_path)]) == 4
    err = capsys.readouterr().err
    assert "Ambiguous DICOM series" in err and UID_SCAN in err and UID_OTHER in err
