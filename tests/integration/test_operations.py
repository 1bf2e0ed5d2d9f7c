"""Issue #21, what a hospital needs to run the service: ``oarmreg config check``, the start-up line,
log level and JSON logs, ``-v`` after the subcommand, ports in use in one line each, storescu's
refused standard contexts at DEBUG, the systemd unit.

Real parts: the CLI's ``main``, the app under uvicorn on loopback, sockets that really hold the
ports, pynetdicom as the storage SCU, ``systemd-analyze verify`` when the tool exists.
"""

from __future__ import annotations

import json
import logging
import shutil
import socket
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path

import pytest

from tests.faults.conftest import fault_settings, mock_robot, serve
from tests.helpers.tokens import make_token

REPO = Path(__file__).resolve().parents[2]
SHIPPED = REPO / "configs" / "oarmreg.toml"
UNIT = REPO / "deploy" / "oarmreg.service"
TOKEN = make_token()


def _cli(argv: list[str], capsys: pytest.CaptureFixture[str]) -> tuple[int, str, str]:
    from service.cli.main import main

    rc = main(argv)
    out = capsys.readouterr()
    return rc, out.out, out.err


@pytest.fixture
def clean_env(monkeypatch: pytest.MonkeyPatch) -> pytest.MonkeyPatch:
    import os

    for k in list(os.environ):
        if k.upper().startswith("OARMREG_"):
            monkeypatch.delenv(k)
    return monkeypatch


@pytest.fixture
def root_logging() -> Iterator[None]:
    """``main`` configures the root logger; put it back for the next test."""
    root = logging.getLogger()
    handlers, level = list(root.handlers), root.level
    yield
    root.handlers[:] = handlers
    root.setLevel(level)


# ---- config check ------------------------------------------------------------------------------


def test_config_check_passes_the_shipped_config_and_names_every_source(
    clean_env: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str], root_logging: None
) -> None:
    clean_env.setenv("OARMREG_QUALITY__MAX_FRE_MM", "0.4")
    clean_env.setenv("OARMREG_API_TOKEN", TOKEN)
    rc, out, _ = _cli(["config", "check", "--config", str(SHIPPED), "--json"], capsys)
    assert rc == 0
    doc = json.loads(out)
    rows = {r["key"]: r for r in doc["settings"]}
    assert rows["quality.max_fre_mm"] == {"key": "quality.max_fre_mm", "value": 0.4,
                                          "source": "env OARMREG_QUALITY__MAX_FRE_MM"}  # fmt: skip
    assert rows["port"]["source"] == f"file {SHIPPED}" and rows["port"]["value"] == 8750
    assert rows["log.level"]["value"] == "INFO"
    assert rows["api_token"]["value"] == f"<set, {len(TOKEN)} characters>"
    assert rows["api_token"]["source"] == "env OARMREG_API_TOKEN"
    assert TOKEN not in out
    assert doc["notes"] == []


def test_config_check_without_a_token_passes_with_a_note(
    clean_env: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str], root_logging: None
) -> None:
    rc, out, _ = _cli(["config", "check", "--config", str(SHIPPED)], capsys)
    assert rc == 0
    assert out.splitlines()[0].endswith(": valid")
    assert "note: api_token is not set" in out
    assert any(
        line.strip().startswith("stillness.window_s") and "(file " in line for line in out.splitlines()
    )


def test_config_check_exits_3_naming_a_misspelt_key(
    tmp_path: Path, clean_env: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str], root_logging: None
) -> None:
    bad = tmp_path / "oarmreg.toml"
    bad.write_text(SHIPPED.read_text().replace("allowed_origins = []", "alowed_origins = []"))
    rc, out, err = _cli(["config", "check", "--config", str(bad)], capsys)
    assert rc == 3 and out == ""
    assert "unknown setting 'api.alowed_origins'" in err and str(bad) in err


def test_config_check_exits_3_on_a_bad_robot_model(
    tmp_path: Path, clean_env: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str], root_logging: None
) -> None:
    clean_env.setenv("OARMREG_ROBOT__MODEL", str(tmp_path / "missing.urdf"))
    rc, _, err = _cli(["config", "check", "--config", str(SHIPPED)], capsys)
    assert rc == 3 and "robot.model" in err


NON_FINITE_CASES = [
    ("igtl.tool0_from_tcp", "translation_mm = [0.0, nan, 0.0]", "nan"),
    ("igtl.tool0_from_tcp", "rpy_deg = [inf, 0.0, 0.0]", "inf"),
    ("robot.tool0_from_phantom", "translation_mm = [0.0, 0.0, 1e300]", "1e+300"),
    ("robot.tool0_from_phantom", "rpy_deg = [0.0, -inf, 0.0]", "-inf"),
    ("quality", "max_fre_mm = nan", "nan"),
    ("retention", "max_disk_mb = 1e300", "1e+300"),
]


@pytest.mark.parametrize(("section", "line", "shown"), NON_FINITE_CASES)
def test_config_check_and_serve_exit_3_on_a_non_finite_or_absurd_setting(
    section: str, line: str, shown: str, tmp_path: Path, clean_env: pytest.MonkeyPatch,
    capsys: pytest.CaptureFixture[str], root_logging: None,
) -> None:  # fmt: skip
    """Issue 31 item 8: NaN, infinity or 1e300 in a transform or limit setting is refused by
    ``config check`` and at start-up (exit 3), the message naming the setting; before, they passed
    (NaN later cut every OpenIGTLink client off, 1e300 gave a 500 at /register)."""
    key = f"{section}.{line.split(' =')[0]}"
    _check_and_serve_exit_3(
        f"[{section}]\n{line}\n", (f"setting '{key}'", shown), tmp_path, clean_env, capsys
    )


def _check_and_serve_exit_3(
    toml: str, shown: tuple[str, ...], tmp_path: Path, clean_env: pytest.MonkeyPatch,
    capsys: pytest.CaptureFixture[str],
) -> None:  # fmt: skip
    """``config check`` and ``serve`` of a file holding ``toml`` exit 3, each error naming ``shown``."""
    bad = tmp_path / "oarmreg.toml"
    bad.write_text(toml)
    rc, out, err = _cli(["config", "check", "--config", str(bad)], capsys)
    assert rc == 3 and out == "", (out, err)
    assert all(x in err for x in shown), err
    clean_env.setenv("OARMREG_API_TOKEN", TOKEN)
    argv = ["serve", "--config", str(bad), "--watch", str(tmp_path / "w"), "--data", str(tmp_path / "d"),
            "--port", "0"]  # fmt: skip
    rc, _, err = _cli(argv, capsys)
    assert rc == 3 and all(x in err for x in shown), err


IMPLAUSIBLE_ROBOT_SIDE = [
    # issue 40 item 1: a rod typed in radians served a matrix 176-275 mm wrong under a "1.00 mm" headline
    ("robot.tool0_from_phantom", "rpy_deg = [3.14159, 0.0, 0.0]", "looks like radians"),
    ("robot.tool0_from_phantom", "rpy_deg = [1.5708, 0.0, -1.5708]", "looks like radians"),
    ("igtl.tool0_from_tcp", "rpy_deg = [0.0, 0.0, 0.7854]", "looks like radians"),
    ("robot.tool0_from_phantom", "translation_mm = [0.0, 0.0, 0.2]", "looks like metres"),
    ("robot.tool0_from_phantom", "translation_mm = [0.0, 0.0, 900.0]", "beyond the arm's own reach"),
]


@pytest.mark.parametrize(("section", "line", "shown"), IMPLAUSIBLE_ROBOT_SIDE)
def test_config_check_and_serve_exit_3_on_an_implausible_robot_side(
    section: str, line: str, shown: str, tmp_path: Path, clean_env: pytest.MonkeyPatch,
    capsys: pytest.CaptureFixture[str], root_logging: None,
) -> None:  # fmt: skip
    """Issue 40 item 1: radians in a degrees field, metres in a millimetre field and a rod beyond the
    arm's reach are refused by ``config check`` and ``serve`` (exit 3), naming the setting and the
    likely unit; on main they passed and the service served a matrix hundreds of mm wrong."""
    _check_and_serve_exit_3(f"[{section}]\n{line}\n", (section, shown), tmp_path, clean_env, capsys)


def test_config_check_passes_a_real_odd_mount(
    tmp_path: Path, clean_env: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str], root_logging: None
) -> None:
    """A tilted, offset rod in degrees and millimetres is not mistaken for a unit slip."""
    odd = tmp_path / "oarmreg.toml"
    odd.write_text(
        "[robot.tool0_from_phantom]\ntranslation_mm = [12.5, -3.0, 87.25]\nrpy_deg = [178.5, 1.2, 90.0]\n"
        "[igtl.tool0_from_tcp]\ntranslation_mm = [0.0, 0.0, 0.0]\nrpy_deg = [0.0, 0.0, 45.0]\n"
    )
    rc, out, err = _cli(["config", "check", "--config", str(odd)], capsys)
    assert rc == 0 and "valid" in out, err


# ---- logging options ---------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("argv", "level"),
    [
        (["serve"], logging.INFO),
        (["serve", "-v"], logging.DEBUG),
        (["-v", "serve"], logging.DEBUG),
        (["serve", "--log-level", "warning"], logging.WARNING),
        (["detect", "x"], logging.WARNING),
        (["detect", "x", "-v"], logging.INFO),
        (["-v", "detect", "x", "-v"], logging.DEBUG),
    ],
)
def test_verbosity_is_accepted_before_and_after_the_subcommand(argv: list[str], level: int) -> None:
    from service.cli.main import build_parser, log_level_of

    args = build_parser().parse_args(argv)
    default = logging.INFO if args.command == "serve" else logging.WARNING
    assert log_level_of(args, default)[0] == level


def test_the_verbosity_help_says_what_the_flags_do() -> None:
    """Issue 34, item 5: ``-v``'s help states each level, and those are the levels the flags give
    (the help once said "serve logs at info by default" while ``serve -v`` gave debug, unstated)."""
    import re

    from service.cli.main import build_parser, log_level_of

    parser = build_parser()
    action = next(a for a in parser._actions if "--verbose" in a.option_strings)
    text = " ".join((action.help or "").lower().split())
    stated = {
        "default": re.search(r"(\w+) by default", text),
        "-v": re.search(r"-v (\w+),", text),
        "-vv": re.search(r"-vv (\w+)", text),
        "serve -v": re.search(r"serve -v is (\w+)", text),
    }
    missing = [k for k, m in stated.items() if m is None]
    assert not missing, f"the -v help does not state the level for {missing}: {text!r}"
    cases = {"default": ["detect", "x"], "-v": ["detect", "x", "-v"], "-vv": ["detect", "x", "-vv"],
             "serve -v": ["serve", "-v"]}  # fmt: skip
    for key, argv in cases.items():
        args = parser.parse_args(argv)
        default = logging.INFO if args.command == "serve" else logging.WARNING
        level = log_level_of(args, default)[0]
        m = stated[key]
        assert m is not None and logging.getLevelName(level).lower() == m.group(1), (key, text)


def test_json_log_lines(capsys: pytest.CaptureFixture[str], root_logging: None) -> None:
    from service.logsetup import configure

    configure(logging.INFO, "json")
    logging.getLogger("oarmreg.test").info("scan %d recorded", 7)
    try:
        raise ValueError("boom")
    except ValueError:
        logging.getLogger("oarmreg.test").exception("failed")
    lines = [json.loads(line) for line in capsys.readouterr().err.splitlines()]
    assert lines[0]["message"] == "scan 7 recorded" and lines[0]["level"] == "INFO"
    assert lines[0]["logger"] == "oarmreg.test" and lines[0]["ts"].endswith("+00:00")
    assert lines[1]["level"] == "ERROR" and "ValueError: boom" in lines[1]["exc"]


# ---- serve: ports in use, the start-up line ------------------------------------------------------


def test_ports_in_use_are_reported_in_one_line_each(
    tmp_path: Path, clean_env: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str], root_logging: None
) -> None:
    held = []
    for _ in range(3):
        s = socket.socket()
        s.bind(("127.0.0.1", 0))
        s.listen()
        held.append(s)
    http, dicom, igtl = (s.getsockname()[1] for s in held)
    clean_env.setenv("OARMREG_API_TOKEN", TOKEN)
    argv = ["serve", "--config", str(SHIPPED), "--watch", str(tmp_path / "w"), "--data", str(tmp_path / "d"),
            "--port", str(http), "--dicom-port", str(dicom), "--igtl-port", str(igtl)]  # fmt: skip
    try:
        rc, _, err = _cli(argv, capsys)
    finally:
        for s in held:
            s.close()
    assert rc == 3
    lines = err.strip().splitlines()
    assert "Traceback" not in err and len(lines) == 3, err
    assert f"HTTP API: 127.0.0.1:{http} cannot be used" in lines[0] and "'port'" in lines[0]
    assert f"DICOM C-STORE: 127.0.0.1:{dicom}" in lines[1] and "'dicom.port'" in lines[1]
    assert f"OpenIGTLink: 127.0.0.1:{igtl}" in lines[2] and "'igtl.port'" in lines[2]
    assert not (tmp_path / "d").exists()  # refused before anything started


def test_the_start_up_line_names_every_listener_and_the_data_folder(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    caplog.set_level(logging.INFO, logger="service.runtime.assembly")
    with mock_robot() as mock:
        settings = fault_settings(tmp_path, mock.url, **{"dicom.enabled": True, "dicom.port": 0,
                                                          "igtl.enabled": True, "igtl.port": 0})  # fmt: skip
        with serve(settings, start_watcher=True) as s:
            status = s.client.get("/status").json()["listeners"]
    record = next(r for r in caplog.records if "listening:" in r.getMessage())
    line = record.getMessage()
    assert record.levelno == logging.INFO  # shown at serve's default level
    assert f"HTTP http://127.0.0.1:{settings.port}" in line
    assert f"DICOM C-STORE OARMREG@127.0.0.1:{status['dicom']['port']}" in line
    assert f"OpenIGTLink 127.0.0.1:{status['igtl']['port']}" in line
    assert f"data folder {settings.data_dir.resolve()}" in line
    assert f"watch folder {settings.watch_dir.resolve()}" in line


# ---- DICOM: the standard contexts a sender proposes ------------------------------------------------


def test_refused_standard_contexts_are_debug_and_still_counted(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    from pydicom.uid import CTImageStorage, ExplicitVRLittleEndian, MRImageStorage, UltrasoundImageStorage
    from pynetdicom import AE

    from dicomnet.scu import associate
    from service.intake.storage_scp import ScpCallbacks, StorageScp
    from service.settings import DicomSettings

    caplog.set_level(logging.DEBUG, logger="service.intake.storage_scp")
    with StorageScp(DicomSettings(port=0), tmp_path, ScpCallbacks(None, None, None)) as scp:
        for contexts in ((CTImageStorage, MRImageStorage, UltrasoundImageStorage), (MRImageStorage,)):
            ae = AE(ae_title="OARM")
            for c in contexts:
                ae.add_requested_context(c, [ExplicitVRLittleEndian])
            assoc = associate(ae, "127.0.0.1", scp.port, ae_title="OARMREG")
            if assoc.is_established:
                assoc.release()
        refused = [r for r in caplog.records if "refused (context)" in r.getMessage()]
        assert scp.counters["refused"] == 2
    assert [r.levelno for r in refused] == [logging.DEBUG, logging.WARNING], [r.getMessage() for r in refused]
    assert "MR Image Storage" in refused[0].getMessage()


# ---- systemd ---------------------------------------------------------------------------------------


def test_the_systemd_unit_is_hardened() -> None:
    text = UNIT.read_text()
    keys = dict(line.split("=", 1) for line in text.splitlines() if "=" in line and not line.startswith("#"))
    assert keys["User"] == "oarmreg" and keys["ProtectSystem"] == "strict"
    assert keys["ReadWritePaths"].split() == ["/var/lib/oarmreg", "/srv/oarm-export"]
    assert keys["Restart"] == "on-failure" and keys["RestartPreventExitStatus"] == "3"
    assert keys["NoNewPrivileges"] == "true" and keys["CapabilityBoundingSet"] == ""
    assert keys["ExecStart"].endswith("oarmreg serve --config /etc/oarmreg/oarmreg.toml")


@pytest.mark.skipif(shutil.which("systemd-analyze") is None, reason="systemd-analyze not installed")
def test_the_systemd_unit_verifies(tmp_path: Path) -> None:
    exe = Path(sys.executable).with_name("oarmreg")
    assert exe.is_file(), exe
    unit = tmp_path / "oarmreg.service"
    unit.write_text(UNIT.read_text().replace("ExecStart=/opt/oarmreg/bin/oarmreg", f"ExecStart={exe}"))
    r = subprocess.run(["systemd-analyze", "verify", str(unit)], capture_output=True, text=True, timeout=60)
    assert r.returncode == 0, r.stderr
    assert "ignoring" not in r.stderr and "Unknown" not in r.stderr, r.stderr


def test_config_check_names_every_problem_at_once(
    tmp_path: Path, clean_env: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str], root_logging: None
) -> None:
    """Issue 34: a missing phantom stopped the check before the robot model and link were looked at."""
    clean_env.setenv("OARMREG_ROBOT__MODEL", str(tmp_path / "missing.urdf"))
    clean_env.setenv("OARMREG_PHANTOM_FILE", str(tmp_path / "missing_phantom.toml"))
    clean_env.setenv("OARMREG_ROBOT__LINK_URL", "simple-message://127.0.0.1:11002?no_such_option=1")
    rc, _, err = _cli(["config", "check", "--config", str(SHIPPED)], capsys)
    assert rc == 3 and "3 problems" in err
    assert all(k in err for k in ("'phantom_file'", "'robot.model'", "'robot.link_url'")), err
