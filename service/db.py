"""SQLite persistence (stdlib ``sqlite3``, WAL) for scans, joints, registrations, verifications.

Schema (``PRAGMA user_version`` = number of applied migrations):

``scans``
    one row per series UID (a re-export of the same UID updates nothing but ``seen_count``):
    folder, arrival time, slice count, geometry (``image_from_voxel``), status
    (``complete`` / ``invalid``) and the reason.
``joint_snapshots``
    joints captured at a scan's arrival and the stillness verdict over the window before it.
``registrations``
    every POST /register, accepted or refused: ``image_from_robot``, quality figures,
    provenance (series UID, joints and their timestamp, config hash, software version),
    status ``accepted`` / ``refused`` + reason.
``verifications``
    every POST /verify: per-sphere errors, mean / RMS / max, histogram path.
``current_registration``
    a single-row pointer to the registration the service serves.

Every write is one transaction (``BEGIN IMMEDIATE`` … ``COMMIT``); a failure rolls back,
so nothing already stored is lost or half-written.  One connection is shared by the
service's threads under a lock (``check_same_thread=False``); WAL keeps readers cheap.
"""

from __future__ import annotations

import json
import logging
import sqlite3
import threading
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

from registration.errors import ConfigError

log = logging.getLogger(__name__)

BUSY_TIMEOUT_S = 10.0
"""How long a write waits for another process holding the database (sqlite3 ``timeout``)."""

MIGRATIONS: tuple[str, ...] = (
    # 1: initial schema
    """
    CREATE TABLE scans (
        id INTEGER PRIMARY KEY,
        series_uid TEXT NOT NULL UNIQUE,
        frame_of_reference_uid TEXT NOT NULL DEFAULT '',
        folder TEXT NOT NULL,
        arrived_at TEXT NOT NULL,
        n_files INTEGER NOT NULL DEFAULT 0,
        n_slices INTEGER NOT NULL DEFAULT 0,
        rows INTEGER NOT NULL DEFAULT 0,
        columns INTEGER NOT NULL DEFAULT 0,
        geometry_json TEXT,
        status TEXT NOT NULL CHECK (status IN ('complete', 'invalid')),
        reason TEXT NOT NULL DEFAULT '',
        seen_count INTEGER NOT NULL DEFAULT 1,
        updated_at TEXT NOT NULL
    );
    CREATE TABLE joint_snapshots (
        id INTEGER PRIMARY KEY,
        scan_id INTEGER NOT NULL UNIQUE REFERENCES scans(id) ON DELETE CASCADE,
        captured_at TEXT NOT NULL,
        link_url TEXT NOT NULL,
        link_state TEXT NOT NULL,
        link_reason TEXT NOT NULL DEFAULT '',
        joints_json TEXT,
        joints_received_at TEXT,
        still INTEGER NOT NULL,
        max_deviation_rad REAL,
        covered_s REAL,
        n_samples INTEGER NOT NULL DEFAULT 0,
        window_s REAL NOT NULL,
        stillness_reason TEXT NOT NULL DEFAULT ''
    );
    CREATE TABLE registrations (
        id INTEGER PRIMARY KEY,
        created_at TEXT NOT NULL,
        scan_id INTEGER REFERENCES scans(id),
        series_uid TEXT NOT NULL DEFAULT '',
        status TEXT NOT NULL CHECK (status IN ('accepted', 'refused')),
        reason TEXT NOT NULL DEFAULT '',
        problem_title TEXT NOT NULL DEFAULT '',
        http_status INTEGER,
        image_from_robot_json TEXT,
        fre_mm REAL,
        figures_json TEXT,
        targets_image_mm_json TEXT,
        joints_json TEXT,
        joints_received_at TEXT,
        config_hash TEXT NOT NULL,
        software_version TEXT NOT NULL,
        duration_s REAL
    );
    CREATE INDEX registrations_scan ON registrations(scan_id);
    CREATE TABLE verifications (
        id INTEGER PRIMARY KEY,
        created_at TEXT NOT NULL,
        registration_id INTEGER NOT NULL REFERENCES registrations(id),
        scan_id INTEGER NOT NULL REFERENCES scans(id),
        series_uid TEXT NOT NULL,
        passed INTEGER NOT NULL,
        mean_mm REAL NOT NULL,
        rms_mm REAL NOT NULL,
        max_mm REAL NOT NULL,
        figures_json TEXT NOT NULL,
        histogram_path TEXT,
        config_hash TEXT NOT NULL,
        software_version TEXT NOT NULL
    );
    CREATE TABLE current_registration (
        singleton INTEGER PRIMARY KEY CHECK (singleton = 1),
        registration_id INTEGER NOT NULL REFERENCES registrations(id),
        set_at TEXT NOT NULL
    );
    """,
)


def utc_now() -> str:
    """ISO 8601 UTC timestamp with microseconds."""
    return datetime.now(UTC).isoformat()


def _loads(s: str | None) -> Any:
    return None if s is None else json.loads(s)


def _dumps(v: Any) -> str | None:
    return None if v is None else json.dumps(v)


@dataclass(frozen=True)
class ScanRow:
    id: int
    series_uid: str
    frame_of_reference_uid: str
    folder: str
    arrived_at: str
    n_files: int
    n_slices: int
    rows: int
    columns: int
    geometry: dict[str, Any] | None
    status: str
    reason: str
    seen_count: int
    updated_at: str
    snapshot: dict[str, Any] | None = None


class Database:
    """The service's store.  Thread-safe; open with :meth:`open`, close with :meth:`close`."""

    def __init__(self, conn: sqlite3.Connection, path: Path) -> None:
        self._conn = conn
        self.path = path
        self._lock = threading.RLock()

    # ---- lifecycle ------------------------------------------------------------------------

    @classmethod
    def open(cls, path: str | Path) -> Database:
        """Open (creating if needed) and migrate the database at ``path``.

        Raises
        ------
        ConfigError
            The folder cannot be created, the file is not a database, or it was written by a
            newer version of the software (``user_version`` above the known migrations).
        """
        p = Path(path)
        try:
            p.parent.mkdir(parents=True, exist_ok=True)
            conn = sqlite3.connect(p, timeout=BUSY_TIMEOUT_S, isolation_level=None, check_same_thread=False)
            conn.row_factory = sqlite3.Row
            conn.execute("PRAGMA journal_mode=WAL")
            conn.execute("PRAGMA foreign_keys=ON")
            conn.execute("PRAGMA synchronous=NORMAL")
        except sqlite3.DatabaseError as e:
            raise ConfigError(
                f"{p} is not a usable oarmreg database: {e}; move it away or fix data_dir"
            ) from None
        except (OSError, sqlite3.Error) as e:
            raise ConfigError(
                f"cannot open the database {p}: {e}; check data_dir and its permissions"
            ) from None
        db = cls(conn, p)
        try:
            db._migrate()
        except sqlite3.DatabaseError as e:
            conn.close()
            raise ConfigError(
                f"{p} is not a usable oarmreg database: {e}; move it away or fix data_dir"
            ) from None
        except ConfigError:
            conn.close()
            raise
        return db

    def close(self) -> None:
        with self._lock:
            self._conn.close()

    def _migrate(self) -> None:
        with self._lock:
            version = int(self._conn.execute("PRAGMA user_version").fetchone()[0])
            if version > len(MIGRATIONS):
                raise ConfigError(
                    f"{self.path}: schema version {version} is newer than this software knows "
                    f"({len(MIGRATIONS)}); upgrade oarmreg or use another data_dir"
                )
            for i in range(version, len(MIGRATIONS)):
                self._conn.execute("BEGIN IMMEDIATE")
                try:
                    for stmt in _split_sql(MIGRATIONS[i]):
                        self._conn.execute(stmt)
                    self._conn.execute(f"PRAGMA user_version = {i + 1}")
                    self._conn.execute("COMMIT")
                except BaseException:
                    self._conn.execute("ROLLBACK")
                    raise
                log.info("database %s: migrated to schema version %d", self.path, i + 1)

    @property
    def schema_version(self) -> int:
        with self._lock:
            return int(self._conn.execute("PRAGMA user_version").fetchone()[0])

    @contextmanager
    def transaction(self) -> Iterator[sqlite3.Connection]:
        """``BEGIN IMMEDIATE`` … ``COMMIT``; rolls back on any exception."""
        with self._lock:
            self._conn.execute("BEGIN IMMEDIATE")
            try:
                yield self._conn
            except BaseException:
                self._conn.execute("ROLLBACK")
                raise
            self._conn.execute("COMMIT")

    def _query(self, sql: str, args: tuple[Any, ...] = ()) -> list[sqlite3.Row]:
        with self._lock:
            return list(self._conn.execute(sql, args).fetchall())

    # ---- scans ----------------------------------------------------------------------------

    def upsert_scan(
        self,
        *,
        series_uid: str,
        folder: str,
        status: str,
        reason: str = "",
        frame_of_reference_uid: str = "",
        n_files: int = 0,
        n_slices: int = 0,
        rows: int = 0,
        columns: int = 0,
        geometry: dict[str, Any] | None = None,
        snapshot: dict[str, Any] | None = None,
        arrived_at: str | None = None,
    ) -> tuple[int, bool]:
        """Record a series; returns ``(scan_id, created)``.

        A series UID seen before with status ``complete`` is a re-export: only
        ``seen_count`` grows and ``created`` is False.  One seen before as ``invalid``
        is replaced by the new record (and its new joint snapshot).
        """
        now = utc_now()
        with self.transaction() as c:
            row = c.execute("SELECT id, status FROM scans WHERE series_uid = ?", (series_uid,)).fetchone()
            if row is not None and row["status"] == "complete":
                c.execute(
                    "UPDATE scans SET seen_count = seen_count + 1, updated_at = ? WHERE id = ?",
                    (now, row["id"]),
                )
                return int(row["id"]), False
            values = (
                frame_of_reference_uid,
                folder,
                arrived_at or now,
                n_files,
                n_slices,
                rows,
                columns,
                _dumps(geometry),
                status,
                reason,
                now,
            )
            if row is None:
                cur = c.execute(
                    "INSERT INTO scans (frame_of_reference_uid, folder, arrived_at, n_files, n_slices, rows, "
                    "columns, geometry_json, status, reason, updated_at, series_uid) "
                    "VALUES (?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?)",
                    (*values, series_uid),
                )
                scan_id = int(cur.lastrowid or 0)
            else:
                scan_id = int(row["id"])
                c.execute(
                    "UPDATE scans SET frame_of_reference_uid=?, folder=?, arrived_at=?, "
                    "n_files=?, n_slices=?, "
                    "rows=?, columns=?, geometry_json=?, status=?, reason=?, updated_at=?, "
                    "seen_count = seen_count + 1 WHERE id = ?",
                    (*values, scan_id),
                )
                c.execute("DELETE FROM joint_snapshots WHERE scan_id = ?", (scan_id,))
            if snapshot is not None:
                c.execute(
                    "INSERT INTO joint_snapshots (scan_id, captured_at, link_url, link_state, link_reason, "
                    "joints_json, joints_received_at, still, max_deviation_rad, covered_s, "
                    "n_samples, window_s, "
                    "stillness_reason) VALUES (?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?)",
                    (
                        scan_id,
                        snapshot.get("captured_at", now),
                        snapshot["link_url"],
                        snapshot["link_state"],
                        snapshot.get("link_reason", ""),
                        _dumps(snapshot.get("joints_rad")),
                        snapshot.get("joints_received_at"),
                        int(bool(snapshot["still"])),
                        snapshot.get("max_deviation_rad"),
                        snapshot.get("covered_s"),
                        int(snapshot.get("n_samples", 0)),
                        float(snapshot["window_s"]),
                        snapshot.get("stillness_reason", ""),
                    ),
                )
            return scan_id, True

    def has_complete_scan(self, series_uid: str) -> bool:
        rows = self._query("SELECT 1 FROM scans WHERE series_uid = ? AND status = 'complete'", (series_uid,))
        return bool(rows)

    def _scan_from_row(self, r: sqlite3.Row) -> ScanRow:
        snaps = self._query("SELECT * FROM joint_snapshots WHERE scan_id = ?", (r["id"],))
        snap = None
        if snaps:
            s = snaps[0]
            snap = {
                "captured_at": s["captured_at"],
                "link_url": s["link_url"],
                "link_state": s["link_state"],
                "link_reason": s["link_reason"],
                "joints_rad": _loads(s["joints_json"]),
                "joints_received_at": s["joints_received_at"],
                "still": bool(s["still"]),
                "max_deviation_rad": s["max_deviation_rad"],
                "covered_s": s["covered_s"],
                "n_samples": s["n_samples"],
                "window_s": s["window_s"],
                "stillness_reason": s["stillness_reason"],
            }
        return ScanRow(
            id=int(r["id"]),
            series_uid=r["series_uid"],
            frame_of_reference_uid=r["frame_of_reference_uid"],
            folder=r["folder"],
            arrived_at=r["arrived_at"],
            n_files=int(r["n_files"]),
            n_slices=int(r["n_slices"]),
            rows=int(r["rows"]),
            columns=int(r["columns"]),
            geometry=_loads(r["geometry_json"]),
            status=r["status"],
            reason=r["reason"],
            seen_count=int(r["seen_count"]),
            updated_at=r["updated_at"],
            snapshot=snap,
        )

    def get_scan(self, scan_id: int) -> ScanRow | None:
        rows = self._query("SELECT * FROM scans WHERE id = ?", (scan_id,))
        return self._scan_from_row(rows[0]) if rows else None

    def latest_complete_scan(self) -> ScanRow | None:
        rows = self._query("SELECT * FROM scans WHERE status = 'complete' ORDER BY id DESC LIMIT 1")
        return self._scan_from_row(rows[0]) if rows else None

    def list_scans(self, limit: int = 100, offset: int = 0) -> list[ScanRow]:
        rows = self._query("SELECT * FROM scans ORDER BY id DESC LIMIT ? OFFSET ?", (limit, offset))
        return [self._scan_from_row(r) for r in rows]

    # ---- registrations --------------------------------------------------------------------

    def insert_registration(self, record: dict[str, Any], *, make_current: bool) -> int:
        """Store a registration (accepted or refused); if ``make_current``, point to it (same transaction)."""
        now = utc_now()
        if make_current and record["status"] != "accepted":
            raise ValueError("only an accepted registration can be made current")
        with self.transaction() as c:
            cur = c.execute(
                "INSERT INTO registrations (created_at, scan_id, series_uid, status, reason, problem_title, "
                "http_status, image_from_robot_json, fre_mm, figures_json, "
                "targets_image_mm_json, joints_json, "
                "joints_received_at, config_hash, software_version, duration_s) "
                "VALUES (?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?)",
                (
                    record.get("created_at", now),
                    record.get("scan_id"),
                    record.get("series_uid", ""),
                    record["status"],
                    record.get("reason", ""),
                    record.get("problem_title", ""),
                    record.get("http_status"),
                    _dumps(record.get("image_from_robot")),
                    record.get("fre_mm"),
                    _dumps(record.get("figures")),
                    _dumps(record.get("targets_image_mm")),
                    _dumps(record.get("joints_rad")),
                    record.get("joints_received_at"),
                    record["config_hash"],
                    record["software_version"],
                    record.get("duration_s"),
                ),
            )
            reg_id = int(cur.lastrowid or 0)
            if make_current:
                c.execute(
                    "INSERT INTO current_registration (singleton, registration_id, set_at) VALUES (1, ?, ?) "
                    "ON CONFLICT(singleton) DO UPDATE SET registration_id = excluded.registration_id, "
                    "set_at = excluded.set_at",
                    (reg_id, now),
                )
            return reg_id

    @staticmethod
    def _registration_from_row(r: sqlite3.Row, current_id: int | None) -> dict[str, Any]:
        return {
            "id": int(r["id"]),
            "created_at": r["created_at"],
            "scan_id": r["scan_id"],
            "series_uid": r["series_uid"],
            "status": r["status"],
            "reason": r["reason"],
            "problem_title": r["problem_title"],
            "http_status": r["http_status"],
            "image_from_robot": _loads(r["image_from_robot_json"]),
            "fre_mm": r["fre_mm"],
            "figures": _loads(r["figures_json"]),
            "targets_image_mm": _loads(r["targets_image_mm_json"]),
            "joints_rad": _loads(r["joints_json"]),
            "joints_received_at": r["joints_received_at"],
            "config_hash": r["config_hash"],
            "software_version": r["software_version"],
            "duration_s": r["duration_s"],
            "is_current": current_id is not None and int(r["id"]) == current_id,
        }

    def current_registration_id(self) -> int | None:
        rows = self._query("SELECT registration_id FROM current_registration WHERE singleton = 1")
        return int(rows[0][0]) if rows else None

    def get_registration(self, reg_id: int) -> dict[str, Any] | None:
        rows = self._query("SELECT * FROM registrations WHERE id = ?", (reg_id,))
        return self._registration_from_row(rows[0], self.current_registration_id()) if rows else None

    def current_registration(self) -> dict[str, Any] | None:
        """The registration the service serves (restored from disk after a restart), or None."""
        cur = self.current_registration_id()
        return None if cur is None else self.get_registration(cur)

    def list_registrations(self, limit: int = 100, offset: int = 0) -> list[dict[str, Any]]:
        cur = self.current_registration_id()
        rows = self._query("SELECT * FROM registrations ORDER BY id DESC LIMIT ? OFFSET ?", (limit, offset))
        return [self._registration_from_row(r, cur) for r in rows]

    # ---- verifications --------------------------------------------------------------------

    def insert_verification(self, record: dict[str, Any]) -> int:
        with self.transaction() as c:
            cur = c.execute(
                "INSERT INTO verifications (created_at, registration_id, scan_id, series_uid, "
                "passed, mean_mm, "
                "rms_mm, max_mm, figures_json, histogram_path, config_hash, software_version) "
                "VALUES (?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?)",
                (
                    record.get("created_at", utc_now()),
                    record["registration_id"],
                    record["scan_id"],
                    record["series_uid"],
                    int(bool(record["passed"])),
                    record["mean_mm"],
                    record["rms_mm"],
                    record["max_mm"],
                    _dumps(record["figures"]),
                    record.get("histogram_path"),
                    record["config_hash"],
                    record["software_version"],
                ),
            )
            return int(cur.lastrowid or 0)

    def set_verification_histogram(self, ver_id: int, path: str) -> None:
        with self.transaction() as c:
            c.execute("UPDATE verifications SET histogram_path = ? WHERE id = ?", (path, ver_id))

    def get_verification(self, ver_id: int) -> dict[str, Any] | None:
        rows = self._query("SELECT * FROM verifications WHERE id = ?", (ver_id,))
        if not rows:
            return None
        r = rows[0]
        return {
            "id": int(r["id"]),
            "created_at": r["created_at"],
            "registration_id": r["registration_id"],
            "scan_id": r["scan_id"],
            "series_uid": r["series_uid"],
            "passed": bool(r["passed"]),
            "mean_mm": r["mean_mm"],
            "rms_mm": r["rms_mm"],
            "max_mm": r["max_mm"],
            "figures": _loads(r["figures_json"]),
            "histogram_path": r["histogram_path"],
            "config_hash": r["config_hash"],
            "software_version": r["software_version"],
        }

    def counts(self) -> dict[str, int]:
        out = {}
        for table in ("scans", "registrations", "verifications"):
            out[table] = int(self._query(f"SELECT COUNT(*) FROM {table}")[0][0])
        return out


def _split_sql(script: str) -> list[str]:
    """Split a migration script into statements (no semicolons inside our literals)."""
    return [s.strip() for s in script.split(";") if s.strip()]
