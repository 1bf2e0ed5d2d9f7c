"""Every CLI output file flag refuses, at parse time, a path that is already a folder (or another
non-regular file): exit 2 naming the flag, before any scan is read and with the folder untouched.
It used to run the whole command and end in an IsADirectoryError traceback."""

from __future__ import annotations

from pathlib import Path

import pytest

from service.cli.main import main


@pytest.mark.parametrize(
    "argv",
    [
        ["detect", "SCAN", "--json", "DIR"],
        ["detect", "SCAN", "--overlay", "DIR"],
        ["register", "SCAN", "--robot-points", "P.json", "--json", "DIR"],
        ["verify", "SCAN", "--registration", "R.json", "--robot-points", "P.json", "--histogram", "DIR"],
        ["calibrate", "plan", "--registration", "R.json", "--json", "DIR"],
        ["robot", "points", "--link", "simple-message://127.0.0.1:1", "--out", "DIR"],
    ],
    ids=lambda a: f"{a[0]} {a[-2]}",
)
def test_a_folder_as_output_file_is_refused_naming_the_flag(
    argv: list[str], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out = tmp_path / "out"
    out.mkdir()
    (out / "keep.txt").write_text("x")
    args = [str(out) if a == "DIR" else str(tmp_path / a) if a[0].isupper() else a for a in argv]
    with pytest.raises(SystemExit) as exit_info:
        main(args)
    assert exit_info.value.code == 2
    err = capsys.readouterr().err
    assert f"argument {argv[-2]}: {out} exists and is not a regular file" in err, err
    assert [p.name for p in out.iterdir()] == ["keep.txt"]
