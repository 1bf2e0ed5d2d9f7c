"""Calibration through the running service (issue #10 item 6; design.md §9).

A seeded true cell (:class:`mocks.cell.TrueCell`: joint origins, offsets, rod, sag differ from the
nominal ones) poses the phantom; the mock controller streams the commanded joints; the simulated
O-arm exports each scan into the watched folder with one FrameOfReferenceUID.  Eight planned poses
are scanned once per module.  Then, over loopback HTTP: ``POST /calibrations`` → ``calibration_done``
(progress pose i of K on ``/events``), figures and URDF; ``activate`` → the current registration is
retired (none current, ``registration_retired`` published); ``/register`` → its provenance names
the calibration and it is closer to the truth at an unseen pose than the nominal one.  Fewer than 6
scans, or scans of two O-arm placements, are refused with the reason and stored.
No sleeps: waits poll with deadlines or read server-sent events.
"""

from __future__ import annotations

import json
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import httpx
import numpy as np
import pytest

from registration.model import frames
from tests.helpers.tokens import make_token
from tests.integration.polling import wait_for

TOKEN = make_token()
WINDOW_S = 0.6
DEADLINE_S = 120.0
JSON = {"Content-Type": "application/json"}
"""Bodiless POSTs carry it too: the service refuses any mutating request without it (CSRF, issue #13)."""
N_POSES = 8
START_JOINTS_RAD = (0.2, -0.15, 1.75, 0.3, 0.6, -0.9)
FOR_UID = "1.2.826.0.1.3680043.8.498.77"
OTHER_FOR_UID = "1.2.826.0.1.3680043.8.498.78"


@dataclass
class Session:
    client: httpx.Client
    robot: Any
    cell: Any
    model: Any
    rod: np.ndarray
    image_from_robot: np.ndarray
    scan_ids: list[int]
    odd_scan_id: int
    held_out_joints: np.ndarray
    watch: Path
    link_url: str
    events: list[tuple[str, dict[str, Any]]] = field(default_factory=list)


def _export(scan: Any, watch: Path, name: str, for_uid: str) -> str:
    from mocks.oarm.dicom_export import write_dicom_series

    staging = watch.parent / f"staging-{name}"
    res = write_dicom_series(scan, staging, write_truth=False, frame_of_reference_uid=for_uid)
    staging.rename(watch / name)
    return str(res.series_uid)


def _scan_at(
    client: httpx.Client,
    robot: Any,
    q: Any,
    make_scan: Callable[[Any], Any],
    watch: Path,
    name: str,
    uid: str,
) -> int:
    """Hold the robot at ``q`` until still, export the scan taken there, return its recorded id."""
    robot.move_to(tuple(float(v) for v in q), 0.01)
    end = robot.motion_end_t_s() + WINDOW_S

    def still() -> bool:
        st = client.get("/status").json()["link"]
        return st["state"] == "connected" and st["history_s"] > WINDOW_S and time.monotonic() > end

    wait_for(still, "the robot to be still", DEADLINE_S)
    series = _export(make_scan(q), watch, name, uid)

    def recorded() -> Any:
        return next((s for s in client.get("/scans").json() if s["series_uid"] == series), None)

    s = wait_for(recorded, f"scan {name} to be recorded", DEADLINE_S)
    assert s["status"] == "complete" and s["joints"]["still"], s
    return int(s["id"])


@pytest.fixture(scope="module")
def session(tmp_path_factory: pytest.TempPathFactory, phantom: Any) -> Iterator[Session]:
    from mocks.cell import TrueCell
    from mocks.oarm.simulator import AcquisitionSettings, simulate_scan
    from mocks.robot.robot import ScriptedRobot
    from mocks.robot.runner import run_mock_controller
    from registration.calibration.planner import PlannerParams, ScanVolume, feasible_poses, plan_poses
    from registration.calibration.urdf import read_chain
    from registration.model.kinematics import RobotModel
    from service.cli.commands.serve import serve_in_thread
    from service.http.app import create_app
    from service.settings import load_settings

    root = tmp_path_factory.mktemp("calsvc")
    watch, data = root / "watch", root / "data"
    model = RobotModel.load("tx60")
    robot = ScriptedRobot(START_JOINTS_RAD)
    acq = AcquisitionSettings.preset("small", rows=200, columns=200, n_slices=120, n_views=120)
    with run_mock_controller("simple-message", robot) as mock:
        settings = load_settings(
            None,
            {
                "watch_dir": watch, "data_dir": data, "api_token": TOKEN, "robot.link_url": mock.url,
                "stillness.window_s": WINDOW_S, "stillness.max_gap_s": 0.25,
                "watcher.quiet_period_s": 0.3, "watcher.poll_interval_s": 0.2,
                "igtl.enabled": True, "igtl.port": 0,
            },
        )  # fmt: skip
        rod = settings.robot.tool0_from_phantom.matrix()
        cell = TrueCell.sample(2, model, rod)
        rng = np.random.default_rng(2)
        y = frames.transform_from_xyz_rpy([1.0, -2.0, 3.0], [10.0, -5.0, 30.0]) @ frames.invert(
            cell.robot_from_tool0_true(START_JOINTS_RAD) @ cell.tool0_from_phantom
        )
        chain, pts = read_chain(model.urdf_path), phantom.centres_phantom_mm
        volume = ScanVolume(
            fov_radius_mm=acq.fov_radius_mm, half_length_mm=acq.n_slices * acq.slice_spacing_mm / 2
        )
        plan = plan_poses(
            y, chain, rod, pts, START_JOINTS_RAD, volume=volume,
            params=PlannerParams(n_poses=N_POSES, shift_mm=18.0),
        )  # fmt: skip
        cand, _, _ = feasible_poses(
            y, chain, rod, pts, START_JOINTS_RAD, volume=volume,
            params=PlannerParams(tilts_deg=(0.0, 20.0, 40.0), shift_mm=10.0),
        )  # fmt: skip
        planned = {tuple(np.round(q, 6)) for q in plan.joints_rad}
        held = np.array([q for q in cand if tuple(np.round(q, 6)) not in planned][:5])

        def make_scan(q: Any) -> Any:
            return simulate_scan(phantom, cell.image_from_phantom_true(y, q, rng), acq)

        app = create_app(settings, phantom=phantom, robot_model=model)
        with (
            serve_in_thread(app) as server,
            httpx.Client(
                base_url=server.base_url, headers={"Authorization": f"Bearer {TOKEN}"}, timeout=60.0
            ) as client,
        ):
            ids = [
                _scan_at(client, robot, q, make_scan, watch, f"pose-{i}", FOR_UID)
                for i, q in enumerate(plan.joints_rad)
            ]
            odd = _scan_at(client, robot, plan.joints_rad[0], make_scan, watch, "odd", OTHER_FOR_UID)
            yield Session(client, robot, cell, model, rod, y, ids, odd, held, watch, mock.url)


def _stream_until(client: httpx.Client, start: Callable[[], Any], done: set[str]) -> tuple[Any, list[Any]]:
    """Subscribe to /events, call ``start``, collect events until one named in ``done`` arrives."""
    events: list[tuple[str, dict[str, Any]]] = []
    with client.stream("GET", "/events", timeout=httpx.Timeout(DEADLINE_S)) as stream:
        out = start()
        name = None
        for line in stream.iter_lines():
            if line.startswith("event:"):
                name = line.split(":", 1)[1].strip()
            elif line.startswith("data:") and name is not None:
                events.append((name, json.loads(line.split(":", 1)[1])))
                if name in done:
                    break
    return out, events


def _true_error_mm(s: Session, reg: dict[str, Any], model: Any, rod: np.ndarray, pts: np.ndarray) -> float:
    """Mean sphere-centre error at the held-out poses: registration + model + rod vs the true cell."""
    y_est = np.asarray(reg["image_from_robot"])
    errs = [
        np.linalg.norm(
            frames.apply(y_est @ model.robot_from_tool0(q) @ rod, pts)
            - frames.apply(s.cell.image_from_phantom_true(s.image_from_robot, q), pts),
            axis=1,
        ).mean()
        for q in s.held_out_joints
    ]
    return float(np.mean(errs))


def test_calibrate_activate_retire_and_register_with_it(session: Session, phantom: Any) -> None:
    from registration.calibration.records import NOMINAL_CHAIN_ERROR_MM
    from registration.model.kinematics import RobotModel

    c = session.client
    before = c.post("/register", json={"scan_id": session.scan_ids[-1]})
    assert before.status_code == 200, before.text
    assert before.json()["provenance"]["calibration"] is None
    # issue 40 item 1: what backs the robot side, first: nothing yet (nominal model, configured rod)
    ev = before.json()["evidence"]
    assert ev["level"] == "unverified" and "verify at another pose" in ev["action"], ev
    # no calibration: the chain figure is the nominal model's prior, never the one-scan TRE alone
    assert before.json()["predicted_chain_error_mm"] == NOMINAL_CHAIN_ERROR_MM
    body = {"scan_ids": session.scan_ids, "drop_weak": True}
    r, events = _stream_until(
        c, lambda: c.post("/calibrations", json=body), {"calibration_done", "calibration_refused"}
    )
    assert r.status_code == 202 and r.json()["status"] == "running", r.text
    cal_id = r.json()["id"]
    assert events[-1][0] == "calibration_done", events[-1]
    progress = [d["pose"] for n, d in events if n == "calibration_progress" and d["stage"] == "detect"]
    assert progress == list(range(1, N_POSES + 1))
    cal = c.get(f"/calibrations/{cal_id}").json()
    assert cal["status"] == "done" and cal["scan_ids"] == session.scan_ids
    assert cal["frame_of_reference_uid"] == FOR_UID and len(cal["poses"]) == N_POSES
    assert all(p["std_error"] > 0 for p in cal["parameters"]) and cal["leave_one_pose_out_mean_mm"] < 0.3
    assert all(len(p["sphere_residuals_mm"]) >= 20 for p in cal["poses"])
    urdf = c.get(cal["urdf_url"])
    assert urdf.status_code == 200 and "<robot" in urdf.text and f"calibration {cal_id}" in urdf.text

    # a registration is current: activation without "force" is refused and changes nothing (#21)
    refused = c.post(f"/calibrations/{cal_id}/activate", headers=JSON)
    assert refused.status_code == 409 and f"registration {before.json()['id']}" in refused.json()["detail"]
    assert c.get("/registration/current").json()["id"] == before.json()["id"]
    act, events = _stream_until(
        c, lambda: c.post(f"/calibrations/{cal_id}/activate", json={"force": True}), {"registration_retired"}
    )
    assert act.status_code == 200 and act.json()["is_active"], act.text
    retired = events[-1][1]
    assert retired["previous_current_registration_id"] == before.json()["id"]
    assert c.get(f"/registrations/{before.json()['id']}").json()["status"] == "retired"
    none = c.get("/registration/current")
    assert none.status_code == 409 and none.json()["title"] == "No current registration", none.text
    assert c.get("/status").json()["active_calibration"]["calibration_id"] == cal_id

    after = c.post("/register", json={"scan_id": session.scan_ids[-1]})
    assert after.status_code == 200, after.text
    prov = after.json()["provenance"]
    assert prov["calibration"]["calibration_id"] == cal_id
    assert after.json()["evidence"]["level"] == "calibrated" and not after.json()["evidence"]["action"]
    # the same level where navigation and the OR read it: OpenIGTLink metadata and the page
    assert _evidence_over_igtl(c, after.json()["id"]) == "calibrated"
    _page_shows_evidence(c, after.json()["id"], "calibrated")
    _restart_under_another_rod_does_not_use_it(session, phantom, cal_id, after.json()["id"])
    assert prov["calibration"]["calibration_hash"] == cal["calibration_hash"]
    assert np.allclose(prov["tool0_from_phantom"], cal["tool0_from_phantom"])
    chain_mm = after.json()["predicted_chain_error_mm"]
    assert chain_mm == prov["calibration"]["predicted_chain_error_mm"]
    assert 0.0 < chain_mm < NOMINAL_CHAIN_ERROR_MM
    pts = phantom.centres_phantom_mm
    cal_model = RobotModel.load(Path(prov["calibration"]["robot_urdf"]))
    nominal_mm = _true_error_mm(session, before.json(), session.model, session.rod, pts)
    calibrated_mm = _true_error_mm(
        session, after.json(), cal_model, np.asarray(cal["tool0_from_phantom"]), pts
    )
    assert calibrated_mm < 0.5 * nominal_mm, (calibrated_mm, nominal_mm)

    # one of its scans changes content: the calibration is withdrawn AND stops being active (the
    # nominal model again), the registration made with it is retired, nothing is current
    victim_scan = c.get(f"/scans/{session.scan_ids[-1]}").json()
    _, events = _stream_until(
        c, lambda: _replace_one_slice(session.watch / f"pose-{N_POSES - 1}"), {"registration_retired"}
    )
    names = [n for n, _ in events]
    assert "derived_withdrawn" in names and "calibration_deactivated" in names, names
    assert events[-1][1]["calibration_id"] == cal_id and events[-1][1]["current"] is None
    assert c.get("/status").json()["active_calibration"] is None
    gone = c.get(f"/calibrations/{cal_id}").json()
    assert not gone["is_active"] and gone["withdrawn_at"] is not None, gone
    again = c.post(f"/calibrations/{cal_id}/activate", json={"force": True})
    assert again.status_code == 409 and "withdrawn" in again.json()["detail"], again.text
    assert c.get("/registration/current").status_code == 409
    assert c.get(f"/registrations/{after.json()['id']}").json()["status"] in ("retired", "withdrawn")
    rejudged = wait_for(
        lambda: (lambda s: s if s["status"] == "complete" and s["joints"] else None)(
            c.get(f"/scans/{victim_scan['id']}").json()
        ),
        "the changed scan to be judged again",
        DEADLINE_S,
    )
    nominal_again = c.post("/register", json={"scan_id": rejudged["id"]})
    assert nominal_again.status_code == 200, nominal_again.text
    assert nominal_again.json()["provenance"]["calibration"] is None


def _evidence_over_igtl(c: httpx.Client, registration_id: int) -> str:
    """``Evidence`` of ``RobotToImage`` for ``registration_id`` as pyigtl (Slicer's Python client)
    reads it, after a version-2 hello (as Slicer sends at connect)."""
    import pyigtl

    port = c.get("/status").json()["listeners"]["igtl"]["port"]
    client = pyigtl.OpenIGTLinkClient(host="127.0.0.1", port=port)
    hello = pyigtl.StringMessage("reads header version 2", device_name="Hello")
    hello.header_version = 2
    client.send_message(hello, wait=False)
    try:
        msg = wait_for(
            lambda: (
                (m := client.wait_for_message("RobotToImage", timeout=0.2)) is not None
                and m.metadata.get("RegistrationId") == str(registration_id)
                and m
            ),
            f"RobotToImage of registration {registration_id}",
            DEADLINE_S,
        )
    finally:
        client.stop()
    return str(msg.metadata["Evidence"])


def _page_shows_evidence(c: httpx.Client, registration_id: int, level: str) -> None:
    """The page (the distribution's Chromium) shows ``registration_id`` as current at ``level``:
    the pill in capitals, no "unverified" warning look, no console error."""
    from tests.browser import harness as bh

    with bh.browser() as b:
        ctx = b.new_context(viewport={"width": 1400, "height": 1000})
        ctx.set_default_timeout(DEADLINE_S * 1000)
        try:
            w = bh.watched_page(ctx, str(c.base_url).rstrip("/"))
            w.page.goto(f"{str(c.base_url).rstrip('/')}/#token={TOKEN}")
            w.page.wait_for_function(
                "id => document.getElementById('current-id').dataset.value === String(id)",
                arg=registration_id,
            )
            p = w.page
            assert p.get_attribute("#current-evidence", "data-level") == level
            assert p.text_content("#current-evidence-level") == level.upper()
            assert "pill ok" in (p.get_attribute("#current-evidence-level", "class") or "")
            assert "unverified" not in (p.text_content("#current-badge") or "")
            assert not w.console_errors(), w.console_errors()
        finally:
            ctx.close()


def _restart_under_another_rod_does_not_use_it(s: Session, phantom: Any, cal_id: int, reg_id: int) -> None:
    """A service started on a copy of the records under a 210 mm rod (not the calibration's 200 mm):
    the calibration stays active but is not used (``/status``, ``/ready`` ``calibration-not-used``,
    naming the setting) and the registration made with it is not restored."""
    import sqlite3

    from registration.model.kinematics import RobotModel
    from service.cli.commands.serve import serve_in_thread
    from service.http.app import create_app
    from service.settings import load_settings

    root = s.watch.parent / "restart-210mm"
    data2 = root / "data"
    data2.mkdir(parents=True)
    settings = load_settings(
        None,
        {
            "watch_dir": root / "watch", "data_dir": data2, "api_token": TOKEN, "robot.link_url": s.link_url,
            "robot.tool0_from_phantom": {"translation_mm": (0.0, 0.0, 210.0), "rpy_deg": (180.0, 0.0, 0.0)},
        },
    )  # fmt: skip
    src, dst = (
        sqlite3.connect(s.watch.parent / "data" / settings.db_path.name),
        sqlite3.connect(settings.db_path),
    )
    try:
        src.backup(dst)  # SQLite's online backup: the running service keeps its folder (serve.lock)
    finally:
        src.close()
        dst.close()
    app = create_app(settings, phantom=phantom, robot_model=RobotModel.load("tx60"))
    with (
        serve_in_thread(app) as server,
        httpx.Client(base_url=server.base_url, headers={"Authorization": f"Bearer {TOKEN}"}) as c2,
    ):
        active = c2.get("/status").json()["active_calibration"]
        assert active["calibration_id"] == cal_id and not active["in_use"], active
        assert "tool0_from_phantom" in active["not_in_use_reason"], active
        ready = c2.get("/ready")
        problems = {p["type"]: p["detail"] for p in ready.json()["problems"]}
        assert ready.status_code == 503 and f"calibration {cal_id}" in problems["calibration-not-used"]
        assert c2.get("/registration/current").status_code == 409
        assert c2.get(f"/registrations/{reg_id}").json()["status"] == "withdrawn"


def _replace_one_slice(folder: Path) -> None:
    """Re-export the middle slice of a recorded folder scan with other bytes (same name)."""
    from tests.helpers.dicom_factory import rewrite_with_other_pixels

    files = sorted(folder.glob("*.dcm"))
    rewrite_with_other_pixels(files[len(files) // 2])


def _assert_refused_and_stored(c: httpx.Client, body: dict[str, Any], title: str, words: str) -> None:
    r = c.post("/calibrations", json=body)
    assert r.status_code == 409 and r.headers["content-type"].startswith("application/problem+json"), r.text
    p = r.json()
    assert p["title"] == title and words in p["detail"]
    stored = c.get(f"/calibrations/{p['calibration_id']}").json()
    assert stored["status"] == "refused" and stored["reason"] == p["detail"] and stored["urdf_url"] is None
    assert c.post(f"/calibrations/{p['calibration_id']}/activate", headers=JSON).status_code == 409


def test_fewer_than_six_scans_are_refused_and_stored(session: Session) -> None:
    _assert_refused_and_stored(
        session.client, {"scan_ids": session.scan_ids[:5]}, "Too few calibration poses", "at least 6"
    )


def test_two_o_arm_placements_are_refused_and_stored(session: Session) -> None:
    body = {"scan_ids": [*session.scan_ids[:6], session.odd_scan_id]}
    _assert_refused_and_stored(session.client, body, "Scans from different O-arm placements", OTHER_FOR_UID)
