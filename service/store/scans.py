"""The ``scans`` and ``joint_snapshots`` tables."""

from __future__ import annotations

import sqlite3
from typing import cast

from service.records import (
    JointSnapshot,
    NewScan,
    ScanGeometry,
    ScanRecord,
    ScanStatus,
    floats,
    stillness_verdict,
)
from service.store.base import Connection, dumps, loads, utc_now

_SCAN_COLUMNS = (
    "frame_of_reference_uid, folder, arrived_at, n_files, n_slices, rows, columns, geometry_json, "
    "status, reason, updated_at"
)


class ScanStore:
    """Series the watcher recorded, each with the joint snapshot taken at its arrival."""

    def __init__(self, db: Connection) -> None:
        self._db = db

    def upsert(self, scan: NewScan, *, reopen: bool = False) -> tuple[int, bool]:
        """Record a series; returns ``(scan_id, created)``.

        A series UID seen before with status ``complete`` is a re-export: only
        ``seen_count`` grows and ``created`` is False.  One seen before as ``invalid``
        is replaced by the new record (and its new joint snapshot).  ``reopen=True`` replaces a
        ``complete`` one too (new instances of a recorded series arrived over C-STORE); the id stays.
        """
        now = utc_now()
        with self._db.transaction() as c:
            row = c.execute(
                "SELECT id, status FROM scans WHERE series_uid = ?", (scan.series_uid,)
            ).fetchone()
            if row is not None and row["status"] == "complete" and not reopen:
                c.execute(
                    "UPDATE scans SET seen_count = seen_count + 1, updated_at = ? WHERE id = ?",
                    (now, row["id"]),
                )
                return int(row["id"]), False
            values = _scan_values(scan, now)
            if row is None:
                cur = c.execute(
                    f"INSERT INTO scans ({_SCAN_COLUMNS}, series_uid) "
                    "VALUES (?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?)",
                    (*values, scan.series_uid),
                )
                scan_id = int(cur.lastrowid or 0)
            else:
                scan_id = int(row["id"])
                assignments = ", ".join(f"{col.strip()}=?" for col in _SCAN_COLUMNS.split(","))
                c.execute(
                    f"UPDATE scans SET {assignments}, seen_count = seen_count + 1 WHERE id = ?",
                    (*values, scan_id),
                )
                c.execute("DELETE FROM joint_snapshots WHERE scan_id = ?", (scan_id,))
            if scan.snapshot is not None:
                _insert_snapshot(c, scan_id, scan.snapshot, now)
            return scan_id, True

    def reopen(self, scan: NewScan) -> tuple[int, int]:
        """Replace the record of a series recorded before (late slices arrived: it was incomplete).

        The row keeps its id (registrations point to it), takes the new slice count, geometry, status
        and joint snapshot, and counts the reopening.  Returns ``(scan_id, previous n_slices)``.
        A series not recorded yet is inserted as by :meth:`upsert`.
        """
        now = utc_now()
        with self._db.transaction() as c:
            row = c.execute(
                "SELECT id, n_slices FROM scans WHERE series_uid = ?", (scan.series_uid,)
            ).fetchone()
            if row is None:
                values = _scan_values(scan, now)
                cur = c.execute(
                    f"INSERT INTO scans ({_SCAN_COLUMNS}, series_uid) "
                    "VALUES (?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?)",
                    (*values, scan.series_uid),
                )
                scan_id, before = int(cur.lastrowid or 0), 0
            else:
                scan_id, before = int(row["id"]), int(row["n_slices"])
                assignments = ", ".join(f"{col.strip()}=?" for col in _SCAN_COLUMNS.split(","))
                c.execute(
                    f"UPDATE scans SET {assignments}, reopened_count = reopened_count + 1 WHERE id = ?",
                    (*_scan_values(scan, now), scan_id),
                )
                c.execute("DELETE FROM joint_snapshots WHERE scan_id = ?", (scan_id,))
            if scan.snapshot is not None:
                _insert_snapshot(c, scan_id, scan.snapshot, now)
            return scan_id, before

    def record(
        self, scan: NewScan, *, files: dict[str, tuple[str, int]] | None = None, why: str = ""
    ) -> tuple[int, str | None]:
        """Write the verdict on a series (:class:`service.intake.scan_lifecycle.ScanLifecycle`): insert its
        row
        or replace every column of it (same id), its joint snapshot and, when given, its instances'
        hashes (``name → (sha256, bytes)``); a state change is logged in ``scan_changes`` with ``why``
        (the record's reason when empty).  Returns ``(scan_id, previous status or None)``."""
        now = utc_now()
        with self._db.transaction() as c:
            row = c.execute(
                "SELECT id, status FROM scans WHERE series_uid = ?", (scan.series_uid,)
            ).fetchone()
            values = _scan_values(scan, now)
            if row is None:
                cur = c.execute(
                    f"INSERT INTO scans ({_SCAN_COLUMNS}, series_uid) "
                    "VALUES (?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?)",
                    (*values, scan.series_uid),
                )
                scan_id, before = int(cur.lastrowid or 0), None
            else:
                scan_id, before = int(row["id"]), str(row["status"])
                assignments = ", ".join(f"{col.strip()}=?" for col in _SCAN_COLUMNS.split(","))
                bump = ", reopened_count = reopened_count + 1" if before in ("reopened", "replaced") else ""
                c.execute(
                    f"UPDATE scans SET {assignments}, seen_count = seen_count + 1{bump}, "
                    "files_deleted_at = NULL, files_deleted_reason = '' WHERE id = ?",
                    (*values, scan_id),
                )
                c.execute("DELETE FROM joint_snapshots WHERE scan_id = ?", (scan_id,))
            if scan.snapshot is not None:
                _insert_snapshot(c, scan_id, scan.snapshot, now)
            if files is not None:
                c.execute("DELETE FROM scan_files WHERE scan_id = ?", (scan_id,))
                c.executemany(
                    "INSERT INTO scan_files (scan_id, name, sha256, bytes) VALUES (?, ?, ?, ?)",
                    [(scan_id, name, sha, n) for name, (sha, n) in sorted(files.items())],
                )
            if before != scan.status:
                _log_change(c, scan_id, before or "", scan.status, why or scan.reason or "recorded", now)
            return scan_id, before

    def set_status(self, scan_id: int, status: ScanStatus, reason: str) -> str:
        """Move one scan to ``status`` with ``reason`` (logged in ``scan_changes``); its previous status."""
        now = utc_now()
        with self._db.transaction() as c:
            row = c.execute("SELECT status FROM scans WHERE id = ?", (scan_id,)).fetchone()
            if row is None:
                raise KeyError(scan_id)
            c.execute(
                "UPDATE scans SET status = ?, reason = ?, updated_at = ? WHERE id = ?",
                (status, reason, now, scan_id),
            )
            _log_change(c, scan_id, str(row["status"]), status, reason, now)
            return str(row["status"])

    def start_receiving(self, series_uid: str, folder: str) -> int:
        """The row of a series whose first instance is arriving (status ``receiving``); its id.  A
        series recorded before keeps its row (its state is the lifecycle's to change)."""
        now = utc_now()
        with self._db.transaction() as c:
            row = c.execute("SELECT id FROM scans WHERE series_uid = ?", (series_uid,)).fetchone()
            if row is not None:
                return int(row["id"])
            cur = c.execute(
                "INSERT INTO scans (series_uid, folder, arrived_at, status, reason, updated_at) "
                "VALUES (?, ?, ?, 'receiving', '', ?)",
                (series_uid, folder, now, now),
            )
            scan_id = int(cur.lastrowid or 0)
            _log_change(c, scan_id, "", "receiving", "first instance received", now)
            return scan_id

    def files(self, scan_id: int) -> dict[str, tuple[str, int]]:
        """``name → (sha256, bytes)`` of the instances recorded with the scan (empty: none recorded)."""
        rows = self._db.query("SELECT name, sha256, bytes FROM scan_files WHERE scan_id = ?", (scan_id,))
        return {str(r[0]): (str(r[1]), int(r[2])) for r in rows}

    def changes(self, scan_id: int) -> list[tuple[str, str, str, str]]:
        """``(at, from, to, reason)`` of every state change of the scan, oldest first."""
        rows = self._db.query(
            "SELECT at, from_status, to_status, reason FROM scan_changes WHERE scan_id = ? ORDER BY id",
            (scan_id,),
        )
        return [(str(r[0]), str(r[1]), str(r[2]), str(r[3])) for r in rows]

    def in_status(self, *statuses: ScanStatus) -> list[ScanRecord]:
        marks = ", ".join("?" for _ in statuses)
        rows = self._db.query(f"SELECT * FROM scans WHERE status IN ({marks}) ORDER BY id", tuple(statuses))
        return [self._record(r) for r in rows]

    def recorded_content(self, series_uid: str) -> dict[str, tuple[str, int]] | None:
        """The instance hashes of the complete record of ``series_uid`` (None when there is none; an
        empty dict for a record made before hashes were kept)."""
        rows = self._db.query(
            "SELECT id FROM scans WHERE series_uid = ? AND status = 'complete'", (series_uid,)
        )
        return self.files(int(rows[0][0])) if rows else None

    def status_of(self, series_uid: str) -> tuple[int, str] | None:
        """``(id, status)`` of the series' record (one query: the SCP asks for every instance)."""
        rows = self._db.query("SELECT id, status FROM scans WHERE series_uid = ?", (series_uid,))
        return (int(rows[0][0]), str(rows[0][1])) if rows else None

    def recorded_slices(self, series_uid: str) -> int | None:
        """Slices of the complete record of ``series_uid`` (None when there is none)."""
        rows = self._db.query(
            "SELECT n_slices FROM scans WHERE series_uid = ? AND status = 'complete'", (series_uid,)
        )
        return int(rows[0][0]) if rows else None

    def mark_files_deleted(self, scan_id: int, folder: str, n_bytes: int, reason: str) -> None:
        """Record that the retention policy deleted a scan's files (the row and its history stay)."""
        now = utc_now()
        with self._db.transaction() as c:
            c.execute(
                "UPDATE scans SET files_deleted_at = ?, files_deleted_reason = ?, updated_at = ? "
                "WHERE id = ?",
                (now, reason, now, scan_id),
            )
            c.execute(
                "INSERT INTO retention_log (deleted_at, scan_id, folder, bytes, reason) "
                "VALUES (?, ?, ?, ?, ?)",
                (now, scan_id, folder, n_bytes, reason),
            )

    def with_files(self) -> list[tuple[int, str, str]]:
        """``(id, folder, arrived_at)`` of every scan whose files were not deleted yet, oldest first."""
        rows = self._db.query(
            "SELECT id, folder, arrived_at FROM scans WHERE files_deleted_at IS NULL ORDER BY arrived_at, id"
        )
        return [(int(r[0]), str(r[1]), str(r[2])) for r in rows]

    def stored_bytes(self) -> int:
        """Bytes of the recorded instances of every scan whose files were not deleted yet (the
        ``scan_files`` sizes: what retention's ``max_disk_mb`` is measured against, without a walk)."""
        rows = self._db.query(
            "SELECT COALESCE(SUM(f.bytes), 0) FROM scan_files f JOIN scans s ON s.id = f.scan_id "
            "WHERE s.files_deleted_at IS NULL"
        )
        return int(rows[0][0])

    def has_complete(self, series_uid: str) -> bool:
        rows = self._db.query(
            "SELECT 1 FROM scans WHERE series_uid = ? AND status = 'complete'", (series_uid,)
        )
        return bool(rows)

    def get(self, scan_id: int) -> ScanRecord | None:
        rows = self._db.query("SELECT * FROM scans WHERE id = ?", (scan_id,))
        return self._record(rows[0]) if rows else None

    def by_series_uid(self, series_uid: str) -> ScanRecord | None:
        rows = self._db.query("SELECT * FROM scans WHERE series_uid = ?", (series_uid,))
        return self._record(rows[0]) if rows else None

    def latest_complete(self) -> ScanRecord | None:
        rows = self._db.query("SELECT * FROM scans WHERE status = 'complete' ORDER BY id DESC LIMIT 1")
        return self._record(rows[0]) if rows else None

    def list(self, limit: int = 100, offset: int = 0) -> list[ScanRecord]:
        rows = self._db.query("SELECT * FROM scans ORDER BY id DESC LIMIT ? OFFSET ?", (limit, offset))
        return [self._record(r) for r in rows]

    def _record(self, r: sqlite3.Row) -> ScanRecord:
        snaps = self._db.query("SELECT * FROM joint_snapshots WHERE scan_id = ?", (r["id"],))
        geometry = loads(r["geometry_json"])
        return ScanRecord(
            id=int(r["id"]),
            series_uid=r["series_uid"],
            frame_of_reference_uid=r["frame_of_reference_uid"],
            folder=r["folder"],
            arrived_at=r["arrived_at"],
            n_files=int(r["n_files"]),
            n_slices=int(r["n_slices"]),
            rows=int(r["rows"]),
            columns=int(r["columns"]),
            geometry=None if geometry is None else ScanGeometry.from_json(geometry),
            status=cast(ScanStatus, r["status"]),
            reason=r["reason"],
            seen_count=int(r["seen_count"]),
            updated_at=r["updated_at"],
            snapshot=_snapshot(snaps[0]) if snaps else None,
        )


def _scan_values(scan: NewScan, now: str) -> tuple[object, ...]:
    """The values of :data:`_SCAN_COLUMNS`, in order."""
    return (
        scan.frame_of_reference_uid,
        scan.folder,
        scan.arrived_at or now,
        scan.n_files,
        scan.n_slices,
        scan.rows,
        scan.columns,
        dumps(None if scan.geometry is None else scan.geometry.to_json()),
        scan.status,
        scan.reason,
        now,
    )


def _log_change(c: sqlite3.Connection, scan_id: int, before: str, after: str, why: str, now: str) -> None:
    c.execute(
        "INSERT INTO scan_changes (scan_id, at, from_status, to_status, reason) VALUES (?, ?, ?, ?, ?)",
        (scan_id, now, before, after, why),
    )


def _insert_snapshot(c: sqlite3.Connection, scan_id: int, s: JointSnapshot, now: str) -> None:
    c.execute(
        "INSERT INTO joint_snapshots (scan_id, captured_at, link_url, link_state, link_reason, "
        "joints_json, joints_received_at, still, max_deviation_rad, covered_s, n_samples, window_s, "
        "stillness_reason, verdict) VALUES (?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?)",
        (
            scan_id,
            s.captured_at or now,
            s.link_url,
            s.link_state,
            s.link_reason,
            dumps(None if s.joints_rad is None else list(s.joints_rad)),
            s.joints_received_at,
            int(s.still),
            s.max_deviation_rad,
            s.covered_s,
            s.n_samples,
            float(s.window_s),
            s.stillness_reason,
            s.verdict,
        ),
    )


def _snapshot(s: sqlite3.Row) -> JointSnapshot:
    return JointSnapshot(
        captured_at=s["captured_at"],
        link_url=s["link_url"],
        link_state=s["link_state"],
        link_reason=s["link_reason"],
        joints_rad=floats(loads(s["joints_json"])),
        joints_received_at=s["joints_received_at"],
        verdict=stillness_verdict(s["verdict"]),
        max_deviation_rad=s["max_deviation_rad"],
        covered_s=s["covered_s"],
        n_samples=int(s["n_samples"]),
        window_s=float(s["window_s"]),
        stillness_reason=s["stillness_reason"],
    )
