"""The calibration jobs alone, without HTTP: a real store in a temp folder, the orchestrator they
activate through and a recording bus.  What is refused at once (and stored so), what a restart does
with a calibration it finds running or made under other robot settings.  A whole calibration from
simulated scans runs through the service in tests/integration/test_calibration_service.py."""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import pytest

from registration.model.kinematics import RobotModel
from service.errors import NotFoundError
from service.events import CalibrationRefused
from service.records import NewScan
from service.registrations.calibration_jobs import CalibrationJobs, CalibrationRefusal, CalibrationRequest
from service.registrations.orchestrator import Orchestrator
from service.registrations.robot_side import FINGERPRINT_KEY
from service.settings import load_settings
from service.store import Database
from service.store.base import utc_now
from service.store.calibrations import CalibrationRecord

PLACEMENT = "1.2.826.0.1.3680043.8.498.4402"


@dataclass
class World:
    jobs: CalibrationJobs
    orchestrator: Orchestrator
    db: Database
    events: list[Any]

    def scan(self, name: str, for_uid: str = PLACEMENT, status: str = "complete") -> int:
        sid, _ = self.db.scans.upsert(
            NewScan(series_uid=f"1.2.3.{name}", folder=f"/{name}", status=status,  # type: ignore[arg-type]
                    frame_of_reference_uid=for_uid)
        )  # fmt: skip
        return sid

    def calibration(self, status: str, fingerprint: Any) -> int:
        return self.db.calibrations.insert(
            CalibrationRecord(
                created_at=utc_now(), status=status, scan_ids=(1, 2, 3, 4, 5, 6),  # type: ignore[arg-type]
                params={FINGERPRINT_KEY: fingerprint}, config_hash="c", software_version="v",
                frame_of_reference_uid=PLACEMENT, urdf_text="<robot name='x'/>", calibration_hash="h" * 64,
                result={}, finished_at=utc_now() if status == "done" else None,
            )
        )  # fmt: skip


@pytest.fixture
def world(tmp_path: Path, phantom: Any) -> Iterator[World]:
    settings = load_settings(None, {"data_dir": tmp_path / "data"})
    db = Database.open(tmp_path / "oarmreg.sqlite3")
    events: list[Any] = []
    try:
        model = RobotModel.load("tx60")
        orch = Orchestrator(settings, db, phantom, model, events.append)
        jobs = CalibrationJobs(settings, db, orch, phantom, model, orch.volumes, events.append)
        yield World(jobs, orch, db, events)
        jobs.stop()
    finally:
        db.close()


def test_scans_from_two_placements_are_refused_at_once_and_stored_refused(world: World) -> None:
    ids = [world.scan(f"a{k}") for k in range(5)] + [world.scan("b", for_uid=PLACEMENT + ".9")]
    out = world.jobs.start(CalibrationRequest(scan_ids=tuple(ids)))
    assert isinstance(out, CalibrationRefusal), out
    stored = world.db.calibrations.get(out.calibration_id)
    assert stored is not None and stored.status == "refused" and stored.reason, stored
    assert not world.jobs.running
    assert [e.calibration_id for e in world.events if isinstance(e, CalibrationRefused)] == [
        out.calibration_id
    ]


def test_a_scan_named_twice_or_incomplete_is_refused(world: World) -> None:
    a = world.scan("a")
    twice = world.jobs.start(CalibrationRequest(scan_ids=(a, a)))
    assert isinstance(twice, CalibrationRefusal) and "once" in str(twice.error), twice
    bad = world.scan("bad", status="invalid")
    incomplete = world.jobs.start(CalibrationRequest(scan_ids=(a, bad)))
    assert isinstance(incomplete, CalibrationRefusal) and "complete" in str(incomplete.error), incomplete
    assert not world.jobs.running


def test_an_unknown_scan_is_not_found_and_nothing_is_stored(world: World) -> None:
    with pytest.raises(NotFoundError, match="scan 999"):
        world.jobs.start(CalibrationRequest(scan_ids=(999,)))
    assert world.db.calibrations.list() == []


def test_a_restart_refuses_a_calibration_it_finds_running(world: World) -> None:
    cal = world.calibration("running", world.orchestrator.robot_settings)
    world.jobs.restore()
    stored = world.db.calibrations.get(cal)
    assert stored is not None and stored.status == "refused" and "stopped" in stored.reason, stored
    assert world.orchestrator.calibration is None


def test_a_restart_does_not_use_a_calibration_made_under_other_robot_settings(world: World) -> None:
    other = {**world.orchestrator.robot_settings, "robot.model": "tx2_60 0123abcd"}
    cal = world.calibration("done", other)
    world.db.calibrations.activate(cal)
    world.jobs.restore()
    assert f"calibration {cal}" in world.jobs.inactive_reason and "not used" in world.jobs.inactive_reason
    assert world.orchestrator.calibration is None  # the nominal model and rod stay in force
