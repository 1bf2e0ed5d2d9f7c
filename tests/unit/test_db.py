"""service/db.py: migrations, transactions, dedup, current pointer survives a reopen."""

from __future__ import annotations

import sqlite3
from pathlib import Path
from typing import Any

import pytest
from service.db import MIGRATIONS, Database

from registration.errors import ConfigError


@pytest.fixture
def db(tmp_path: Path) -> Any:
    d = Database.open(tmp_path / "data" / "x.sqlite3")
    yield d
    d.close()


SNAP = {
    "link_url": "simple-message://127.0.0.1:1",
    "link_state": "connected",
    "still": True,
    "window_s": 2.0,
    "joints_rad": [0.0, 0.1, 0.2, 0.3, 0.4, 0.5],
    "joints_received_at": "2025-01-01T00:00:00+00:00",
}


def reg(status: str = "accepted", **kw: Any) -> dict[str, Any]:
    return {
        "status": status,
        "config_hash": "abc",
        "software_version": "0.1.0",
        "scan_id": None,
        "image_from_robot": [[1.0, 0, 0, 0], [0, 1.0, 0, 0], [0, 0, 1.0, 0], [0, 0, 0, 1.0]],
        **kw,
    }


def test_open_creates_folder_wal_and_schema(db: Database) -> None:
    assert db.path.is_file() and db.schema_version == len(MIGRATIONS)
    mode = sqlite3.connect(db.path).execute("PRAGMA journal_mode").fetchone()[0]
    assert mode == "wal"


def test_reopen_does_not_migrate_again(tmp_path: Path) -> None:
    p = tmp_path / "x.sqlite3"
    Database.open(p).close()
    d = Database.open(p)
    assert d.schema_version == len(MIGRATIONS)
    d.close()


def test_newer_schema_is_refused(tmp_path: Path) -> None:
    p = tmp_path / "x.sqlite3"
    c = sqlite3.connect(p)
    c.execute(f"PRAGMA user_version = {len(MIGRATIONS) + 1}")
    c.close()
    with pytest.raises(ConfigError, match="newer than this software"):
        Database.open(p)


def test_not_a_database_is_refused(tmp_path: Path) -> None:
    p = tmp_path / "x.sqlite3"
    p.write_bytes(b"this is not sqlite" * 100)
    with pytest.raises(ConfigError, match="not a usable oarmreg database"):
        Database.open(p)


def test_scan_dedup_by_uid(db: Database) -> None:
    sid, created = db.upsert_scan(
        series_uid="1.2.3", folder="/a", status="complete", snapshot=SNAP, n_slices=5
    )
    assert created
    sid2, created2 = db.upsert_scan(series_uid="1.2.3", folder="/b", status="complete", snapshot=SNAP)
    assert (sid2, created2) == (sid, False)
    s = db.get_scan(sid)
    assert s is not None and s.folder == "/a" and s.seen_count == 2 and s.n_slices == 5
    assert s.snapshot is not None and s.snapshot["joints_rad"] == SNAP["joints_rad"] and s.snapshot["still"]
    assert len(db.list_scans()) == 1 and db.has_complete_scan("1.2.3")


def test_invalid_scan_is_replaced_by_complete_reexport(db: Database) -> None:
    sid, _ = db.upsert_scan(series_uid="9", folder="/a", status="invalid", reason="missing slice")
    assert not db.has_complete_scan("9") and db.latest_complete_scan() is None
    sid2, created = db.upsert_scan(series_uid="9", folder="/b", status="complete", snapshot=SNAP)
    assert sid2 == sid and created
    s = db.get_scan(sid)
    assert s is not None and s.status == "complete" and s.reason == "" and s.folder == "/b" and s.snapshot


def test_current_registration_pointer_and_refusals(tmp_path: Path) -> None:
    p = tmp_path / "x.sqlite3"
    d = Database.open(p)
    a = d.insert_registration(reg(fre_mm=0.1), make_current=True)
    r = d.insert_registration(reg("refused", reason="robot moved"), make_current=False)
    with pytest.raises(ValueError, match="accepted"):
        d.insert_registration(reg("refused"), make_current=True)
    assert d.current_registration_id() == a
    regs = {x["id"]: x for x in d.list_registrations()}
    assert regs[a]["is_current"] and not regs[r]["is_current"] and regs[r]["reason"] == "robot moved"
    d.close()
    d2 = Database.open(p)  # a restart restores the current registration
    cur = d2.current_registration()
    assert (
        cur is not None
        and cur["id"] == a
        and cur["fre_mm"] == 0.1
        and cur["image_from_robot"][3] == [0, 0, 0, 1]
    )
    b = d2.insert_registration(reg(), make_current=True)
    assert d2.current_registration_id() == b
    d2.close()


def test_failed_transaction_leaves_nothing_behind(db: Database) -> None:
    with pytest.raises(sqlite3.IntegrityError):
        # a snapshot missing a NOT NULL value fails after the scan row was inserted: both roll back
        db.upsert_scan(series_uid="x", folder="/a", status="complete", snapshot={**SNAP, "link_url": None})
    assert db.list_scans() == [] and db.counts()["scans"] == 0
    with pytest.raises(sqlite3.IntegrityError):
        db.insert_registration(reg(status="weird"), make_current=False)
    assert db.counts()["registrations"] == 0 and db.current_registration() is None


def test_verification_round_trip(db: Database) -> None:
    sid, _ = db.upsert_scan(series_uid="s", folder="/a", status="complete")
    rid = db.insert_registration(reg(scan_id=sid), make_current=True)
    vid = db.insert_verification(
        {
            "registration_id": rid,
            "scan_id": sid,
            "series_uid": "s",
            "passed": True,
            "mean_mm": 0.1,
            "rms_mm": 0.11,
            "max_mm": 0.2,
            "figures": {"errors": []},
            "config_hash": "abc",
            "software_version": "0.1.0",
        }
    )
    db.set_verification_histogram(vid, "/tmp/h.png")
    v = db.get_verification(vid)
    assert (
        v is not None and v["passed"] is True and v["histogram_path"] == "/tmp/h.png" and v["max_mm"] == 0.2
    )
    assert db.get_verification(vid + 1) is None
