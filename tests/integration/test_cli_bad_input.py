"""Every bad input of issue 34 (items 3, 4) is one line on stderr and a documented exit code, and
nothing is created where the user did not ask (``main`` in-process, real files)."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from service.cli.main import build_parser, join_negative_lists, main
from service.error_map import EXIT_CONFIG, EXIT_FILES, EXIT_INPUT, EXIT_USAGE


def _one_line_error(capsys: pytest.CaptureFixture[str]) -> str:
    err = capsys.readouterr().err
    assert "Traceback" not in err
    lines = [ln for ln in err.splitlines() if ln.strip()]
    assert len(lines) == 1, err
    return lines[0]


def test_joints_file_with_a_string_is_input_error(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    joints = tmp_path / "J.json"
    joints.write_text(json.dumps({"joints_rad": [0, 0, 1.57, 0, 0.78, "x"]}))
    pts = tmp_path / "img.json"
    pts.write_text(json.dumps({"spheres_mm": [[0, 0, 0]] * 4}))
    code = main(["register", "--image-points", str(pts), "--joints", str(joints)])
    assert code == EXIT_INPUT
    assert "joints_rad" in _one_line_error(capsys)


def test_simulate_out_an_existing_file_is_refused_at_parse_time(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    f = tmp_path / "scan"
    f.write_text("not a folder")
    with pytest.raises(SystemExit) as e:
        main(["simulate", "--out", str(f)])
    assert e.value.code == EXIT_USAGE
    assert "not a folder" in _one_line_error(capsys)


def test_simulate_refuses_a_non_empty_folder(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    (tmp_path / "CT_001_0001.dcm").write_bytes(b"old slice")
    assert main(["simulate", "--out", str(tmp_path), "--preset", "small"]) == EXIT_USAGE
    assert "--replace" in _one_line_error(capsys)
    assert (tmp_path / "CT_001_0001.dcm").read_bytes() == b"old slice"
    # --replace deletes only what simulate writes: a foreign file is refused, nothing deleted
    (tmp_path / "notes.txt").write_text("mine")
    assert main(["simulate", "--out", str(tmp_path), "--preset", "small", "--replace"]) == EXIT_USAGE
    assert "notes.txt" in _one_line_error(capsys)
    assert (tmp_path / "CT_001_0001.dcm").exists()


def test_replace_clears_an_earlier_series(tmp_path: Path) -> None:
    from service.cli.commands.simulate import clear_output_folder

    for name in ("CT_001_0001.dcm", "CT_001_0002.dcm", "truth.json"):
        (tmp_path / name).write_text("old")
    clear_output_folder(tmp_path, replace=True)
    assert list(tmp_path.iterdir()) == []


def test_unwritable_output_is_a_file_system_error(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """/proc refuses new entries even to root: the write fails, one line, exit 8 (or 2 at parse)."""
    code: object
    try:
        code = main(["backup", "/proc/oarmreg-backup", "--data", str(tmp_path / "data")])
    except SystemExit as e:
        code = e.code
    assert code in (EXIT_FILES, EXIT_USAGE)
    assert "/proc/oarmreg-backup" in _one_line_error(capsys)


def test_restore_of_a_missing_backup_creates_nothing(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    missing = tmp_path / "nonexistent"
    assert main(["restore", str(missing), "--data", str(tmp_path / "data")]) == EXIT_CONFIG
    assert "no such backup" in _one_line_error(capsys)
    assert not missing.exists()


def test_json_into_a_missing_folder_creates_no_folder(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out = tmp_path / "nonexistent" / "dir" / "x.json"
    with pytest.raises(SystemExit) as e:
        main(["detect", str(tmp_path), "--json", str(out)])
    assert e.value.code == EXIT_USAGE
    assert "does not exist" in _one_line_error(capsys)
    assert not (tmp_path / "nonexistent").exists()


def test_sro_without_a_data_folder_writes_nothing_in_the_working_folder(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    monkeypatch.chdir(tmp_path)
    argv = ["register", "--image-points", "i.json", "--robot-points", "r.json", "--sro", "reg.dcm"]
    assert main(argv) == EXIT_USAGE
    assert "--robot-frame-uid" in _one_line_error(capsys)
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize("flag", ["--pose", "--pose="])
def test_comma_separated_flags_take_a_leading_negative_number(flag: str) -> None:
    value = "-12.3,4,-5e1,0,-90,0"
    argv = (
        ["simulate", "--out", "x", flag + value]
        if flag.endswith("=")
        else ["simulate", "--out", "x", flag, value]
    )
    args = build_parser(only="simulate").parse_args(join_negative_lists(argv))
    assert args.pose == value


def test_a_lone_negative_number_and_options_are_left_alone() -> None:
    argv = ["register", "--max-fre-mm", "-1", "-v", "--json", "-x,1"]
    assert join_negative_lists(argv) == argv


@pytest.mark.parametrize(
    "argv",
    [
        ["register", "--image-points", "{pts}", "--joints", "{missing}"],
        ["calibrate", "run", "{missing}", "--out", "{tmp}/cal"],
        ["calibrate", "plan", "--registration", "{missing}", "--json", "{tmp}/plan.json"],
        ["verify", "{tmp}", "--registration", "{missing}", "--robot-points", "{pts}"],
    ],
    ids=["joints", "poses", "plan-registration", "verify-registration"],
)
def test_a_missing_input_file_is_a_file_system_error(
    argv: list[str], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """Issue 42, item 4: exit 8 as docs/cli.md says, not 4 "Invalid points file"."""
    pts = tmp_path / "img.json"
    pts.write_text(json.dumps({"spheres_mm": [[0, 0, 0], [10, 0, 0], [0, 10, 0], [0, 0, 10]]}))
    missing = tmp_path / "nope.json"
    filled = [a.format(pts=pts, missing=missing, tmp=tmp_path) for a in argv]
    assert main(filled) == EXIT_FILES
    line = _one_line_error(capsys)
    assert str(missing) in line and "no such file" in line and "Invalid points file" not in line


def test_a_joints_deg_key_names_the_accepted_key(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    joints = tmp_path / "J.json"
    joints.write_text(json.dumps({"joints_deg": [0, 0, 90, 0, 45, 0]}))
    pts = tmp_path / "img.json"
    pts.write_text(json.dumps({"spheres_mm": [[0, 0, 0]] * 4}))
    assert main(["register", "--image-points", str(pts), "--joints", str(joints)]) == EXIT_INPUT
    line = _one_line_error(capsys)
    assert "joints_deg" in line and 'accepted key is "joints_rad"' in line and "None" not in line


def test_simulate_of_a_pose_that_images_no_sphere_fails(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """Issue 40 item 6: the mock robot's own default pose at placement or1 images no sphere; on main
    ``simulate`` exited 0 with 'spheres fully imaged: 0 of 28' and wrote the empty series."""
    out = tmp_path / "scan"
    argv = ["simulate", "--joints", "0,0,1.5707963,0,0.7853982,0", "--placement", "or1", "--out", str(out),
            "--preset", "small"]  # fmt: skip
    assert main(argv) == EXIT_INPUT
    err = capsys.readouterr().err
    assert "Traceback" not in err
    assert "simulating" not in err, err  # refused before the simulation's cost, not after it
    line = err.strip()
    assert (
        line.startswith("oarmreg simulate: ")
        and "none of the phantom's 28 spheres" in line
        and "field" in line
    )
    assert not any(out.glob("*.dcm"))


def test_detect_that_finds_no_sphere_fails(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """Issue 40 item 6: a scan with no metal sphere (plastic ones) detects none; on main ``detect``
    printed '0 sphere(s)' and exited 0."""
    out = tmp_path / "scan"
    assert main(["simulate", "--out", str(out), "--preset", "small", "--metal-free"]) == 0
    capsys.readouterr()
    assert main(["detect", str(out)]) == EXIT_INPUT
    err = capsys.readouterr().err
    assert "no sphere found" in err and "phantom" in err and "Traceback" not in err
