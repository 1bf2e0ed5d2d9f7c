"""Retention policy (issue #13): oldest first, by age or disk quota, never the current registration's
scan; every deletion recorded (row kept, ``files_deleted_at``, ``retention_log``) and published."""

from __future__ import annotations

from collections.abc import Iterator
from datetime import UTC, datetime, timedelta
from pathlib import Path

import pytest

from service.events import Event, ScanFilesDeleted
from service.intake.retention import PROTECTORS, protected_scan_ids, run_retention
from service.records import NewScan, RegistrationRecord
from service.store import Database

IDENTITY = ((1.0, 0.0, 0.0, 0.0), (0.0, 1.0, 0.0, 0.0), (0.0, 0.0, 1.0, 0.0), (0.0, 0.0, 0.0, 1.0))
NOW = datetime(2026, 6, 1, tzinfo=UTC)


@pytest.fixture
def db(tmp_path: Path) -> Iterator[Database]:
    d = Database.open(tmp_path / "data" / "db.sqlite3")
    yield d
    d.close()


def _scan(db: Database, watch: Path, name: str, age_days: float, n_bytes: int = 1000) -> int:
    folder = watch / name
    folder.mkdir(parents=True)
    (folder / "CT1.dcm").write_bytes(b"\0" * n_bytes)
    arrived = (NOW - timedelta(days=age_days)).isoformat()
    scan_id, _ = db.scans.upsert(
        NewScan(series_uid=f"1.2.{name}", folder=str(folder), status="complete", arrived_at=arrived)
    )
    return scan_id


def _make_current(db: Database, scan_id: int) -> None:
    rec = RegistrationRecord(
        created_at=NOW.isoformat(), status="accepted", config_hash="x", software_version="0",
        image_from_robot=IDENTITY, scan_id=scan_id,
    )  # fmt: skip
    db.registrations.insert(rec, make_current=True)


def test_old_scans_deleted_oldest_first_except_the_current_registrations(
    db: Database, tmp_path: Path
) -> None:
    watch = tmp_path / "watch"
    old_current = _scan(db, watch, "a", age_days=40)
    old = _scan(db, watch, "b", age_days=35)
    young = _scan(db, watch, "c", age_days=2)
    _make_current(db, old_current)
    events: list[Event] = []
    done = run_retention(db, watch, events.append, max_age_days=30, max_disk_mb=None, now=NOW)
    assert [d.scan_ids for d in done] == [(old,)]
    assert not (watch / "b").exists() and (watch / "a").exists() and (watch / "c").exists()
    assert events == [
        ScanFilesDeleted(scan_ids=(old,), folder=str(watch / "b"), bytes=1000, reason=done[0].reason)
    ]
    assert "max_age_days" in done[0].reason
    assert {s for s, _, _ in db.scans.with_files()} == {old_current, young}
    assert db.scans.get(old) is not None  # the record stays


def test_quota_deletes_oldest_until_under_it(db: Database, tmp_path: Path) -> None:
    watch = tmp_path / "watch"
    ids = [_scan(db, watch, n, age_days=10 - k, n_bytes=400_000) for k, n in enumerate("defg")]
    done = run_retention(db, watch, lambda event: None, max_age_days=None, max_disk_mb=0.9, now=NOW)
    assert [d.scan_ids[0] for d in done] == ids[:2]  # 1.6 MB → 0.8 MB: the two oldest
    assert run_retention(db, watch, lambda event: None, max_age_days=None, max_disk_mb=None, now=NOW) == []


def test_protection_is_extensible(db: Database, tmp_path: Path) -> None:
    watch = tmp_path / "watch"
    kept = _scan(db, watch, "h", age_days=99)
    PROTECTORS.append(lambda d: {kept})  # what the calibration engineer adds for the active calibration
    try:
        assert kept in protected_scan_ids(db)
        assert run_retention(db, watch, lambda event: None, max_age_days=1, max_disk_mb=None, now=NOW) == []
    finally:
        PROTECTORS.pop()
