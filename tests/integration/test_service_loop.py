"""The service on mock hardware: mock simple_message controller + simulated O-arm + real uvicorn.

Issue #6, done-when: the loop recovers ``image_from_robot`` (TRE ≤ 0.15 mm at targets 150 mm
from the phantom); robot moving during the scan → 409 refused, current unchanged; link down →
refused and visible in /status; restart → current registration restored; missing / wrong token
→ 401; a bad scan folder → 422 and the service keeps serving; two concurrent /register calls →
consistent records.

The two small scans are simulated once per module; one service (mock controller, app, uvicorn
thread) serves the tests of this module.  Each test sets up what it needs through fixtures
(``baseline``: the robot still at Q1 and a current registration of a scan taken there), so any
one of them passes alone and in any order.  No sleeps: every wait polls with a deadline or
reads server-sent events.
"""

from __future__ import annotations

import json
import shutil
import socket
import threading
import time
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import httpx
import numpy as np
import pytest

from registration.model.frames import apply, invert, transform_from_xyz_rpy
from tests.helpers.scan_cache import simulated_scan
from tests.helpers.tokens import make_token
from tests.integration.fast_service import fast_overrides
from tests.integration.polling import wait_for, wait_robot_still

TOKEN = make_token()
WINDOW_S = 0.6
"""Stillness window for the tests (s): short, so the robot settles quickly."""
DEADLINE_S = 60.0
TRE_TARGET_DISTANCE_MM = 150.0
TRE_LIMIT_MM = 0.15
Q1 = (0.0, 0.0, np.pi / 2, 0.0, np.pi / 4, 0.0)
Q2 = (0.0, 0.0, np.pi / 2, 0.0, np.pi / 4, 0.3)  # J6 +0.3 rad: the phantom turns about its own axis
IMAGE_FROM_PHANTOM_1 = transform_from_xyz_rpy([2.0, -3.0, 1.0], [10.0, -6.0, 20.0])


@dataclass
class World:
    """Ground truth shared by the module."""

    phantom: Any
    model: Any
    tool0_from_phantom: np.ndarray
    image_from_robot: np.ndarray
    scan1: Any
    scan2: Any


@pytest.fixture(scope="module")
def world(phantom) -> World:  # type: ignore[no-untyped-def]
    from mocks.oarm.simulator import AcquisitionSettings
    from registration.model.kinematics import RobotModel

    model = RobotModel.load("tx60")
    t0p = transform_from_xyz_rpy([0, 0, 200], [180, 0, 0])
    robot_from_phantom_1 = model.robot_from_tool0(Q1) @ t0p
    image_from_robot = IMAGE_FROM_PHANTOM_1 @ invert(robot_from_phantom_1)
    image_from_phantom_2 = image_from_robot @ model.robot_from_tool0(Q2) @ t0p
    acq = AcquisitionSettings.preset("small")
    scan1 = simulated_scan(phantom, IMAGE_FROM_PHANTOM_1, acq)
    scan2 = simulated_scan(phantom, image_from_phantom_2, AcquisitionSettings.preset("small", seed=1))
    return World(phantom, model, t0p, image_from_robot, scan1, scan2)


@dataclass
class Service:
    base_url: str
    client: httpx.Client
    robot: Any
    mock: Any
    settings: Any
    watch: Path
    data: Path
    n_exports: int = 0
    baseline_scan_id: int | None = None
    ctx: Any = None
    """The app's :class:`service.runtime.context.ServiceContext` (its event bus)."""

    def export(
        self, scan: Any, name: str, *, series_uid: str | None = None, drop_slice: int | None = None
    ) -> str:
        """Write ``scan`` as a DICOM series into ``watch/<name>-<n>`` (atomically, like the O-arm export).

        Without ``series_uid`` every export is a new series (a new UID).
        """
        from mocks.oarm.dicom_export import write_dicom_series

        name = f"{name}-{self.n_exports}"
        staging = self.watch.parent / f"staging-{name}"
        res = write_dicom_series(scan, staging, series_uid=series_uid, write_truth=False)
        if drop_slice is not None:
            sorted(staging.glob("*.dcm"))[drop_slice].unlink()
        staging.rename(self.watch / name)
        self.n_exports += 1
        return str(res.series_uid)

    def scan_by_uid(self, uid: str) -> dict[str, Any] | None:
        r = self.client.get("/scans")
        r.raise_for_status()
        return next((s for s in r.json() if s["series_uid"] == uid), None)

    def wait_scan(self, uid: str) -> dict[str, Any]:
        return wait_for(lambda: self.scan_by_uid(uid), f"scan {uid} to be recorded")  # type: ignore[no-any-return]

    def wait_still(self) -> None:
        """Wait until the robot has been still for the stillness window and the link buffered it."""
        wait_robot_still(self.client, self.robot, WINDOW_S, DEADLINE_S)

    def hold_at(self, joints_rad: tuple[float, ...]) -> None:
        """Put the robot at ``joints_rad`` (at once if it is elsewhere) and wait until it is still there."""
        if not np.allclose(self.robot.joints_rad_at(), joints_rad, atol=1e-9) or time.monotonic() < (
            self.robot.motion_end_t_s()
        ):
            self.robot.move_to(joints_rad, duration_s=0.01)
        self.wait_still()


@dataclass(frozen=True)
class Baseline:
    """A scan taken with the robot still at Q1 and the current registration made from it."""

    scan_id: int
    registration: dict[str, Any]


def make_settings(watch: Path, data: Path, link_url: str, **kw: Any) -> Any:
    from service.settings import load_settings

    return load_settings(None, fast_overrides(watch, data, link_url, TOKEN, WINDOW_S, **kw))


@pytest.fixture(scope="module")
def svc(tmp_path_factory: pytest.TempPathFactory, world: World) -> Iterator[Service]:
    from mocks.robot.robot import ScriptedRobot
    from mocks.robot.runner import run_mock_controller
    from service.cli.commands.serve import serve_in_thread
    from service.http.app import create_app

    root = tmp_path_factory.mktemp("svc")
    watch, data = root / "watch", root / "data"
    robot = ScriptedRobot(Q1)
    with run_mock_controller("simple-message", robot) as mock:
        settings = make_settings(watch, data, mock.url)
        app = create_app(settings, phantom=world.phantom, robot_model=world.model)
        with (
            serve_in_thread(app) as server,
            httpx.Client(
                base_url=server.base_url, headers={"Authorization": f"Bearer {TOKEN}"}, timeout=60.0
            ) as client,
        ):
            s = Service(server.base_url, client, robot, mock, settings, watch, data, ctx=app.state.ctx)
            s.wait_still()
            yield s


@pytest.fixture
def baseline(svc: Service, world: World) -> Baseline:
    """The robot still at Q1; a scan taken there (exported once per module); a current registration of it."""
    svc.hold_at(Q1)
    if svc.baseline_scan_id is None:
        scan = svc.wait_scan(svc.export(world.scan1, "baseline"))
        assert scan["status"] == "complete" and scan["joints"]["still"], scan
        svc.baseline_scan_id = int(scan["id"])
    r = svc.client.get("/registration/current")
    if r.status_code == 200 and r.json()["scan_id"] == svc.baseline_scan_id:
        return Baseline(svc.baseline_scan_id, r.json())
    r = svc.client.post("/register", json={"scan_id": svc.baseline_scan_id})
    assert r.status_code == 200, r.text
    return Baseline(svc.baseline_scan_id, r.json())


def tre_at_targets_mm(world: World, estimated: np.ndarray, joints_rad: Any) -> float:
    """Largest |estimated − true| at 14 points 150 mm from the phantom centre (robot frame)."""
    centre = (world.model.robot_from_tool0(joints_rad) @ world.tool0_from_phantom)[:3, 3]
    dirs = np.vstack(
        [np.eye(3), -np.eye(3), np.array(np.meshgrid([-1, 1], [-1, 1], [-1, 1])).reshape(3, -1).T]
    )
    dirs = dirs / np.linalg.norm(dirs, axis=1, keepdims=True)
    pts = centre + TRE_TARGET_DISTANCE_MM * dirs
    return float(np.max(np.linalg.norm(apply(estimated, pts) - apply(world.image_from_robot, pts), axis=1)))


def assert_problem(r: httpx.Response, status: int) -> dict[str, Any]:
    assert r.status_code == status, r.text
    assert r.headers["content-type"].startswith("application/problem+json")
    body = r.json()
    assert body["status"] == status and body["title"] and body["detail"]
    return body  # type: ignore[no-any-return]


# ------------------------------------------------------------------------------------- tests


def test_missing_or_wrong_token_is_401(svc: Service) -> None:
    with httpx.Client(base_url=svc.base_url, timeout=10.0) as anon:
        assert anon.get("/health").status_code == 200
        for path in ("/status", "/scans", "/registration/current", "/robot/joints"):
            body = assert_problem(anon.get(path), 401)
            assert "Bearer" in body["detail"]
        r = anon.get("/status")
        assert r.headers["www-authenticate"].startswith("Bearer")
        assert_problem(anon.post("/register", json={}), 401)
        assert_problem(anon.get("/status", headers={"Authorization": "Bearer wrong-token-xxxxxxxxxxxx"}), 401)
        assert_problem(anon.get("/status", headers={"Authorization": f"Basic {TOKEN}"}), 401)
    assert svc.client.get("/status").status_code == 200


def test_register_recovers_image_from_robot(svc: Service, world: World) -> None:
    """Scan arrives (seen on /events), /register recovers the hidden transform within 0.15 mm TRE."""
    svc.hold_at(Q1)
    joints = svc.client.get("/robot/joints").json()
    assert np.allclose(joints["joints_rad"], Q1, atol=1e-6)
    events: list[tuple[str, dict[str, Any]]] = []
    with svc.client.stream("GET", "/events", timeout=httpx.Timeout(DEADLINE_S)) as stream:
        assert stream.headers["content-type"].startswith("text/event-stream")
        uid = svc.export(world.scan1, "scan1")
        name = None
        for line in stream.iter_lines():
            if line.startswith("event: "):
                name = line[7:]
            elif line.startswith("data: ") and name:
                events.append((name, json.loads(line[6:])))
                if name == "scan_arrived" and events[-1][1]["series_uid"] == uid:
                    break
    arrived = events[-1][1]
    assert arrived["still"] is True and arrived["link_state"] == "connected"
    scan = svc.client.get(f"/scans/{arrived['scan_id']}").json()
    assert scan["status"] == "complete" and scan["n_slices"] == 96
    assert np.allclose(scan["joints"]["joints_rad"], Q1, atol=1e-6)

    r = svc.client.post("/register", json={})
    assert r.status_code == 200, r.text
    reg = r.json()
    assert reg["status"] == "accepted" and reg["is_current"] and reg["scan_id"] == arrived["scan_id"]
    m = np.asarray(reg["image_from_robot"])
    tre = tre_at_targets_mm(world, m, Q1)
    assert tre <= TRE_LIMIT_MM, f"true TRE {tre:.4f} mm at {TRE_TARGET_DISTANCE_MM} mm"
    assert reg["n_matched"] >= 20 and reg["n_expected"] == 28
    assert 0 < reg["fre_mm"] < 0.5 and reg["fle_mm"] >= reg["fre_mm"]
    assert len(reg["predicted_tre_mm"]) == 6 and all(0 < t < 1 for t in reg["predicted_tre_mm"])
    assert reg["symmetry_margin"] >= 3 and abs(reg["rotation_det"] - 1) < 1e-9
    assert reg["provenance"]["series_uid"] == uid and reg["config_hash"] and reg["software_version"]
    assert np.allclose(reg["joints_rad"], Q1, atol=1e-6)
    cur = svc.client.get("/registration/current").json()
    assert cur["id"] == reg["id"] and cur["image_from_robot"] == reg["image_from_robot"]
    # the phantom's face offset β (issue #43): fitted with the pose, bounded, with its error
    assert abs(cur["face_offset_mm"]) < 0.15 and 0 < cur["face_offset_se_mm"] < 0.05

    # targets given in the IMAGE frame: predicted TRE reported at exactly those points
    targets = [[0.0, 0.0, 150.0], [100.0, 50.0, -20.0]]
    r2 = svc.client.post("/register", json={"targets_image_mm": targets})
    assert r2.status_code == 200, r2.text
    assert r2.json()["targets_image_mm"] == targets and len(r2.json()["predicted_tre_mm"]) == 2
    # the default targets (robot frame), sent back in the image frame, give the same predicted TRE:
    # the image → robot mapping of the UI's targets is right
    r3 = svc.client.post("/register", json={"targets_image_mm": reg["targets_image_mm"]})
    assert r3.status_code == 200, r3.text
    np.testing.assert_allclose(r3.json()["predicted_tre_mm"], reg["predicted_tre_mm"], rtol=1e-9)


def test_current_registration_fast_path_matches_the_route(svc: Service, baseline: Baseline) -> None:
    """GET /registration/current is served by a pure-ASGI fast path; it must answer exactly what the
    FastAPI route and model give, and leave every refusal to the route."""
    r = svc.client.get("/registration/current")
    assert r.status_code == 200 and r.headers["content-type"] == "application/json"
    cur = r.json()
    assert cur["id"] == baseline.registration["id"]
    assert cur == svc.client.get(f"/registrations/{cur['id']}").json()
    with httpx.Client(base_url=svc.base_url, timeout=10.0) as anon:
        assert_problem(anon.get("/registration/current"), 401)
        bad = {"Authorization": "Bearer wrong-token-xxxxxxxxxxxx"}
        assert_problem(anon.get("/registration/current", headers=bad), 401)
        assert_problem(anon.get("/registration/current", headers={"Authorization": f"Basic {TOKEN}"}), 401)
        prefix = {"Authorization": f"Bearer {TOKEN[:-1]}"}
        assert_problem(anon.get("/registration/current", headers=prefix), 401)


def test_a_raising_listener_breaks_nothing_and_a_failing_safety_one_holds_readiness(
    svc: Service, baseline: Baseline
) -> None:
    """Issue #35: listeners that raise on ``registration_done`` leave POST /register a 200 with the
    registration current, the listener after them still runs, the failures are counted on
    /status; a failing safety listener makes /ready 503 until its next call succeeds."""
    from service.events import RegistrationDone

    bus = svc.ctx.bus
    duty_fails = True
    seen_after: list[int] = []

    def buggy(event: RegistrationDone) -> None:
        raise RuntimeError("a listener bug (test)")

    def duty(event: RegistrationDone) -> None:
        if duty_fails:
            raise OSError("the safety duty could not be done (test)")

    def after(event: RegistrationDone) -> None:
        seen_after.append(event.registration_id)

    bus.listen(RegistrationDone, buggy)
    bus.listen(RegistrationDone, duty, safety=True)
    bus.listen(RegistrationDone, after)
    try:
        r = svc.client.post("/register", json={"scan_id": baseline.scan_id})
        assert r.status_code == 200, r.text
        reg_id = r.json()["id"]
        assert svc.client.get("/registration/current").json()["id"] == reg_id
        assert seen_after == [reg_id]
        counted = {
            f["listener"].rsplit(".", 1)[-1]: f
            for f in svc.client.get("/status").json()["listeners"]["event_bus_failures"]
        }
        assert counted["buggy"]["failures"] == 1 and not counted["buggy"]["safety"]
        assert counted["buggy"]["last_error"] == "RuntimeError: a listener bug (test)"
        assert counted["duty"]["safety"] and counted["duty"]["failing"]
        ready = svc.client.get("/ready")
        assert ready.status_code == 503, ready.text
        assert "safety-listener-failing" in [p["type"] for p in ready.json()["problems"]]

        duty_fails = False
        again = svc.client.post("/register", json={"scan_id": baseline.scan_id})
        assert again.status_code == 200, again.text
        ready = svc.client.get("/ready")
        assert "safety-listener-failing" not in [p["type"] for p in ready.json()["problems"]], ready.text
        assert seen_after == [reg_id, again.json()["id"]]
    finally:
        for fn in (buggy, duty, after):
            bus.unlisten(RegistrationDone, fn)


def test_concurrent_register_calls_give_consistent_records(svc: Service, baseline: Baseline) -> None:
    before = {r["id"] for r in svc.client.get("/registrations").json()}
    results: list[httpx.Response] = []
    lock = threading.Lock()

    def call() -> None:
        with httpx.Client(base_url=svc.base_url, headers=svc.client.headers, timeout=120.0) as c:
            resp = c.post("/register", json={"scan_id": baseline.scan_id})
        with lock:
            results.append(resp)

    threads = [threading.Thread(target=call) for _ in range(2)]
    for t in threads:
        t.start()
    for t in threads:
        t.join(120.0)
    assert [r.status_code for r in results] == [200, 200], [r.text for r in results]
    ids = sorted(r.json()["id"] for r in results)
    regs = {r["id"]: r for r in svc.client.get("/registrations").json()}
    assert set(regs) - before == set(ids)
    assert all(regs[i]["status"] == "accepted" for i in ids)
    cur = svc.client.get("/registration/current").json()
    assert cur["id"] == ids[-1]  # the later one is current, both stored whole
    assert [regs[i]["is_current"] for i in ids] == [False, True]
    assert np.allclose(regs[ids[0]]["image_from_robot"], regs[ids[1]]["image_from_robot"], atol=1e-9)


def test_bad_scan_folder_is_422_and_service_keeps_serving(
    svc: Service, world: World, baseline: Baseline
) -> None:
    cur_before = baseline.registration["id"]
    junk = svc.watch.parent / "staging-junk"
    junk.mkdir()
    (junk / "notes.txt").write_text("not DICOM")
    (junk / "image.dcm").write_bytes(b"\x00" * 300)
    junk.rename(svc.watch / "junk")
    uid = svc.export(
        world.scan1, "missing-slice", series_uid="1.2.826.0.1.3680043.8.498.999001", drop_slice=40
    )
    scan = svc.wait_scan(uid)
    assert scan["status"] == "invalid" and scan["reason"]
    body = assert_problem(svc.client.post("/register", json={"scan_id": scan["id"]}), 422)
    assert uid in body["detail"] and body["registration_id"] > 0
    stored = svc.client.get(f"/registrations/{body['registration_id']}").json()
    assert stored["status"] == "refused" and stored["reason"] == body["detail"]
    assert svc.client.get("/registration/current").json()["id"] == cur_before
    assert_problem(svc.client.post("/register", json={"scan_id": 99999}), 404)
    assert_problem(svc.client.post("/register", json={"targets_image_mm": [[1, 2]]}), 422)
    status = svc.client.get("/status").json()
    assert status["watcher"]["running"] and status["link"]["state"] == "connected"
    # issue #13 item 8: a folder with no readable series is recorded as invalid, with the reason
    (junk_scan,) = [s for s in svc.client.get("/scans").json() if s["folder"] == str(svc.watch / "junk")]
    assert junk_scan["status"] == "invalid" and "no readable CT series" in junk_scan["reason"]
    assert_problem(svc.client.post("/register", json={"scan_id": junk_scan["id"]}), 422)


def test_robot_moving_during_scan_is_refused(svc: Service, world: World, baseline: Baseline) -> None:
    cur_before = baseline.registration
    j6_start = svc.robot.joints_rad_at()[5]
    svc.robot.move_to(Q2, duration_s=6.0)  # still moving while the series is exported and settles
    # The minimum-jerk profile starts slowly: export only once J6 has clearly left the start, so the
    # stillness window sees motion however fast this machine writes the series.
    moved_rad = 20 * 5e-4  # 20 × the default stillness.max_deviation_rad
    wait_for(lambda: abs(svc.robot.joints_rad_at()[5] - j6_start) > moved_rad, "the robot to start moving")
    uid = svc.export(world.scan1, "moving", series_uid="1.2.826.0.1.3680043.8.498.999002")
    scan = svc.wait_scan(uid)
    assert scan["joints"]["still"] is False
    body = assert_problem(svc.client.post("/register", json={"scan_id": scan["id"]}), 409)
    assert "moved" in body["detail"] and body["title"] == "Robot moved during the scan"
    refused = svc.client.get(f"/registrations/{body['registration_id']}").json()
    assert refused["status"] == "refused" and not refused["is_current"]
    audited = [e for e in svc.client.get("/audit").json() if e["target_id"] == body["registration_id"]]
    assert [(e["action"], e["outcome"], e["detail"]) for e in audited] == [
        ("register", "refused", "Robot moved during the scan")
    ]  # the audit row names the stored refusal
    cur = svc.client.get("/registration/current").json()
    assert cur["id"] == cur_before["id"] and cur["image_from_robot"] == cur_before["image_from_robot"]


def test_controller_in_motion_with_constant_joints_is_refused_as_moved(
    svc: Service, baseline: Baseline
) -> None:
    """Issue 31 item 8: the mock controller reports STATUS in_motion = TRUE while its joints stand
    still at Q1: the scan is refused as moved, with the controller's own reason, and /status shows the
    flag (before, the scan registered: the joints alone looked still)."""
    from dataclasses import replace

    svc.hold_at(Q1)
    normal = svc.robot.controller_status
    svc.robot.controller_status = replace(normal, in_motion=1)
    try:
        wait_for(
            lambda: svc.client.get("/status").json()["link"].get("in_motion") is True, "/status in_motion"
        )
        svc.wait_still()  # the joints: still, and watched, for the whole window
        # a small series (the stillness check comes before the volume is loaded; with world.scan1 the
        # old code answered 200 and made it current, measured: 7.6 s of this test's time was its export)
        from tests.helpers.dicom_factory import ramp_volume, write_series

        staging, uid = svc.watch.parent / "staging-in-motion", "1.2.826.0.1.3680043.8.498.999003"
        write_series(staging, ramp_volume(6, 8, 8), series_uid=uid)
        staging.rename(svc.watch / "in-motion")
        scan = svc.wait_scan(uid)
        joints = scan["joints"]
        assert joints["still"] is False and joints["max_deviation_rad"] <= 5e-4, joints
        assert "controller reported in_motion at t=" in str(joints), joints
        body = assert_problem(svc.client.post("/register", json={"scan_id": scan["id"]}), 409)
        assert body["title"] == "Robot moved during the scan" and "in_motion" in body["detail"], body
    finally:
        svc.robot.controller_status = normal
    wait_for(lambda: svc.client.get("/status").json()["link"].get("in_motion") is False, "in_motion false")


def test_verify_after_moving_the_robot(svc: Service, world: World, baseline: Baseline) -> None:
    """The current registration (scan at Q1) predicts the spheres of a newer scan at Q2."""
    svc.hold_at(Q2)
    uid = svc.export(world.scan2, "scan2")
    scan = svc.wait_scan(uid)
    assert scan["joints"]["still"] is True
    r = svc.client.post("/verify", json={"scan_id": scan["id"]})
    assert r.status_code == 200, r.text
    ver = r.json()
    assert ver["registration_id"] == baseline.registration["id"]
    assert ver["n_matched"] >= 20 and ver["passed"]
    # issue 40 item 1: a pass at another pose upgrades the evidence, on REST and the fast path alike
    for path in ("/registration/current", f"/registrations/{baseline.registration['id']}"):
        ev = svc.client.get(path).json()["evidence"]
        assert ev["level"] == "verified" and str(ver["id"]) in ev["summary"], (path, ev)
    assert ver["mean_mm"] < TRE_LIMIT_MM and ver["max_mm"] < 0.5
    assert ver["rms_mm"] >= ver["mean_mm"] and len(ver["errors"]) == ver["n_matched"]
    png = svc.client.get(ver["histogram_url"])
    assert png.status_code == 200 and png.headers["content-type"] == "image/png"
    assert png.content.startswith(b"\x89PNG")
    assert (svc.data / "histograms").is_dir()


def test_restart_restores_current_registration(
    svc: Service, world: World, baseline: Baseline, tmp_path: Path
) -> None:
    from service.cli.commands.serve import serve_in_thread
    from service.http.app import create_app

    cur = svc.client.get("/registration/current").json()
    assert cur["id"] == baseline.registration["id"]
    n_regs = len(svc.client.get("/registrations").json())
    # A second service may not share the running one's data folder (serve.lock, issue 19): the
    # restarted service opens a copy of the database (SQLite's online backup).
    data2 = _copy_database(svc, tmp_path)
    app2 = create_app(
        make_settings(svc.watch, data2, svc.mock.url), phantom=world.phantom, robot_model=world.model
    )
    with (
        serve_in_thread(app2) as server2,
        httpx.Client(base_url=server2.base_url, headers={"Authorization": f"Bearer {TOKEN}"}) as c2,
    ):
        cur2 = c2.get("/registration/current").json()
        assert cur2["id"] == cur["id"] and cur2["image_from_robot"] == cur["image_from_robot"]
        assert cur2["fre_mm"] == cur["fre_mm"]
        assert len(c2.get("/registrations").json()) == n_regs
        # the series already in the folder are recognised by UID, not recorded again
        scans2 = wait_for(lambda: c2.get("/status").json()["watcher"]["last_scan_at"], "a watcher pass")
        assert scans2
        assert len(c2.get("/scans").json()) == len(svc.client.get("/scans").json())


def _copy_database(svc: Service, tmp_path: Path) -> Path:
    """A data folder holding a copy of the running service's database (SQLite's online backup): a
    second service may not share the running one's data folder (serve.lock, issue 19)."""
    import sqlite3

    data2 = tmp_path / "data"
    data2.mkdir()
    src = sqlite3.connect(svc.settings.db_path)
    dst = sqlite3.connect(data2 / svc.settings.db_path.name)
    try:
        src.backup(dst)
    finally:
        src.close()
        dst.close()
    return data2


def test_restart_after_a_rod_change_withdraws_the_current_registration(
    svc: Service, world: World, baseline: Baseline, tmp_path: Path
) -> None:
    """Issue 40 item 2: a restart under another rod does not restore the registration made with the
    old one (on main: 'restored current registration', the old matrix served); it is withdrawn with
    a reason naming the setting, and nothing is current."""
    from service.cli.commands.serve import serve_in_thread
    from service.http.app import create_app

    reg_id = baseline.registration["id"]
    data2 = _copy_database(svc, tmp_path)
    rod = {"translation_mm": (0.0, 0.0, 210.0), "rpy_deg": (180.0, 0.0, 0.0)}
    settings2 = make_settings(svc.watch, data2, svc.mock.url, **{"robot.tool0_from_phantom": rod})
    app2 = create_app(settings2, phantom=world.phantom, robot_model=world.model)
    with (
        serve_in_thread(app2) as server2,
        httpx.Client(base_url=server2.base_url, headers={"Authorization": f"Bearer {TOKEN}"}) as c2,
    ):
        assert c2.get("/registration/current").status_code != 200
        rec = c2.get(f"/registrations/{reg_id}").json()
        assert rec["status"] == "withdrawn", rec
        assert "robot.tool0_from_phantom" in rec["reason"], rec
        ready = c2.get("/ready")  # not ready, and it says why (on main: 200, the old matrix current)
        problems = {p["type"]: p["detail"] for p in ready.json()["problems"]}
        assert ready.status_code == 503 and "robot.tool0_from_phantom" in problems["robot-settings-changed"]


def _dead_port() -> int:
    s = socket.socket()
    s.bind(("127.0.0.1", 0))
    port = int(s.getsockname()[1])
    s.close()
    return port


def test_link_down_is_refused_and_visible(tmp_path: Path, world: World) -> None:
    from service.cli.commands.serve import serve_in_thread
    from service.http.app import create_app

    watch, data = tmp_path / "watch", tmp_path / "data"
    settings = make_settings(watch, data, f"simple-message://127.0.0.1:{_dead_port()}")
    app = create_app(settings, phantom=world.phantom, robot_model=world.model)
    with (
        serve_in_thread(app) as server,
        httpx.Client(base_url=server.base_url, headers={"Authorization": f"Bearer {TOKEN}"}) as c,
    ):
        st = wait_for(lambda: (s := c.get("/status").json())["link"]["state"] == "down" and s, "link down")
        assert st["link"]["reason"]
        assert_problem(c.get("/robot/joints"), 409)
        assert_problem(c.post("/register", json={}), 409)  # no scan yet
        from mocks.oarm.dicom_export import write_dicom_series

        staging = tmp_path / "staging"
        uid = write_dicom_series(world.scan1, staging, write_truth=False).series_uid
        shutil.move(str(staging), str(watch / "scan"))
        scan = wait_for(
            lambda: next((s for s in c.get("/scans").json() if s["series_uid"] == uid), None), "scan recorded"
        )
        assert scan["joints"]["link_state"] == "down" and scan["joints"]["joints_rad"] is None
        body = assert_problem(c.post("/register", json={}), 409)
        assert "link" in body["detail"].lower() and body["title"].lower().startswith("robot link")
        assert_problem(c.get("/registration/current"), 409)
        assert c.get("/status").json()["current_registration"] is None
