"""The stillness verdict is a typed field of the joint snapshot, stored in its own column (schema 10)
and the only thing the registration gate decides by; the reason text is quoted, never parsed
(issue #35).  Old rows get the column from the migration, the one place that reads old text."""

from __future__ import annotations

import sqlite3
from collections.abc import Iterator
from pathlib import Path

import pytest

from registration.errors import JointHistoryIncompleteError, RobotMovedError
from service.records import JointSnapshot, NewScan, StillnessVerdict, stillness_verdict
from service.registrations.scan_checks import check_capture
from service.store import Database
from service.store.migrations import MIGRATIONS, STILLNESS_VERDICT_MIGRATION
from tests.helpers.old_schema import database_before

JOINTS = (0.0, 0.1, 0.2, 0.3, 0.4, 0.5)
MOVED_TEXT = "robot moved: joint 2 deviated 0.0573° (0.001000 rad > 0.0002 rad) during the 2 s window"
GAP_TEXT = "joint history incomplete: a 0.400 s gap (> 0.25 s) at 0.8 s into the 2 s window"


@pytest.fixture
def db(tmp_path: Path) -> Iterator[Database]:
    d = Database.open(tmp_path / "x.sqlite3")
    yield d
    d.close()


def _snap(verdict: StillnessVerdict, reason: str) -> JointSnapshot:
    return JointSnapshot(
        link_url="simple-message://127.0.0.1:1",
        link_state="connected",
        window_s=2.0,
        verdict=verdict,
        joints_rad=JOINTS,
        joints_received_at="2026-01-01T00:00:00+00:00",
        stillness_reason=reason,
    )


@pytest.mark.parametrize(
    ("verdict", "reason", "refusal"),
    [
        ("still", MOVED_TEXT, None),  # the text says moved, the verdict says still: registered
        ("moved", GAP_TEXT, RobotMovedError),  # the text says incomplete: refused as moved
        ("incomplete", MOVED_TEXT, JointHistoryIncompleteError),  # the text says moved: refused as unknown
    ],
)
def test_the_gate_decides_by_the_stored_verdict_not_the_reason_text(
    db: Database, verdict: StillnessVerdict, reason: str, refusal: type[Exception] | None
) -> None:
    snap = _snap(verdict, reason)
    new = NewScan(series_uid=f"1.2.{verdict}", folder="/w/a", status="complete", snapshot=snap)
    sid, _ = db.scans.upsert(new)
    assert db._conn.query("SELECT verdict FROM joint_snapshots WHERE scan_id = ?", (sid,))[0][0] == verdict
    scan = db.scans.get(sid)
    assert scan is not None and scan.snapshot is not None
    assert scan.snapshot.verdict == verdict and scan.snapshot.still is (verdict == "still")
    if refusal is None:
        snap, joints = check_capture(scan, window_s=2.0)
        assert joints == JOINTS and snap.stillness_reason == reason
    else:
        with pytest.raises(refusal) as err:
            check_capture(scan, window_s=2.0)
        assert reason in str(err.value)  # quoted for the operator, not parsed


def _schema_9_with_old_snapshots(path: Path) -> None:
    """A database as schema 9 left it: four scans whose snapshots carry only ``still`` and the reason."""
    c = database_before(path, STILLNESS_VERDICT_MIGRATION)
    rows = [
        (1, 1, ""),
        (2, 0, MOVED_TEXT),
        (3, 0, GAP_TEXT),
        (4, 0, "joint history incomplete: no joint samples from sim:// (robot moved? unknown)"),
    ]
    for scan_id, still, reason in rows:
        c.execute(
            "INSERT INTO scans (id, series_uid, folder, arrived_at, status, updated_at) "
            "VALUES (?, ?, '/w', '2026-01-01', 'complete', '2026-01-01')",
            (scan_id, f"1.2.{scan_id}"),
        )
        c.execute(
            "INSERT INTO joint_snapshots (scan_id, captured_at, link_url, link_state, joints_json, still, "
            "window_s, stillness_reason) VALUES (?, '2026-01-01', 'sim://', 'connected', ?, ?, 2.0, ?)",
            (scan_id, "[0, 0.1, 0.2, 0.3, 0.4, 0.5]", still, reason),
        )
    c.close()


def test_migration_10_backfills_the_verdict_of_old_rows_and_the_gate_reads_it(tmp_path: Path) -> None:
    p = tmp_path / "old.sqlite3"
    _schema_9_with_old_snapshots(p)
    db = Database.open(p)
    try:
        assert db.schema_version == len(MIGRATIONS)
        stored = dict(db._conn.query("SELECT scan_id, verdict FROM joint_snapshots ORDER BY scan_id"))
        assert stored == {1: "still", 2: "moved", 3: "incomplete", 4: "incomplete"}
        scans = {i: db.scans.get(i) for i in stored}
        assert {i: s.snapshot.verdict for i, s in scans.items() if s and s.snapshot} == stored
        assert check_capture(scans[1], 2.0)[1] == JOINTS  # type: ignore[arg-type]
        with pytest.raises(RobotMovedError):
            check_capture(scans[2], 2.0)  # type: ignore[arg-type]
        for i in (3, 4):
            with pytest.raises(JointHistoryIncompleteError):
                check_capture(scans[i], 2.0)  # type: ignore[arg-type]
        with pytest.raises(sqlite3.IntegrityError), db._conn.transaction() as c:
            c.execute("UPDATE joint_snapshots SET verdict = 'probably' WHERE scan_id = 1")
    finally:
        db.close()


def test_an_unknown_verdict_is_refused_not_guessed() -> None:
    assert stillness_verdict("moved") == "moved"
    with pytest.raises(ValueError, match=r"unknown stillness verdict 'Still'.*still, moved, incomplete"):
        stillness_verdict("Still")
