"""service/store: migrations, transactions, dedup, typed records, current pointer survives a reopen."""

from __future__ import annotations

import sqlite3
from collections.abc import Iterator
from dataclasses import replace
from pathlib import Path
from typing import Any

import pytest

from registration.errors import ConfigError
from service.http.api.models import registration_out, scan_out, verification_out
from service.records import (
    JointSnapshot,
    NewScan,
    RegistrationFigures,
    RegistrationRecord,
    ScanGeometry,
    SphereError,
    SphereMatch,
    VerificationFigures,
    VerificationRecord,
)
from service.store import MIGRATIONS, Database
from service.store.integrity import APPLICATION_ID

IDENTITY = ((1.0, 0.0, 0.0, 0.0), (0.0, 1.0, 0.0, 0.0), (0.0, 0.0, 1.0, 0.0), (0.0, 0.0, 0.0, 1.0))


@pytest.fixture
def db(tmp_path: Path) -> Iterator[Database]:
    d = Database.open(tmp_path / "data" / "x.sqlite3")
    yield d
    d.close()


SNAP = JointSnapshot(
    link_url="simple-message://127.0.0.1:1",
    link_state="connected",
    verdict="still",
    window_s=2.0,
    joints_rad=(0.0, 0.1, 0.2, 0.3, 0.4, 0.5),
    joints_received_at="2025-01-01T00:00:00+00:00",
)

FIGURES = RegistrationFigures(
    fle_mm=0.12,
    n_expected=28,
    n_detected=27,
    n_matched=26,
    symmetry_margin=12,
    rotation_det=1.0,
    predicted_tre_mm=(0.05, 0.06),
    targets_image_mm=((1.0, 2.0, 3.0), (4.0, 5.0, 6.0)),
    targets_source="request",
    spheres=(SphereMatch(sphere="+x-r0c0", robot_index=0, image_index=3, residual_mm=0.04),),
    provenance={"series_uid": "1.2.3"},
    timings_s={"load_s": 0.5},
)


def reg(status: Any = "accepted", **kw: Any) -> RegistrationRecord:
    return RegistrationRecord(
        created_at="2025-01-01T00:00:01+00:00",
        status=status,
        config_hash="abc",
        software_version="0.1.0",
        image_from_robot=IDENTITY,
        **kw,
    )


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
    c.execute(f"PRAGMA application_id = {APPLICATION_ID}")  # an oarmreg database from a newer release
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
    sid, created = db.scans.upsert(
        NewScan(series_uid="1.2.3", folder="/a", status="complete", snapshot=SNAP, n_slices=5)
    )
    assert created
    sid2, created2 = db.scans.upsert(
        NewScan(series_uid="1.2.3", folder="/b", status="complete", snapshot=SNAP)
    )
    assert (sid2, created2) == (sid, False)
    s = db.scans.get(sid)
    assert s is not None and s.folder == "/a" and s.seen_count == 2 and s.n_slices == 5
    assert s.snapshot is not None and s.snapshot.joints_rad == SNAP.joints_rad and s.snapshot.still
    assert len(db.scans.list()) == 1 and db.scans.has_complete("1.2.3")


def test_scan_geometry_and_snapshot_round_trip_into_the_api_model(db: Database) -> None:
    geom = ScanGeometry(
        image_from_voxel=((0.5, 0.0, 0.0, -10.0), (0.0, 0.5, 0.0, -20.0), (0.0, 0.0, 1.0, 5.0), IDENTITY[3]),
        spacing_mm=(0.5, 0.5, 1.0),
        shape_kji=(96, 128, 128),
    )
    sid, _ = db.scans.upsert(
        NewScan(series_uid="g", folder="/g", status="complete", geometry=geom, snapshot=SNAP)
    )
    s = db.scans.get(sid)
    assert (
        s is not None
        and s.geometry == geom
        and s.snapshot == replace(SNAP, captured_at=s.snapshot.captured_at)
    )
    out = scan_out(s).model_dump()
    assert out["image_from_voxel"][0] == [0.5, 0.0, 0.0, -10.0] and out["spacing_mm"] == [0.5, 0.5, 1.0]
    assert out["joints"]["joints_rad"] == list(SNAP.joints_rad) and out["joints"]["still"] is True
    bare = scan_out(db.scans.get(db.scans.upsert(NewScan(series_uid="b", folder="/b", status="invalid"))[0]))  # type: ignore[arg-type]
    assert bare.image_from_voxel is None and bare.joints is None


def test_invalid_scan_is_replaced_by_complete_reexport(db: Database) -> None:
    sid, _ = db.scans.upsert(NewScan(series_uid="9", folder="/a", status="invalid", reason="missing slice"))
    assert not db.scans.has_complete("9") and db.scans.latest_complete() is None
    sid2, created = db.scans.upsert(NewScan(series_uid="9", folder="/b", status="complete", snapshot=SNAP))
    assert sid2 == sid and created
    s = db.scans.get(sid)
    assert s is not None and s.status == "complete" and s.reason == "" and s.folder == "/b" and s.snapshot


def test_current_registration_pointer_and_refusals(tmp_path: Path) -> None:
    p = tmp_path / "x.sqlite3"
    d = Database.open(p)
    a = d.registrations.insert(reg(fre_mm=0.1), make_current=True)
    r = d.registrations.insert(reg("refused", reason="robot moved"), make_current=False)
    with pytest.raises(ValueError, match="accepted"):
        d.registrations.insert(reg("refused"), make_current=True)
    assert d.registrations.current_id() == a
    regs = {x.id: x for x in d.registrations.list()}
    assert regs[a].is_current and not regs[r].is_current and regs[r].reason == "robot moved"
    d.close()
    d2 = Database.open(p)  # a restart restores the current registration
    cur = d2.registrations.current()
    assert cur is not None and cur.id == a and cur.fre_mm == 0.1 and cur.image_from_robot == IDENTITY
    b = d2.registrations.insert(reg(), make_current=True)
    assert d2.registrations.current_id() == b
    d2.close()


def test_registration_figures_round_trip_into_the_api_model(db: Database) -> None:
    rid = db.registrations.insert(
        reg(fre_mm=0.1, figures=FIGURES, targets_image_mm=((9.0, 9.0, 9.0),), joints_rad=(0.1,) * 6),
        make_current=True,
    )
    stored = db.registrations.get(rid)
    assert stored is not None and stored.figures == FIGURES and stored.targets_image_mm == ((9.0, 9.0, 9.0),)
    out = registration_out(stored).model_dump()
    assert out["id"] == rid and out["is_current"] and out["fle_mm"] == 0.12 and out["n_matched"] == 26
    # the API reports the figures' targets (where the TRE was predicted), not the raw request field
    assert out["targets_image_mm"] == [[1.0, 2.0, 3.0], [4.0, 5.0, 6.0]]
    assert out["spheres"] == [{"sphere": "+x-r0c0", "robot_index": 0, "image_index": 3, "residual_mm": 0.04}]
    assert out["provenance"] == {"series_uid": "1.2.3"} and out["timings_s"] == {"load_s": 0.5}
    assert "figures" not in out
    refused = registration_out(replace(reg("refused", reason="moved"), id=7))
    assert refused.spheres == [] and refused.fle_mm is None and refused.targets_image_mm == []


def test_failed_transaction_leaves_nothing_behind(db: Database) -> None:
    with pytest.raises(sqlite3.IntegrityError):
        # a snapshot missing a NOT NULL value fails after the scan row was inserted: both roll back
        bad = replace(SNAP, link_url=None)  # type: ignore[arg-type]
        db.scans.upsert(NewScan(series_uid="x", folder="/a", status="complete", snapshot=bad))
    assert db.scans.list() == [] and db.counts()["scans"] == 0
    with pytest.raises(sqlite3.IntegrityError):
        db.registrations.insert(reg(status="weird"), make_current=False)
    assert db.counts()["registrations"] == 0 and db.registrations.current() is None


def test_verification_round_trip(db: Database) -> None:
    sid, _ = db.scans.upsert(NewScan(series_uid="s", folder="/a", status="complete"))
    rid = db.registrations.insert(reg(scan_id=sid), make_current=True)
    figures = VerificationFigures(
        errors=(SphereError(sphere="+y-r1c1", robot_index=4, error_mm=0.2),),
        n_expected=28,
        n_detected=28,
        n_matched=1,
        max_verification_error_mm=0.5,
    )
    record = VerificationRecord(
        created_at="2025-01-01T00:00:02+00:00",
        registration_id=rid,
        scan_id=sid,
        series_uid="s",
        passed=True,
        mean_mm=0.1,
        rms_mm=0.11,
        max_mm=0.2,
        figures=figures,
        config_hash="abc",
        software_version="0.1.0",
    )
    vid = db.verifications.insert(record)
    assert verification_out(replace(record, id=vid)).histogram_url is None
    db.verifications.set_histogram(vid, "/tmp/h.png")
    v = db.verifications.get(vid)
    assert v is not None and v == replace(record, id=vid, histogram_path="/tmp/h.png")
    out = verification_out(v).model_dump()
    assert out["histogram_url"] == f"/verifications/{vid}/histogram.png" and "histogram_path" not in out
    assert (
        out["errors"] == [{"sphere": "+y-r1c1", "robot_index": 4, "error_mm": 0.2}] and out["n_matched"] == 1
    )
    assert db.verifications.get(vid + 1) is None
