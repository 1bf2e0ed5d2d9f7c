"""Issue 19 items 7 and 8 against the real service: "joint history incomplete" is not "robot moved",
health that reflects health, one serve per data folder, a private data folder, bounded ids, and a
link child process that dies with the service."""

from __future__ import annotations

import os
import stat
import subprocess
import sys
from pathlib import Path
from typing import Any

import pytest

from tests.faults._service import (
    REPO,
    TOKEN,
    ServeProcess,
    factory_series,
    free_port,
    in_process_service,
    wait_for,
    write_config,
)
from tests.helpers import http


@pytest.fixture(scope="module")
def world() -> Any:
    from registration.model.kinematics import RobotModel
    from registration.model.phantom import load_phantom
    from service.settings import DEFAULT_PHANTOM_FILE

    return load_phantom(DEFAULT_PHANTOM_FILE), RobotModel.load("tx60")


def test_first_scan_after_start_up_is_incomplete_not_moved(tmp_path: Path, world: Any) -> None:
    phantom, model = world
    with in_process_service(tmp_path, phantom, model, **{"health.link_hold_off_s": 0.5}) as svc:
        # the acquisition window (0.6 s before the first file) began before the link connected
        factory_series(svc.watch / "first")
        scan = svc.scan_where(lambda s: s["status"] == "complete", "the first scan")
        # what navigation sees first (the refusal), then the record (before issue 19 the 409 said
        # "Robot moved" with a deviation of 0.0 and the record had no verdict)
        r = svc.client.post("/register", json={"scan_id": scan["id"]})
        body = r.json()
        assert r.status_code == 409 and body["title"] == "Joint history incomplete", body
        assert body["type"].endswith("joint-history-incomplete") and "moved" not in body["title"].lower()
        assert "rescan" in body["detail"] and "deviat" not in body["detail"].lower(), body["detail"]
        assert scan["joints"]["verdict"] == "incomplete", scan["joints"]
        # ids beyond SQLite's integer range are a 4xx, never a 500
        for path in ("/calibrations/9223372036854775808", "/calibrations/9223372036854775808/robot.urdf"):
            assert svc.client.get(path).status_code == 422, path
        r = svc.client.post(
            "/calibrations/9223372036854775808/activate", headers={"Content-Type": "application/json"}
        )
        assert 400 <= r.status_code < 500
        # the data folder is private: folder 0700, every file 0600
        assert stat.S_IMODE(svc.data.stat().st_mode) == 0o700
        files = [p for p in svc.data.rglob("*") if p.is_file()]
        assert files and all(stat.S_IMODE(p.stat().st_mode) == 0o600 for p in files), [
            (p.name, oct(p.stat().st_mode)) for p in files
        ]
        # a healthy service, then the controller goes away: unhealthy after the hold-off, typed
        assert svc.client.get("/status").json()["healthy"] is True
        # the controller dies: connections closed, nothing listens (disconnect(down_s) blocked the test
        # for down_s, 30 s of the suite's budget)
        svc.mock.run(svc.mock.server.stop())

        def unhealthy() -> dict[str, Any] | None:
            st = svc.client.get("/status").json()
            return st if not st["healthy"] else None

        st = wait_for(unhealthy, "/status to turn unhealthy")
        assert [p["type"] for p in st["problem_details"]] == ["robot-link-down"], st["problem_details"]
        assert svc.client.get("/ready").status_code == 503
        assert svc.client.get("/health").status_code == 200  # liveness stays


def test_second_serve_on_one_data_folder_exits_3_and_kill9_ends_the_link_child(tmp_path: Path) -> None:
    from mocks.robot.robot import ScriptedRobot
    from mocks.robot.runner import run_mock_controller

    with run_mock_controller("simple-message", ScriptedRobot()) as mock:
        cfg = tmp_path / "oarmreg.toml"
        write_config(
            cfg,
            {
                "watch_dir": str(tmp_path / "watch"), "data_dir": str(tmp_path / "data"), "api_token": TOKEN,
                "port": free_port(), "robot.link_url": mock.url,
            },
        )  # fmt: skip
        first = ServeProcess(cfg, 0, tmp_path / "serve1.log")
        first.port = int(_port_of(cfg))
        first.start()
        try:
            second = subprocess.run(
                [sys.executable, "-m", "service.cli", "serve", "--config", str(cfg)],
                cwd=REPO, capture_output=True, text=True, timeout=120,
            )  # fmt: skip
            assert second.returncode == 3, second.stderr[-2000:]
            assert "another oarmreg serve" in second.stderr and f"pid {first.proc.pid}" in second.stderr  # type: ignore[union-attr]
            link = http.get(first.base_url + "/status", headers={"Authorization": f"Bearer {TOKEN}"}).json()
            assert link["healthy"], link["problems"]
            child = _link_child(first.proc.pid)  # type: ignore[union-attr]
            first.kill9()
            wait_for(lambda: not _alive(child), "the link child to exit after kill -9 of serve", 10.0)
        finally:
            first.stop()


def _port_of(cfg: Path) -> int:
    import tomllib

    return int(tomllib.loads(cfg.read_text())["port"])


def _link_child(parent_pid: int) -> int:
    def find() -> int | None:
        for d in Path("/proc").iterdir():
            if not d.name.isdigit():
                continue
            try:
                stat_fields = (d / "stat").read_text().rsplit(")", 1)[1].split()
                cmd = (d / "cmdline").read_bytes()
            except OSError:
                continue
            if int(stat_fields[1]) == parent_pid and b"drivers.link_process" in cmd:
                return int(d.name)
        return None

    return int(wait_for(find, "the link child process"))


def _alive(pid: int) -> bool:
    try:
        state = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0]
    except OSError:
        return False
    return state != "Z"


def test_data_dir_modes_are_tightened_at_start(tmp_path: Path) -> None:
    from service.data_dir import make_private

    data = tmp_path / "data"
    (data / "sub").mkdir(parents=True)
    (data / "sub" / "old.dcm").write_bytes(b"x")
    os.chmod(data, 0o755)
    os.chmod(data / "sub" / "old.dcm", 0o644)
    make_private(data)
    assert stat.S_IMODE(data.stat().st_mode) == 0o700
    assert stat.S_IMODE((data / "sub" / "old.dcm").stat().st_mode) == 0o600
