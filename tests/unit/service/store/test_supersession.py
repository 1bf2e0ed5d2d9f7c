"""The store's half of "which registration may be current" (docs/safety.md, issue #31): a failed
verification withdraws the registration it verified in its own transaction, and
``RegistrationStore.supersession`` names the newer evidence against a scan, rule by rule.  The
service-level behaviour is tested against the running service in
``tests/faults/test_verification_governs.py``; this covers every branch of the rule cheaply."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import pytest

from service.records import NewScan, RegistrationRecord, VerificationFigures, VerificationRecord
from service.store import Database
from service.store.calibrations import CalibrationRecord

IDENTITY = ((1.0, 0.0, 0.0, 0.0), (0.0, 1.0, 0.0, 0.0), (0.0, 0.0, 1.0, 0.0), (0.0, 0.0, 0.0, 1.0))
PLACEMENT = "1.2.826.0.1.3680043.8.498.31"


@pytest.fixture
def db(tmp_path: Path) -> Iterator[Database]:
    d = Database.open(tmp_path / "x.sqlite3")
    yield d
    d.close()


def _scan(db: Database, name: str, for_uid: str = PLACEMENT) -> int:
    sid, _ = db.scans.upsert(
        NewScan(
            series_uid=f"1.2.3.{name}", folder=f"/{name}", status="complete", frame_of_reference_uid=for_uid
        )
    )
    return sid


def _register(db: Database, scan_id: int) -> int:
    return db.registrations.insert(
        RegistrationRecord(
            created_at="2026-01-01T00:00:00+00:00", status="accepted", config_hash="c", software_version="v",
            scan_id=scan_id, image_from_robot=IDENTITY,
        ),
        make_current=True,
    )  # fmt: skip


def _verify(db: Database, reg_id: int, scan_id: int, *, passed: bool) -> int:
    figures = VerificationFigures(
        errors=(), n_expected=28, n_detected=28, n_matched=28, max_verification_error_mm=1.0
    )
    record = VerificationRecord(
        created_at="2026-01-01T00:00:01+00:00", registration_id=reg_id, scan_id=scan_id, series_uid="s",
        passed=passed, mean_mm=0.5 if passed else 1.5, rms_mm=0.6, max_mm=0.9 if passed else 2.0,
        figures=figures, config_hash="c", software_version="v",
    )  # fmt: skip
    return db.verifications.insert(record, withdraw_reason=lambda v: f"verification {v} failed its gate")


def test_a_failed_verification_withdraws_and_supersedes_older_scans_at_its_placement(db: Database) -> None:
    older, reg_scan = _scan(db, "older"), _scan(db, "reg")
    elsewhere = _scan(db, "elsewhere", for_uid="1.2.826.0.1.3680043.8.498.99")
    reg = _register(db, reg_scan)
    passing_scan = _scan(db, "pass")
    _verify(db, reg, passing_scan, passed=True)  # a passing verification changes nothing
    assert (
        db.registrations.current_id() == reg and db.registrations.standing_verification_withdrawal() is None
    )
    assert db.registrations.supersession(older, PLACEMENT).rule == "newer-registration"  # type: ignore[union-attr]
    failing_scan = _scan(db, "fail")
    vid = _verify(db, reg, failing_scan, passed=False)
    assert db.registrations.current_id() is None
    withdrawn = db.registrations.get(reg)
    assert withdrawn is not None and withdrawn.status == "withdrawn"
    assert (withdrawn.withdrawn_by_scan, withdrawn.withdrawn_by_verification) == (failing_scan, vid)
    assert withdrawn.reason == f"verification {vid} failed its gate"
    standing = db.registrations.standing_verification_withdrawal()
    assert standing is not None and standing.id == reg
    # the withdrawn registration's own scan: rule "withdrawn", naming the verification scan
    own = db.registrations.supersession(reg_scan, PLACEMENT)
    assert own is not None and (own.rule, own.scan_id) == ("withdrawn", failing_scan)
    assert f"verification {vid} of scan {failing_scan}" in own.detail
    # an older scan at that placement: the newest newer evidence is the failed verification's scan
    sup = db.registrations.supersession(older, PLACEMENT)
    assert sup is not None and (sup.rule, sup.scan_id) == ("newer-failed-verification", failing_scan)
    assert f"failed verification {vid}" in sup.detail
    # another placement, an empty FrameOfReferenceUID, the newest scan itself: nothing applies
    assert db.registrations.supersession(elsewhere, "1.2.826.0.1.3680043.8.498.99") is None
    assert db.registrations.supersession(older, "") is None
    assert db.registrations.supersession(failing_scan, PLACEMENT) is None


def test_an_uncomputable_verification_withdraws_and_supersedes_like_a_failed_one(db: Database) -> None:
    older, reg_scan = _scan(db, "older"), _scan(db, "reg")
    reg = _register(db, reg_scan)
    beyond = _scan(db, "beyond")
    db.registrations.withdraw_for_verification(
        reg, "could not be computed", scan_id=beyond, verification_id=None
    )
    assert db.registrations.current_id() is None
    w = db.registrations.get(reg)
    assert w is not None and (w.withdrawn_by_scan, w.withdrawn_by_verification) == (beyond, None)
    sup = db.registrations.supersession(older, PLACEMENT)
    assert sup is not None and (sup.rule, sup.scan_id) == ("newer-failed-verification", beyond)
    assert "could not be computed" in sup.detail


def test_a_calibration_activation_makes_the_old_evidence_stale(db: Database) -> None:
    older, reg_scan = _scan(db, "older"), _scan(db, "reg")
    reg = _register(db, reg_scan)
    _verify(db, reg, _scan(db, "fail"), passed=False)
    cal = db.calibrations.insert(
        CalibrationRecord(
            created_at="2026-01-01T00:00:02+00:00", status="done", scan_ids=(), params={},
            config_hash="c", software_version="v",
        )
    )  # fmt: skip
    db.calibrations.activate(cal)
    assert db.registrations.standing_verification_withdrawal() is None
    # what failed under the nominal model says nothing of the calibrated one: the same scan may be
    # registered again; the newer scan's registration (retired) still supersedes the older scan
    assert db.registrations.supersession(reg_scan, PLACEMENT) is None
    sup = db.registrations.supersession(older, PLACEMENT)
    assert sup is not None and (sup.rule, sup.scan_id) == ("newer-registration", reg_scan)
