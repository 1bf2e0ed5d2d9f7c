"""Unit tests of :class:`service.registrations.orchestrator.Orchestrator` without the HTTP app.

A real SQLite database, real settings, the real pipeline after detection (kinematics, matching, the
FRE and verification gates); detection returns the sphere centres the test put in the scan
(tests/unit/service/registrations/doubles.py).  Each test checks the events published.
"""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from drivers.errors import RobotLinkError
from registration.errors import AccuracyGateError, RobotMovedError, TooFewSpheresError
from service.errors import (
    InternalError,
    NoCurrentRegistrationError,
    NoScanError,
    NotFoundError,
    SupersededScanError,
    VerificationRefusedError,
    VerificationUncomputableError,
)
from service.events import (
    DerivedWithdrawn,
    RegistrationDone,
    RegistrationRefused,
    RegistrationWithdrawn,
    VerificationDone,
)
from service.records import RegistrationRecord, RegistrationRefusal
from service.registrations.orchestrator import Orchestrator, SupersededOverride
from service.store.calibrations import CalibrationRecord
from tests.unit.service.registrations.doubles import (
    IMAGE_FROM_ROBOT,
    POSES,
    Cell,
    make_settings,
    moved,
    open_cell,
)


@pytest.fixture
def cell(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Iterator[Cell]:
    c = open_cell(tmp_path, monkeypatch)
    yield c
    c.db.close()


def orchestrator(cell: Cell) -> Orchestrator:
    return Orchestrator(cell.settings, cell.db, cell.phantom, cell.model, cell.publish, volumes=cell.volumes)


def accepted(out: RegistrationRecord | RegistrationRefusal) -> RegistrationRecord:
    assert isinstance(out, RegistrationRecord), f"refused: {getattr(out, 'error', out)}"
    return out


def refused(out: RegistrationRecord | RegistrationRefusal) -> RegistrationRefusal:
    assert isinstance(out, RegistrationRefusal), f"accepted: registration {getattr(out, 'id', out)}"
    return out


def registered(cell: Cell, orch: Orchestrator, joints: Any = POSES[0]) -> RegistrationRecord:
    """A scan at ``joints``, registered and current; the events so far are cleared."""
    rec = accepted(orch.register(cell.scan(joints)))
    cell.publish.clear()
    return rec


# ---- register ------------------------------------------------------------------------------


def test_an_accepted_registration_becomes_current_and_is_published(cell: Cell) -> None:
    orch = orchestrator(cell)
    assert orch.current is None and orch.no_current_reason == ""
    sid = cell.scan()
    rec = accepted(orch.register())  # the latest complete scan
    assert (rec.status, rec.scan_id, rec.is_current) == ("accepted", sid, True)
    assert orch.current is not None and orch.current.id == rec.id
    assert cell.db.registrations.current_id() == rec.id
    # the real matching recovered the pose the detections were made with
    assert rec.image_from_robot is not None
    assert np.allclose(np.asarray(rec.image_from_robot), IMAGE_FROM_ROBOT, atol=0.2)
    assert rec.fre_mm is not None and rec.fre_mm < cell.settings.quality.max_fre_mm
    assert rec.figures is not None and rec.figures.n_matched == len(cell.phantom.centres_phantom_mm)
    prov = rec.figures.provenance
    assert prov["joints_rad"] == list(POSES[0]) and prov["calibration"] is None
    assert rec.figures.predicted_chain_error_mm == 1.0  # the nominal prior: no calibration
    [done] = cell.publish.events
    assert isinstance(done, RegistrationDone)
    assert (done.registration_id, done.scan_id, done.fre_mm) == (rec.id, sid, rec.fre_mm)
    assert cell.detector.calls == [rec.series_uid]


def test_targets_and_phantom_confirmation_are_passed_to_the_pipeline(cell: Cell) -> None:
    orch = orchestrator(cell)
    targets = [[300.0, -100.0, 500.0], [310.0, -90.0, 520.0]]
    rec = accepted(orch.register(cell.scan(), targets, phantom_confirmed=True))
    assert rec.figures is not None
    assert rec.figures.targets_source == "request"
    assert [list(t) for t in rec.figures.targets_image_mm] == targets
    assert len(rec.figures.predicted_tre_mm) == 2


@pytest.mark.parametrize(
    ("what", "error", "title", "status"),
    [
        ("too few spheres", TooFewSpheresError, "Too few spheres", 409),
        ("robot moved", RobotMovedError, "Robot moved during the scan", 409),
        ("no joints", RobotLinkError, "Robot link error", 409),
        ("FRE over the gate", AccuracyGateError, "Accuracy gate failed", 409),
        ("a bug", InternalError, "Internal error", 500),
    ],
)
def test_a_refusal_is_stored_and_published_and_the_current_registration_stays(
    tmp_path: Path,
    monkeypatch: pytest.MonkeyPatch,
    what: str,
    error: type[Exception],
    title: str,
    status: int,
) -> None:
    cell = open_cell(tmp_path, monkeypatch, **({"quality.max_fre_mm": 0.01} if "FRE" in what else {}))
    try:
        orch = orchestrator(cell)
        before = None
        if "FRE" not in what:  # with a 0.01 mm gate nothing is accepted
            before = registered(cell, orch)
        if what == "too few spheres":
            sid = cell.scan(POSES[1], n_spheres=4)
        elif what == "robot moved":
            sid = cell.scan(POSES[1], verdict="moved")
        elif what == "no joints":
            sid = cell.scan(POSES[1], snapshot=False)
        elif what == "a bug":
            sid = cell.scan(POSES[1])

            def boom(uid: str) -> None:
                raise ZeroDivisionError("oops")

            cell.detector.before = boom
        else:
            sid = cell.scan(POSES[1])
        out = refused(orch.register(sid))
        assert out.registration_id is not None
        stored = cell.db.registrations.get(out.registration_id)
        assert stored is not None
        assert (stored.status, stored.scan_id, stored.is_current) == ("refused", sid, False)
        assert (stored.problem_title, stored.http_status) == (title, status)
        assert stored.reason == str(out.error) and stored.reason
        assert type(out.error) is error
        if what == "a bug":
            assert "ZeroDivisionError: oops" in stored.reason
        # the previous current registration stays current, in memory and on disk
        assert (orch.current and orch.current.id) == (before and before.id)
        assert cell.db.registrations.current_id() == (before and before.id)
        [event] = cell.publish.events
        assert isinstance(event, RegistrationRefused)
        assert (event.registration_id, event.scan_id, event.title) == (out.registration_id, sid, title)
        assert event.reason == stored.reason
    finally:
        cell.db.close()


def test_a_scan_that_changes_while_it_is_registered_is_refused(cell: Cell) -> None:
    orch = orchestrator(cell)
    before = registered(cell, orch)
    sid = cell.scan(POSES[1])
    cell.detector.before = lambda uid: cell.db.scans.set_status(sid, "reopened", "instances added")
    out = refused(orch.register(sid))
    assert "changed while it was being registered" in str(out.error) and "reopened" in str(out.error)
    assert out.registration_id is not None
    stored = cell.db.registrations.get(out.registration_id)
    assert stored is not None and stored.status == "refused"
    assert orch.current is not None and orch.current.id == before.id
    assert cell.publish.names == ["registration_refused"]


def test_nothing_to_register_raises_and_stores_nothing(cell: Cell) -> None:
    orch = orchestrator(cell)
    with pytest.raises(NoScanError):
        orch.register()
    with pytest.raises(NotFoundError):
        orch.register(99)
    cell.scan(status="invalid")
    with pytest.raises(NoScanError):  # an invalid scan is not a complete one
        orch.register()
    assert cell.db.registrations.list() == [] and cell.publish.events == []
    assert not orch.busy


# ---- supersession --------------------------------------------------------------------------


def test_an_older_scan_is_refused_once_a_newer_scan_at_its_placement_is_registered(cell: Cell) -> None:
    orch = orchestrator(cell)
    older, newer = cell.scan(POSES[0]), cell.scan(POSES[1])
    current = accepted(orch.register(newer))
    cell.publish.clear()
    out = refused(orch.register(older))
    assert isinstance(out.error, SupersededScanError)
    assert (out.error.rule, out.error.newer_scan_id) == ("newer-registration", newer)
    assert out.registration_id is not None
    stored = cell.db.registrations.get(out.registration_id)
    assert stored is not None and (stored.status, stored.http_status) == ("refused", 409)
    assert orch.current is not None and orch.current.id == current.id
    assert cell.publish.names == ["registration_refused"]
    older_uid = cell.db.scans.get(older).series_uid  # type: ignore[union-attr]
    assert older_uid not in cell.detector.calls  # refused before the pipeline ran
    # elsewhere (another placement) an older scan is not superseded
    other = accepted(orch.register(cell.scan(POSES[2], for_uid="1.2.826.0.1.3680043.8.498.4402")))
    assert orch.current is not None and orch.current.id == other.id


def test_an_override_registers_a_superseded_scan_and_names_it_in_the_provenance(cell: Cell) -> None:
    orch = orchestrator(cell)
    older, newer = cell.scan(POSES[0]), cell.scan(POSES[1])
    accepted(orch.register(newer))
    cell.publish.clear()
    rec = accepted(orch.register(older, override=SupersededOverride("the surgeon asked")))
    assert rec.figures is not None
    override = rec.figures.provenance["superseded_override"]
    assert override["rule"] == "newer-registration" and override["newer_scan_id"] == newer
    assert override["reason"] == "the surgeon asked"
    assert orch.current is not None and orch.current.id == rec.id
    assert cell.publish.names == ["registration_done"]


def test_the_scan_of_a_registration_a_verification_withdrew_may_not_be_registered_again(cell: Cell) -> None:
    orch = orchestrator(cell)
    reg = registered(cell, orch, POSES[0])
    failing = cell.scan(POSES[1], image_from_robot=moved([2.0, 0.0, 0.0]))
    assert not orch.verify(failing).passed
    out = refused(orch.register(reg.scan_id))
    assert isinstance(out.error, SupersededScanError)
    assert (out.error.rule, out.error.newer_scan_id) == ("withdrawn", failing)
    assert "may not be registered again" in str(out.error)
    assert orch.current is None


# ---- verify --------------------------------------------------------------------------------


def test_a_passing_verification_at_another_pose_keeps_and_upgrades_the_current_registration(
    cell: Cell,
) -> None:
    orch = orchestrator(cell)
    reg = registered(cell, orch, POSES[0])
    assert reg.verified_by is None
    sid = cell.scan(POSES[1])
    ver = orch.verify()
    assert (ver.registration_id, ver.scan_id, ver.passed) == (reg.id, sid, True)
    assert ver.max_mm <= cell.settings.quality.max_verification_error_mm
    assert ver.histogram_path is not None and Path(ver.histogram_path).is_file()
    assert orch.current is not None and orch.current.id == reg.id and orch.current.verified_by == ver.id
    [done] = cell.publish.events
    assert isinstance(done, VerificationDone)
    assert (done.verification_id, done.registration_id, done.passed) == (ver.id, reg.id, True)
    # a restart restores the current registration with its evidence
    again = orchestrator(cell)
    assert again.current is not None and again.current.verified_by == ver.id


def test_a_failed_verification_withdraws_the_registration_it_verified(cell: Cell) -> None:
    orch = orchestrator(cell)
    reg = registered(cell, orch, POSES[0])
    sid = cell.scan(POSES[1], image_from_robot=moved([0.0, 2.0, 0.0]))  # the phantom was knocked 2 mm
    ver = orch.verify(sid)
    assert not ver.passed and 1.5 < ver.max_mm < 2.5
    assert orch.current is None and cell.db.registrations.current_id() is None
    withdrawn = cell.db.registrations.get(reg.id)
    assert withdrawn is not None and withdrawn.status == "withdrawn"
    assert (withdrawn.withdrawn_by_scan, withdrawn.withdrawn_by_verification) == (sid, ver.id)
    assert cell.publish.names == ["verification_done", "registration_withdrawn"]
    done, gone = cell.publish.events
    assert isinstance(done, VerificationDone) and not done.passed
    assert isinstance(gone, RegistrationWithdrawn)
    assert (gone.registration_ids, gone.was_current, gone.verification_scan_id) == ((reg.id,), True, sid)
    assert (
        gone.verification_id == ver.id
        and f"verification {ver.id} (scan {sid}) failed its gate" in gone.reason
    )
    # why nothing is current: at another pose, with the nominal model's 1 mm prior at the 1 mm gate
    w = orch.withdrawal
    assert w is not None and (w.registration_id, w.verification_id) == (reg.id, ver.id)
    assert (w.likely_cause, w.calibrated, w.predicted_chain_error_mm) == ("cell-not-calibrated", False, 1.0)
    assert orch.no_current_reason == w.describe() and f"registration {reg.id} was withdrawn" in w.describe()
    with pytest.raises(NoCurrentRegistrationError):
        orch.verify()
    # the withdrawal is still why nothing is current after a restart
    again = orchestrator(cell)
    assert again.current is None and again.withdrawal == w
    # a new accepted registration ends it
    accepted(orch.register(cell.scan(POSES[2], image_from_robot=moved([0.0, 2.0, 0.0]))))
    assert orch.withdrawal is None and orch.no_current_reason == ""


def test_a_failed_verification_at_the_registration_pose_blames_the_phantom_or_the_oarm(cell: Cell) -> None:
    orch = orchestrator(cell)
    registered(cell, orch, POSES[0])
    orch.verify(cell.scan(POSES[0], image_from_robot=moved([2.0, 0.0, 0.0])))
    w = orch.withdrawal
    assert w is not None and w.likely_cause == "phantom-or-oarm-moved"
    assert "registration scan's own joints" in w.cause


def test_a_verification_beyond_matching_withdraws_and_raises_uncomputable(cell: Cell) -> None:
    orch = orchestrator(cell)
    reg = registered(cell, orch, POSES[0])
    sid = cell.scan(POSES[1], image_from_robot=moved([40.0, 0.0, 0.0]))
    with pytest.raises(VerificationUncomputableError, match=f"registration {reg.id} is withdrawn"):
        orch.verify(sid)
    assert orch.current is None
    withdrawn = cell.db.registrations.get(reg.id)
    assert withdrawn is not None and (withdrawn.withdrawn_by_scan, withdrawn.withdrawn_by_verification) == (
        sid,
        None,
    )
    assert cell.db.verifications.list() == []
    [gone] = cell.publish.events
    assert isinstance(gone, RegistrationWithdrawn)
    assert (gone.registration_ids, gone.verification_scan_id, gone.verification_id) == ((reg.id,), sid, None)
    w = orch.withdrawal
    assert w is not None and w.verification_id is None and "could not be computed" in w.reason


def test_a_verification_scan_showing_too_few_spheres_withdraws_nothing(cell: Cell) -> None:
    orch = orchestrator(cell)
    reg = registered(cell, orch, POSES[0])
    with pytest.raises(TooFewSpheresError):
        orch.verify(cell.scan(POSES[1], n_spheres=3))
    assert orch.current is not None and orch.current.id == reg.id
    assert cell.db.registrations.current_id() == reg.id
    assert cell.publish.events == []


def test_a_verification_needs_a_current_registration_and_a_newer_scan(cell: Cell) -> None:
    orch = orchestrator(cell)
    with pytest.raises(NoCurrentRegistrationError):
        orch.verify(cell.scan())
    older = cell.scan(POSES[1])
    reg = registered(cell, orch, POSES[2])
    for sid in (older, reg.scan_id):
        with pytest.raises(VerificationRefusedError, match="is not newer than"):
            orch.verify(sid)
    assert orch.current is not None and orch.current.id == reg.id
    assert cell.publish.events == [] and cell.db.verifications.list() == []
    assert not orch.busy


# ---- withdrawals ---------------------------------------------------------------------------


def test_withdraw_scan_withdraws_the_registrations_of_a_changed_scan(cell: Cell) -> None:
    orch = orchestrator(cell)
    first = registered(cell, orch, POSES[0])
    assert first.scan_id is not None
    assert orch.withdraw_scan(first.scan_id + 100, "no such scan") == []  # nothing to withdraw
    assert cell.publish.events == []
    second = registered(cell, orch, POSES[1])
    assert second.scan_id is not None
    # the old scan changed: its registration is withdrawn, the current one (another scan) stays
    assert orch.withdraw_scan(first.scan_id, "instances replaced") == [first.id]
    assert orch.current is not None and orch.current.id == second.id
    [gone] = cell.publish.events
    assert isinstance(gone, RegistrationWithdrawn)
    assert (gone.registration_ids, gone.was_current, gone.reason) == (
        (first.id,),
        False,
        "instances replaced",
    )
    cell.publish.clear()
    # the current one's scan changed: nothing is current
    assert orch.withdraw_scan(second.scan_id, "instances added") == [second.id]
    assert orch.current is None and cell.db.registrations.current_id() is None
    [gone] = cell.publish.events
    assert isinstance(gone, RegistrationWithdrawn) and gone.was_current and gone.scan_id == second.scan_id
    assert orch.withdrawal is None  # not a verification's withdrawal
    assert orch.no_current_reason == f"registration {second.id} was withdrawn: instances added"


def test_withdraw_scan_also_withdraws_the_verifications_made_from_it(cell: Cell) -> None:
    orch = orchestrator(cell)
    reg = registered(cell, orch, POSES[0])
    sid = cell.scan(POSES[1])
    ver = orch.verify(sid)
    cell.publish.clear()
    assert orch.withdraw_scan(sid, "instances replaced") == []
    [derived] = cell.publish.events
    assert isinstance(derived, DerivedWithdrawn)
    assert (derived.verification_ids, derived.calibration_ids) == ((ver.id,), ())
    assert orch.current is not None and orch.current.id == reg.id


def test_a_restart_under_other_robot_settings_withdraws_the_restored_registration(
    cell: Cell, tmp_path: Path
) -> None:
    reg = registered(cell, orchestrator(cell))
    same = orchestrator(cell)  # a restart under the same settings restores it
    assert same.current is not None and same.current.id == reg.id
    assert same.withdraw_if_robot_side_changed() == "" and same.current is not None
    assert cell.publish.events == []
    cell.settings = make_settings(tmp_path, **{"robot.tool0_from_phantom.translation_mm": [0.0, 0.0, 250.0]})
    other = orchestrator(cell)
    assert other.current is not None  # restored, until the check
    reason = other.withdraw_if_robot_side_changed()
    assert "robot.tool0_from_phantom" in reason and f"registration {reg.id}" in reason
    assert other.current is None and cell.db.registrations.current_id() is None
    assert other.robot_side_withdrawal == reason
    stored = cell.db.registrations.get(reg.id)
    assert stored is not None and stored.status == "withdrawn"
    [gone] = cell.publish.events
    assert isinstance(gone, RegistrationWithdrawn)
    assert (gone.registration_ids, gone.was_current, gone.reason) == ((reg.id,), True, reason)
    assert other.no_current_reason == f"registration {reg.id} was withdrawn: {reason}"


# ---- calibration ---------------------------------------------------------------------------


def test_use_calibration_changes_the_model_and_rod_and_an_activation_clears_the_current(cell: Cell) -> None:
    orch = orchestrator(cell)
    reg = registered(cell, orch, POSES[0])
    rod = cell.rod.copy()
    ref = {"calibration_id": 7, "calibration_hash": "h", "robot_urdf": "x", "predicted_chain_error_mm": 0.2}
    assert orch.use_calibration(cell.model, rod, ref) is None  # a restore: the current one stays
    assert orch.calibration == ref and orch.tool0_from_phantom is rod
    assert orch.current is not None and orch.current.id == reg.id
    assert orch.use_calibration(cell.model, rod, ref, activate=lambda: "activated") == "activated"
    assert orch.current is None
    rec = accepted(orch.register(cell.scan(POSES[1])))
    assert rec.figures is not None and rec.figures.provenance["calibration"] == ref
    assert rec.figures.predicted_chain_error_mm == 0.2
    assert "calibration 7 posterior" in rec.figures.chain_error_source
    assert cell.publish.names == ["registration_done"]


def test_after_an_activation_no_current_reason_does_not_blame_an_older_withdrawal(cell: Cell) -> None:
    orch = orchestrator(cell)
    first = registered(cell, orch, POSES[0])
    assert first.scan_id is not None
    orch.withdraw_scan(first.scan_id, "instances replaced")  # nothing current: this is why
    assert orch.no_current_reason == f"registration {first.id} was withdrawn: instances replaced"
    second = registered(cell, orch, POSES[1])  # current again: the withdrawal is history
    cal_id = cell.db.calibrations.insert(
        CalibrationRecord(
            created_at="2026-01-01T00:00:00+00:00", status="done", scan_ids=(), params={},
            config_hash="c", software_version="v",
        )
    )  # fmt: skip
    orch.use_calibration(
        cell.model,
        cell.rod,
        {"calibration_id": cal_id},
        activate=lambda: cell.db.calibrations.activate(cal_id),
    )
    retired = cell.db.registrations.get(second.id)
    assert orch.current is None and retired is not None and retired.retired_by_calibration == cal_id
    # nothing is current because calibration cal_id retired registration `second`, not because of
    # registration `first`'s withdrawal (which `second` outlived)
    assert f"registration {first.id} was withdrawn" not in orch.no_current_reason
    assert orch.no_current_reason.startswith(
        f"registration {second.id} was retired when calibration {cal_id}"
    )
