"""The scan lifecycle's pieces (issue 19): the table rebuild of migration 7, content diffs, the offer
tally, retention of ``dicom-intake/`` and its quota problem, the exporter's ImagesInAcquisition."""

from __future__ import annotations

import sqlite3
from collections import Counter
from datetime import UTC, datetime, timedelta
from pathlib import Path

import pytest

from service.intake.retention import quota_problem, run_retention
from service.intake.scan_lifecycle import OfferTally, diff, hash_files, rehash
from service.records import NewScan, RegistrationRecord
from service.store import Database
from service.store.migrations import MIGRATIONS, SCAN_LIFECYCLE_MIGRATION
from tests.helpers.old_schema import database_before

IDENTITY = ((1.0, 0.0, 0.0, 0.0), (0.0, 1.0, 0.0, 0.0), (0.0, 0.0, 1.0, 0.0), (0.0, 0.0, 0.0, 1.0))


def _schema_before_issue_19(path: Path) -> None:
    """A database as the release before issue 19 left it: one scan with its joint snapshot, an
    accepted registration of it, current."""
    c = database_before(path, SCAN_LIFECYCLE_MIGRATION)
    c.execute(
        "INSERT INTO scans (id, series_uid, folder, arrived_at, status, updated_at, reopened_count) "
        "VALUES (1, '1.2.3', '/w/a', '2026-01-01', 'complete', '2026-01-01', 2)"
    )
    c.execute(
        "INSERT INTO joint_snapshots (scan_id, captured_at, link_url, link_state, still, window_s) "
        "VALUES (1, '2026-01-01', 'sim://', 'connected', 1, 1.0)"
    )
    c.execute(
        "INSERT INTO registrations (id, created_at, scan_id, status, config_hash, software_version) "
        "VALUES (1, '2026-01-01', 1, 'accepted', 'x', '0')"
    )
    c.execute("INSERT INTO current_registration VALUES (1, 1, '2026-01-01')")
    c.close()


def test_migration_7_rebuilds_scans_keeping_every_row_and_reference(tmp_path: Path) -> None:
    p = tmp_path / "db.sqlite3"
    _schema_before_issue_19(p)
    db = Database.open(p)
    try:
        assert db.schema_version == len(MIGRATIONS)
        scan = db.scans.get(1)
        assert scan is not None and scan.status == "complete" and scan.snapshot is not None  # not cascaded
        assert db.registrations.current_id() == 1
        assert db._conn.query("PRAGMA foreign_key_check") == []
        assert db._conn.query("PRAGMA foreign_keys")[0][0] == 1  # back on after the rebuild
        assert db._conn.query("SELECT reopened_count FROM scans")[0][0] == 2
        db.scans.set_status(1, "reopened", "instances added")  # the widened constraint
        with pytest.raises(sqlite3.IntegrityError), db._conn.transaction() as c:
            c.execute("UPDATE scans SET status = 'bogus' WHERE id = 1")
        assert [c[1:3] for c in db.scans.changes(1)] == [("complete", "reopened")]
    finally:
        db.close()


def test_diff_and_rehash_name_what_changed(tmp_path: Path) -> None:
    for name, data in (("a.dcm", b"a"), ("b.dcm", b"b"), ("c.dcm", b"c")):
        (tmp_path / name).write_bytes(data)
    before = hash_files(tmp_path.glob("*.dcm"))
    (tmp_path / "b.dcm").write_bytes(b"B")
    (tmp_path / "c.dcm").unlink()
    (tmp_path / "d.dcm").write_bytes(b"d")
    after = hash_files(tmp_path.glob("*.dcm"))
    change = diff(before, after)
    assert (change.added, change.replaced, change.removed) == (("d.dcm",), ("b.dcm",), ("c.dcm",))
    assert change.state == "replaced"
    assert "1 instance(s) added (d.dcm)" in change.describe()
    again = rehash(tmp_path, before)
    assert (again.replaced, again.removed) == (("b.dcm",), ("c.dcm",))
    assert not diff(after, after).changed
    assert diff(before, {**before, "z.dcm": ("0", 1)}).state == "reopened"


def test_offer_tally_names_how_many_and_why() -> None:
    t = OfferTally()
    for _ in range(79):
        t.add_stored()
    for _ in range(17):
        t.add_failed("0xA900 Modality is 'OT'")
    assert "17 of the 96 instance(s)" in t.problem("1.2") and "17 × 0xA900" in t.problem("1.2")
    assert OfferTally(3, 3, Counter()).problem("1.2") == ""


def _scan(db: Database, folder: Path, uid: str, arrived: datetime, n_bytes: int) -> int:
    folder.mkdir(parents=True)
    (folder / "CT1.dcm").write_bytes(b"\0" * n_bytes)
    scan_id, _ = db.scans.upsert(
        NewScan(series_uid=uid, folder=str(folder), status="complete", arrived_at=arrived.isoformat())
    )
    return scan_id


def test_retention_covers_the_cstore_intake_and_says_when_the_quota_cannot_be_kept(tmp_path: Path) -> None:
    now = datetime(2026, 6, 1, tzinfo=UTC)
    watch, intake = tmp_path / "watch", tmp_path / "data" / "dicom-intake"
    db = Database.open(tmp_path / "data" / "db.sqlite3")
    try:
        old = _scan(db, intake / "1.9" / "1.9.1", "1.9.1", now - timedelta(days=3), 600_000)
        kept = _scan(db, intake / "1.9" / "1.9.2", "1.9.2", now - timedelta(days=4), 600_000)
        db.registrations.insert(
            RegistrationRecord(created_at=now.isoformat(), status="accepted", config_hash="x",
                               software_version="0", image_from_robot=IDENTITY, scan_id=kept),
            make_current=True,
        )  # fmt: skip
        done = run_retention(db, watch, lambda event: None, max_age_days=None, max_disk_mb=0.5, now=now,
                             extra_roots=(intake,))  # fmt: skip
        assert [d.scan_ids for d in done] == [(old,)]  # the current registration's scan is protected
        assert not (intake / "1.9" / "1.9.1").exists() and (intake / "1.9" / "1.9.2").exists()
        assert db.scans.get(old).status == "complete"  # type: ignore[union-attr]  # not a content change
        problem = quota_problem(db, watch, max_disk_mb=0.5, extra_roots=(intake,))
        assert problem is not None and "retention cannot keep the quota" in problem and "0.6 MB" in problem
        assert quota_problem(db, watch, max_disk_mb=1.0, extra_roots=(intake,)) is None
        assert intake.is_dir()  # the root itself is never deleted
    finally:
        db.close()


@pytest.mark.parametrize("announce", [False, True, 7])
def test_exporter_writes_images_in_acquisition_and_the_loader_holds_it(
    tmp_path: Path, announce: bool | int
) -> None:
    import numpy as np
    import pydicom

    from mocks.oarm.dicom_export import write_dicom_series
    from mocks.oarm.simulator import AcquisitionSettings, SimulatedScan
    from registration.dicom import load_series
    from registration.errors import DicomSeriesError

    settings = AcquisitionSettings.preset("small", rows=16, columns=16, n_slices=6)
    scan = SimulatedScan(
        hu=np.zeros((6, 16, 16), dtype=np.int16), image_from_voxel=settings.image_from_voxel(),
        image_from_phantom=np.eye(4), spheres_image_mm=np.zeros((0, 3)),
        sphere_indices=np.zeros(0, dtype=np.int64), settings=settings,
    )  # fmt: skip
    res = write_dicom_series(scan, tmp_path, write_truth=False, images_in_acquisition=announce)
    ds = pydicom.dcmread(res.paths[0])
    if announce is False:
        assert "ImagesInAcquisition" not in ds
        assert load_series(tmp_path).shape[0] == 6
    elif announce is True:
        assert ds.ImagesInAcquisition == 6 and load_series(tmp_path).shape[0] == 6
    else:  # announces one more than was written: an unfinished export, refused by the count rule
        assert ds.ImagesInAcquisition == 7
        with pytest.raises(DicomSeriesError, match="ImagesInAcquisition"):
            load_series(tmp_path)
