"""Issue #13 items 4 and 9, and the data lifecycle: a damaged, foreign, empty or vanished database
is refused or reported, never silently re-initialised; ``serve`` says so in one line with exit 3;
``backup`` / ``restore`` keep every record; CLI numbers are checked at parse time.
"""

from __future__ import annotations

import os
import sqlite3
import subprocess
import sys
from pathlib import Path

import pytest

from registration.errors import ConfigError
from service.error_map import EXIT_CONFIG, EXIT_USAGE
from service.records import NewScan
from service.store import Database
from tests.faults.conftest import JSON, REPO_ROOT, fault_settings, mock_robot, serve
from tests.helpers import http
from tests.helpers.tokens import make_token

N_SCANS = 83
"""As many records as the tester lost to a 0-byte file."""
SERVE_TIMEOUT_S = 120.0


def make_db(path: Path, n: int = N_SCANS) -> None:
    db = Database.open(path)
    for i in range(n):
        db.scans.upsert(NewScan(series_uid=f"1.2.3.{i}", folder=f"/x/{i}", status="complete"))
    db.close()


def serve_cli(root: Path, *extra: str) -> subprocess.CompletedProcess[str]:
    """``oarmreg serve`` in a subprocess (it must fail before listening)."""
    env = {**os.environ, "OARMREG_API_TOKEN": make_token()}
    return subprocess.run(
        [sys.executable, "-m", "service.cli", "serve", "--port", "0", "--data", str(root / "data"),
         "--watch", str(root / "watch"), "--robot-link", "simple-message://127.0.0.1:9", *extra],
        cwd=REPO_ROOT, env=env, capture_output=True, text=True, timeout=SERVE_TIMEOUT_S, check=False,
    )  # fmt: skip


def assert_one_line_refusal(p: subprocess.CompletedProcess[str], *needles: str) -> None:
    assert p.returncode == EXIT_CONFIG, (p.returncode, p.stderr)
    assert "Traceback" not in p.stderr, p.stderr
    lines = [ln for ln in p.stderr.splitlines() if ln.strip()]
    assert len(lines) == 1, p.stderr
    for needle in needles:
        assert needle in lines[0], lines[0]


# ---- refused at start-up --------------------------------------------------------------------


def test_zero_byte_database_is_refused_not_reinitialised(tmp_path: Path) -> None:
    db = tmp_path / "data" / "oarmreg.sqlite3"
    db.parent.mkdir()
    db.touch()
    with pytest.raises(ConfigError, match="empty"):
        Database.open(db)
    assert db.stat().st_size == 0  # untouched
    assert_one_line_refusal(serve_cli(tmp_path), "empty", "oarmreg restore")
    assert db.stat().st_size == 0


def test_garbage_mid_file_is_refused_by_quick_check(tmp_path: Path) -> None:
    db = tmp_path / "data" / "oarmreg.sqlite3"
    make_db(db, 2000)  # several pages of scans
    size = db.stat().st_size
    with db.open("r+b") as f:
        f.seek(size // 2 // 4096 * 4096)
        f.write(os.urandom(4096))
    with pytest.raises(ConfigError, match=r"quick_check|cannot read"):
        Database.open(db)
    assert_one_line_refusal(serve_cli(tmp_path), "not a usable oarmreg database")


@pytest.mark.parametrize("kind", ["not-sqlite", "foreign-sqlite", "empty-sqlite"])
def test_foreign_files_are_refused(tmp_path: Path, kind: str) -> None:
    db = tmp_path / "oarmreg.sqlite3"
    if kind == "not-sqlite":
        db.write_bytes(b"PK\x03\x04 a zip, say" * 200)
    else:
        c = sqlite3.connect(db)
        if kind == "foreign-sqlite":
            c.execute("CREATE TABLE scans (x)")
            c.execute("PRAGMA user_version = 1")
        else:
            c.execute("PRAGMA user_version = 0")
            c.execute("CREATE TABLE t (x)")
            c.execute("DROP TABLE t")
        c.commit()
        c.close()
    before = db.read_bytes()
    with pytest.raises(ConfigError, match="not a usable oarmreg database"):
        Database.open(db)
    assert db.read_bytes() == before


def test_new_path_is_initialised_with_identity(tmp_path: Path) -> None:
    db = tmp_path / "new" / "oarmreg.sqlite3"
    Database.open(db).close()
    c = sqlite3.connect(db)
    assert c.execute("PRAGMA application_id").fetchone()[0] == 0x4F41524D
    row = c.execute("SELECT application, schema_version FROM oarmreg_identity").fetchone()
    assert row == ("oarmreg", c.execute("PRAGMA user_version").fetchone()[0])
    c.close()
    Database.open(db).close()  # and reopens


def test_serve_refuses_without_token_unless_loopback_no_auth_is_explicit(tmp_path: Path) -> None:
    env = {k: v for k, v in os.environ.items() if k != "OARMREG_API_TOKEN"}
    p = subprocess.run(
        [sys.executable, "-m", "service.cli", "serve", "--port", "0", "--data", str(tmp_path / "d"),
         "--watch", str(tmp_path / "w")],
        cwd=REPO_ROOT, env=env, capture_output=True, text=True, timeout=SERVE_TIMEOUT_S, check=False,
    )  # fmt: skip
    assert_one_line_refusal(p, "api_token", "none-loopback-only")
    with pytest.raises(ConfigError, match="none-loopback-only"):
        fault_settings(tmp_path, host="0.0.0.0", api_token="", **{"api.auth": "none-loopback-only"})


def test_no_auth_mode_is_explicit_and_warned(tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    settings = fault_settings(tmp_path, api_token="", **{"api.auth": "none-loopback-only"})
    with mock_robot() as mock, serve(settings.model_copy(update={"robot": settings.robot.model_copy(
            update={"link_url": mock.url})})) as s:  # fmt: skip
        assert http.get(s.base_url + "/status").status_code == 200
        assert http.post(s.base_url + "/register", headers={"Content-Type": "text/plain"}).status_code == 415
    assert any("authentication is OFF" in r.getMessage() for r in caplog.records)


# ---- vanished while running -----------------------------------------------------------------


def test_database_deleted_while_running_is_reported_and_rescued(tmp_path: Path) -> None:
    settings = fault_settings(tmp_path)
    make_db(settings.db_path)
    with mock_robot() as mock, serve(fault_settings(tmp_path, mock.url)) as s:
        assert s.client.get("/health").json()["status"] == "ok"
        for suffix in ("", "-wal", "-shm"):
            Path(str(settings.db_path) + suffix).unlink(missing_ok=True)
        h = s.client.get("/health")
        assert h.status_code == 503 and h.json()["status"] == "unhealthy"
        problem = h.json()["problems"][0]
        assert "deleted" in problem and "oarmreg restore" in problem
        st = s.client.get("/status").json()
        assert st["healthy"] is False and st["problems"] == [problem]
        r = s.client.post("/register", headers=JSON)
        assert r.status_code == 503 and r.json()["detail"] == problem
        assert s.client.post("/events/ticket", headers=JSON).status_code == 503
    rescued = sorted(settings.db_path.parent.glob("oarmreg.sqlite3.recovered-*"))
    assert len(rescued) == 1 and str(rescued[0]) in problem
    assert not settings.db_path.exists()
    from service.cli.main import main

    assert main(["restore", str(rescued[0]), "--data", str(settings.data_dir)]) == 0
    db = Database.open(settings.db_path)
    assert db.counts()["scans"] == N_SCANS  # every record came back
    db.close()


def test_database_replaced_while_running_is_reported(tmp_path: Path) -> None:
    settings = fault_settings(tmp_path)
    with mock_robot() as mock, serve(fault_settings(tmp_path, mock.url)) as s:
        other = tmp_path / "other.sqlite3"
        make_db(other, 1)
        os.replace(other, settings.db_path)
        assert "replaced" in s.client.get("/health").json()["problems"][0]
        assert s.client.post("/verify", json={}).status_code == 503


# ---- backup / restore -----------------------------------------------------------------------


def test_backup_while_serving_restore_refused_until_stopped(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    from service.cli.main import main

    settings = fault_settings(tmp_path)
    make_db(settings.db_path)
    (settings.data_dir / "calibrations").mkdir()
    (settings.data_dir / "calibrations" / "rod.json").write_text('{"translation_mm": [0, 0, 200]}')
    data = str(settings.data_dir)
    with mock_robot() as mock, serve(fault_settings(tmp_path, mock.url)) as s:
        s.client.post("/register", json={"scan_id": 1})  # an audited refusal (the scan has no files)
        assert main(["backup", str(tmp_path / "bk"), "--data", data]) == 0
        assert main(["restore", str(tmp_path / "bk"), "--data", data]) == EXIT_CONFIG
        assert "stop the service" in capsys.readouterr().err
    assert main(["backup", str(tmp_path / "bk"), "--data", data]) == EXIT_CONFIG  # not empty: refused
    db = Database.open(settings.db_path)  # lose records after the backup
    with db._conn.transaction() as c:
        c.execute("DELETE FROM registrations")
        c.execute("DELETE FROM scans")
    db.close()
    (settings.data_dir / "calibrations" / "rod.json").write_text("{}")
    assert main(["restore", str(tmp_path / "bk"), "--data", data]) == 0
    db = Database.open(settings.db_path)
    assert db.counts()["scans"] == N_SCANS and db.audit.list()[0].action == "register"
    db.close()
    assert "200" in (settings.data_dir / "calibrations" / "rod.json").read_text()
    assert list(settings.data_dir.glob("oarmreg.sqlite3.before-restore-*"))  # the replaced one kept


def test_damaged_backup_is_refused(tmp_path: Path) -> None:
    from service.cli.main import main

    settings = fault_settings(tmp_path)
    make_db(settings.db_path, 3)
    assert main(["backup", str(tmp_path / "bk"), "--data", str(settings.data_dir)]) == 0
    with (tmp_path / "bk" / "oarmreg.sqlite3").open("r+b") as f:
        f.seek(100)
        f.write(b"\x00" * 16)
    assert main(["restore", str(tmp_path / "bk"), "--data", str(settings.data_dir)]) == EXIT_CONFIG


# ---- item 9: CLI arguments ------------------------------------------------------------------


@pytest.mark.parametrize(
    ("args", "flag"),
    [
        (["--max-fre-mm", "-1"], "--max-fre-mm"),
        (["--max-fre-mm", "nan"], "--max-fre-mm"),
        (["--min-margin", "0"], "--min-margin"),
        (["--prior-rotation", "10,20"], "--prior-rotation"),
        (["--prior-rotation", "missing.json"], "--prior-rotation"),
        (["--prior-tolerance-deg", "50"], "--prior-tolerance-deg"),
    ],
)
def test_register_flags_are_checked(capsys: pytest.CaptureFixture[str], args: list[str], flag: str) -> None:
    from service.cli.main import main

    with pytest.raises(SystemExit) as e:
        main(["register", "--image-points", "x.json", "--robot-points", "y.json", *args])
    assert e.value.code == EXIT_USAGE
    err = capsys.readouterr().err
    assert f"argument {flag}" in err and "Invalid points file" not in err
