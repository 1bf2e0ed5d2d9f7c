"""Unit tests of :class:`service.registrations.calibration_jobs.CalibrationJobs` without the HTTP app.

A real SQLite database, real settings and orchestrator, the real calibration worker thread (pose
matching and the solver) on scans whose sphere centres the test computed from the nominal robot
model and rod (tests/unit/service/registrations/doubles.py); a recording publisher checks the events
and is what the tests wait on (no sleeps).
"""

from __future__ import annotations

import threading
from collections.abc import Callable, Iterator, Sequence
from pathlib import Path

import pytest

from registration.calibration.records import MIN_POSES
from registration.errors import RobotMovedError, SessionMismatchError, TooFewPosesError
from service.error_map import http_status_of
from service.errors import (
    CalibrationBusyError,
    CalibrationNotUsableError,
    CalibrationRefusedError,
    NotFoundError,
)
from service.events import (
    CalibrationActivated,
    CalibrationDeactivated,
    CalibrationDone,
    CalibrationProgress,
    CalibrationRefused,
    CalibrationStarted,
    Event,
    RegistrationDone,
    RegistrationRetired,
    RegistrationWithdrawn,
)
from service.records import RegistrationRecord
from service.registrations.calibration_jobs import (
    URDF_FILE,
    CalibrationJobs,
    CalibrationRefusal,
    CalibrationRequest,
    calibration_hash,
)
from service.registrations.orchestrator import Orchestrator
from service.registrations.robot_side import FINGERPRINT_KEY
from service.store.calibrations import CalibrationRecord
from tests.unit.service.registrations.doubles import POSES, Cell, make_settings, open_cell

N_POSES = 8
"""Scans of a calibration session here: 6 (MIN_POSES) fit in ~1.5 s, 8 in ~0.7 s."""


class Service:
    """The two objects as ``_start_core`` makes them (service/http/app.py), on one cell."""

    def __init__(self, cell: Cell, publish: Callable[[Event], None] | None = None) -> None:
        """``publish`` defaults to the cell's recorder."""
        self.cell = cell
        publish = cell.publish if publish is None else publish
        self.orch = Orchestrator(
            cell.settings, cell.db, cell.phantom, cell.model, publish, volumes=cell.volumes
        )
        self.jobs = CalibrationJobs(
            cell.settings, cell.db, self.orch, cell.phantom, cell.model, cell.volumes, publish
        )

    def restart(self) -> Service:
        """A new service on the same database (the old one's worker stopped)."""
        self.jobs.stop()
        again = Service(self.cell)
        again.jobs.restore()
        again.orch.withdraw_if_robot_side_changed()
        return again


@pytest.fixture
def cell(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Iterator[Cell]:
    c = open_cell(tmp_path, monkeypatch)
    yield c
    c.db.close()


@pytest.fixture
def svc(cell: Cell) -> Iterator[Service]:
    s = Service(cell)
    yield s
    s.jobs.stop()  # joins the worker: no thread outlives the test


def session(cell: Cell, n: int = N_POSES) -> list[int]:
    assert len(POSES) >= n
    return [cell.scan(q) for q in POSES[:n]]


def calibrated(svc: Service, scan_ids: Sequence[int] | None = None) -> CalibrationRecord:
    """A finished calibration of ``scan_ids`` (default: a new session); its events are cleared."""
    ids = tuple(session(svc.cell) if scan_ids is None else scan_ids)
    started = svc.jobs.start(CalibrationRequest(scan_ids=ids))
    assert isinstance(started, CalibrationRecord)
    done = svc.cell.publish.wait_for(CalibrationDone)
    svc.jobs.stop()
    rec = svc.cell.db.calibrations.get(done.calibration_id)
    assert rec is not None and rec.status == "done", rec
    svc.cell.publish.clear()
    return rec


# ---- a calibration session -----------------------------------------------------------------


def test_calibration_started_reaches_listeners_before_the_workers_progress(cell: Cell) -> None:
    """``calibration_started`` is published before the worker can report: a listener here holds it
    for up to ``hold_s`` watching for the worker's first ``calibration_progress``, which it sees
    first if the worker is already running (as it was: started was published after the worker
    began, and under load the first progress came first in a full run)."""
    hold_s = 0.5
    record = cell.publish

    def listener(event: Event) -> None:
        if isinstance(event, CalibrationStarted):
            record.published_within(CalibrationProgress, hold_s)
        record(event)

    jobs = Service(cell, publish=listener).jobs
    ids = session(cell)
    try:
        assert isinstance(jobs.start(CalibrationRequest(scan_ids=tuple(ids))), CalibrationRecord)
        record.wait_for(CalibrationDone)
    finally:
        jobs.stop()
    assert record.names[:2] == ["calibration_started", "calibration_progress"], record.names


def test_a_calibration_runs_on_a_worker_and_stores_the_calibrated_model(svc: Service) -> None:
    cell = svc.cell
    ids = session(cell)
    out = svc.jobs.start(CalibrationRequest(last=N_POSES, parameter_set="full"))
    assert isinstance(out, CalibrationRecord)
    assert (out.status, out.scan_ids) == ("running", tuple(ids))  # the last K complete, oldest first
    done = cell.publish.wait_for(CalibrationDone)
    svc.jobs.stop()
    assert not svc.jobs.running
    rec = cell.db.calibrations.get(out.id)
    assert rec is not None and rec.status == "done" and rec.reason == ""
    assert not rec.is_active  # done is not active: only activate() makes it so
    assert svc.orch.calibration is None
    assert rec.result is not None and rec.urdf_text is not None and rec.urdf_path is not None
    assert Path(rec.urdf_path) == cell.settings.data_dir / "calibrations" / str(rec.id) / URDF_FILE
    assert Path(rec.urdf_path).read_text(encoding="utf-8") == rec.urdf_text
    assert rec.calibration_hash == calibration_hash(rec.urdf_text, rec.result["tool0_from_phantom"])
    prov = rec.result["provenance"]
    assert prov["calibration_id"] == rec.id and [s["scan_id"] for s in prov["scans"]] == ids
    assert rec.params[FINGERPRINT_KEY] == svc.orch.robot_settings
    assert rec.params["request"]["last"] == N_POSES
    # events: started, one detect step per scan, the fit, done
    assert cell.publish.names == (
        ["calibration_started"] + ["calibration_progress"] * (N_POSES + 1) + ["calibration_done"]
    )
    started = cell.publish.of(CalibrationStarted)[0]
    assert (started.calibration_id, started.scan_ids) == (rec.id, tuple(ids))
    progress = cell.publish.of(CalibrationProgress)
    assert [(p.stage, p.pose, p.scan_id) for p in progress[:-1]] == [
        ("detect", i, sid) for i, sid in enumerate(ids, start=1)
    ]
    assert all(p.n_matched == len(cell.phantom.centres_phantom_mm) for p in progress[:-1])
    assert (progress[-1].stage, progress[-1].pose, progress[-1].n_poses) == ("fit", N_POSES, N_POSES)
    assert (done.calibration_id, done.calibration_hash, done.n_poses_used) == (
        rec.id,
        rec.calibration_hash,
        N_POSES,
    )
    # the scans were consistent with the nominal model: the fit explains them to well under a mm
    assert done.leave_one_pose_out_mean_mm is not None and done.leave_one_pose_out_mean_mm < 0.5


def test_request_params_map_the_request_and_the_settings_target(cell: Cell) -> None:
    p = CalibrationRequest(parameter_set="offsets", drop_weak=True, max_condition=1e6).params(0.2)
    assert (p.parameter_set, p.on_weak, p.max_condition, p.target_rms_mm) == ("offsets", "drop", 1e6, 0.2)
    default = CalibrationRequest().params()
    assert (default.parameter_set, default.on_weak, default.max_condition) == ("full", "refuse", None)


@pytest.mark.parametrize("what", ["too few", "twice", "incomplete", "two placements", "none"])
def test_a_request_refused_at_once_is_stored_and_published_and_starts_nothing(
    svc: Service, what: str
) -> None:
    cell = svc.cell
    ids = session(cell, MIN_POSES)
    req = CalibrationRequest(scan_ids=tuple(ids))
    if what == "too few":
        req = CalibrationRequest(scan_ids=tuple(ids[:-1]))
    elif what == "twice":
        req = CalibrationRequest(scan_ids=(*ids, ids[0]))
    elif what == "incomplete":
        req = CalibrationRequest(scan_ids=(*ids, cell.scan(POSES[6], status="invalid")))
    elif what == "two placements":
        req = CalibrationRequest(scan_ids=(*ids, cell.scan(POSES[6], for_uid="1.2.826.0.1.3680043.8.498.9")))
    else:
        req = CalibrationRequest()  # neither scan ids nor last: no scans
    cell.publish.clear()
    out = svc.jobs.start(req)
    assert isinstance(out, CalibrationRefusal)
    expected = {
        "too few": TooFewPosesError,
        "twice": CalibrationRefusedError,
        "incomplete": CalibrationRefusedError,
        "two placements": SessionMismatchError,
        "none": TooFewPosesError,
    }[what]
    assert isinstance(out.error, expected)
    assert not svc.jobs.running
    rec = cell.db.calibrations.get(out.calibration_id)
    assert rec is not None and rec.status == "refused" and rec.reason == str(out.error)
    assert rec.finished_at is not None
    [event] = cell.publish.events
    assert isinstance(event, CalibrationRefused)
    assert (event.calibration_id, event.reason, event.title) == (rec.id, rec.reason, rec.problem_title)
    assert event.status == http_status_of(out.error) and event.status >= 400
    with pytest.raises(CalibrationNotUsableError, match="only a finished calibration"):
        svc.jobs.activate(rec.id)
    assert svc.orch.calibration is None and cell.db.calibrations.active_id() is None


def test_an_unknown_scan_raises_and_stores_nothing(svc: Service) -> None:
    ids = session(svc.cell, MIN_POSES)
    with pytest.raises(NotFoundError):
        svc.jobs.start(CalibrationRequest(scan_ids=(*ids, 999)))
    assert svc.cell.db.calibrations.list() == [] and svc.cell.publish.events == []


def test_a_scan_the_worker_refuses_refuses_the_calibration_and_nothing_is_activated(svc: Service) -> None:
    cell = svc.cell
    ids = session(cell, MIN_POSES)
    ids.append(cell.scan(POSES[MIN_POSES], verdict="moved"))
    out = svc.jobs.start(CalibrationRequest(scan_ids=tuple(ids)))
    assert isinstance(out, CalibrationRecord) and out.status == "running"
    refusal = cell.publish.wait_for(CalibrationRefused)
    svc.jobs.stop()
    rec = cell.db.calibrations.get(out.id)
    assert rec is not None and rec.status == "refused"
    assert rec.problem_title == RobotMovedError.title and "moved" in rec.reason
    assert (refusal.calibration_id, refusal.reason) == (rec.id, rec.reason)
    assert cell.publish.of(CalibrationDone) == []
    with pytest.raises(CalibrationNotUsableError):
        svc.jobs.activate(rec.id)
    with pytest.raises(NotFoundError):
        svc.jobs.activate(rec.id + 1)
    assert svc.orch.calibration is None and cell.db.calibrations.active_id() is None


def test_one_calibration_at_a_time_and_stop_abandons_the_running_one(svc: Service) -> None:
    cell = svc.cell
    ids = session(cell, MIN_POSES)
    entered, release = threading.Event(), threading.Event()

    def hold(uid: str) -> None:  # the worker waits in its first detection until released
        entered.set()
        assert release.wait(timeout=60.0)

    cell.detector.before = hold
    out = svc.jobs.start(CalibrationRequest(scan_ids=tuple(ids)))
    assert isinstance(out, CalibrationRecord)
    assert entered.wait(timeout=60.0) and svc.jobs.running
    with pytest.raises(CalibrationBusyError):
        svc.jobs.start(CalibrationRequest(scan_ids=tuple(ids)))
    assert [c.id for c in cell.db.calibrations.list()] == [out.id]  # the busy request stored nothing
    release.set()
    svc.jobs.stop()  # asks the worker to stop after this step, waits for it
    assert not svc.jobs.running
    rec = cell.db.calibrations.get(out.id)
    assert rec is not None and rec.status == "refused" and "stopping" in rec.reason
    assert len(cell.publish.of(CalibrationProgress)) == 1  # one scan, then it stopped
    assert cell.publish.of(CalibrationRefused)[0].calibration_id == out.id


# ---- activation and restore ----------------------------------------------------------------


def test_activating_a_calibration_makes_the_orchestrator_use_it_and_retires_the_registrations(
    svc: Service,
) -> None:
    cell = svc.cell
    cal = calibrated(svc)
    reg = svc.orch.register(cell.scan(POSES[0]))
    assert isinstance(reg, RegistrationRecord) and svc.orch.current is not None
    cell.publish.clear()
    rec, act = svc.jobs.activate(cal.id)
    assert rec.is_active and cell.db.calibrations.active_id() == cal.id
    assert (act.retired_registration_ids, act.previous_current_registration_id) == ((reg.id,), reg.id)
    assert svc.orch.current is None and cell.db.registrations.current_id() is None
    assert svc.orch.calibration is not None
    assert (svc.orch.calibration["calibration_id"], svc.orch.calibration["calibration_hash"]) == (
        cal.id,
        cal.calibration_hash,
    )
    assert svc.orch.robot_model.urdf_path == Path(str(cal.urdf_path))
    assert cell.publish.names == ["calibration_activated", "registration_retired"]
    activated, retired = cell.publish.events
    assert isinstance(activated, CalibrationActivated) and isinstance(retired, RegistrationRetired)
    assert (activated.calibration_id, activated.previous_calibration_id) == (cal.id, None)
    assert (retired.registration_ids, retired.calibration_id) == ((reg.id,), cal.id)
    # the next registration is made with the calibrated model and names it
    cell.publish.clear()
    new = svc.orch.register(cell.scan(POSES[1]))
    assert isinstance(new, RegistrationRecord) and new.figures is not None
    assert new.figures.provenance["calibration"]["calibration_id"] == cal.id
    assert cell.publish.of(RegistrationDone)[0].registration_id == new.id


def test_restore_after_a_restart_uses_the_active_calibration(svc: Service) -> None:
    cell = svc.cell
    cal = calibrated(svc)
    svc.jobs.activate(cal.id)
    reg = svc.orch.register(cell.scan(POSES[0]))
    assert isinstance(reg, RegistrationRecord)
    assert cal.urdf_path is not None
    Path(cal.urdf_path).unlink()  # rewritten from the stored row
    cell.publish.clear()
    again = svc.restart()
    try:
        assert again.orch.calibration is not None and again.orch.calibration["calibration_id"] == cal.id
        assert Path(cal.urdf_path).read_text(encoding="utf-8") == cal.urdf_text
        assert again.jobs.inactive_reason == ""
        # the registration made with it stays current
        assert again.orch.current is not None and again.orch.current.id == reg.id
        assert cell.publish.events == []
    finally:
        again.jobs.stop()


def test_restore_refuses_an_interrupted_calibration(svc: Service) -> None:
    cell = svc.cell
    ids = session(cell, MIN_POSES)
    entered, release = threading.Event(), threading.Event()

    def hold(uid: str) -> None:
        entered.set()
        assert release.wait(timeout=60.0)

    cell.detector.before = hold
    out = svc.jobs.start(CalibrationRequest(scan_ids=tuple(ids)))
    assert isinstance(out, CalibrationRecord) and entered.wait(timeout=60.0)
    # a second service on the database while the row says running: what a crash leaves behind
    other = Service(cell)
    other.jobs.restore()
    rec = cell.db.calibrations.get(out.id)
    assert rec is not None and rec.status == "refused" and "service stopped" in rec.reason
    assert other.orch.calibration is None
    release.set()
    svc.jobs.stop()


def test_restore_under_other_robot_settings_does_not_use_the_calibration(
    svc: Service, tmp_path: Path
) -> None:
    cell = svc.cell
    cal = calibrated(svc)
    svc.jobs.activate(cal.id)
    reg = svc.orch.register(cell.scan(POSES[0]))
    assert isinstance(reg, RegistrationRecord)
    svc.jobs.stop()
    cell.settings = make_settings(tmp_path, **{"robot.tool0_from_phantom.translation_mm": [0.0, 0.0, 250.0]})
    cell.publish.clear()
    again = svc.restart()
    try:
        assert f"calibration {cal.id} was made under other robot settings" in again.jobs.inactive_reason
        assert "robot.tool0_from_phantom" in again.jobs.inactive_reason
        assert again.orch.calibration is None
        # ...and the registration made with it is withdrawn, not served
        assert again.orch.current is None
        [gone] = cell.publish.events
        assert isinstance(gone, RegistrationWithdrawn) and gone.registration_ids == (reg.id,)
    finally:
        again.jobs.stop()


def test_a_changed_scan_of_the_active_calibration_deactivates_it(svc: Service) -> None:
    cell = svc.cell
    ids = session(cell)
    cal = calibrated(svc, ids)
    svc.jobs.activate(cal.id)
    reg = svc.orch.register(cell.scan(POSES[0]))
    assert isinstance(reg, RegistrationRecord)
    cell.publish.clear()
    assert svc.orch.withdraw_scan(ids[0], "instances replaced") == []
    assert svc.orch.calibration is None and svc.orch.robot_model is cell.model  # the nominal model again
    assert svc.orch.current is None and cell.db.calibrations.active_id() is None
    assert cell.publish.names == ["derived_withdrawn", "calibration_deactivated", "registration_retired"]
    deactivated = cell.publish.of(CalibrationDeactivated)[0]
    assert deactivated.calibration_id == cal.id and "instances replaced" in deactivated.reason
    assert cell.publish.of(RegistrationRetired)[0].registration_ids == (reg.id,)
    with pytest.raises(CalibrationNotUsableError, match="was withdrawn"):
        svc.jobs.activate(cal.id)
