"""The database schema and its version (``PRAGMA user_version`` = number of applied migrations).

``scans``
    one row per series UID (a re-export of the same UID updates nothing but ``seen_count``):
    folder, arrival time, slice count, geometry (``image_from_voxel``), status
    (``receiving`` / ``complete`` / ``reopened`` / ``replaced`` / ``invalid``, schema 7) and the reason.
``joint_snapshots``
    joints captured at a scan's arrival and the stillness verdict over the window before it.
``registrations``
    every POST /register, accepted or refused: ``image_from_robot``, quality figures,
    provenance (series UID, joints and their timestamp, config hash, software version),
    status ``accepted`` / ``refused`` + reason; ``withdrawn_at`` / ``withdrawn_reason`` (schema 2)
    mark an accepted one withdrawn (its scan was reopened: incomplete when registered).
``verifications``
    every POST /verify: per-sphere errors, mean / RMS / max, histogram path.
``current_registration``
    a single-row pointer to the registration the service serves.
``oarmreg_identity`` (2)
    a single row naming the application, a random database id, its creation time and the schema
    version (kept equal to ``user_version``; :mod:`service.store.integrity`).
``audit_log`` (2)
    who (``principal``: a 12-hex hash of the token, never the token) did what to which record.
``scan_instances`` (3)
    per series UID, the headers a DICOM Spatial Registration object references (patient and
    study attributes, SOP Class / Instance UIDs of every slice), :mod:`service.store.scan_instances`.
``calibrations``, ``active_calibration``
    every POST /calibrations (running / done / refused + reason, figures, URDF) and the active one;
    ``registrations.retired_at`` marks the registrations its activation retired.
``retention_log`` (schema 2)
    every scan folder the retention policy deleted, with its size and why.
``scan_files``, ``scan_changes`` (7)
    the SHA-256 and size of every stored instance of a scan; every state change of a scan and why
    (:mod:`service.intake.scan_lifecycle`); ``verifications`` / ``calibrations`` gain ``withdrawn_at`` /
    ``withdrawn_reason``.
``qa_protocols``, ``qa_checks``
    named sets of verification poses; which verification was taken at which pose of which protocol.
``registrations.withdrawn_by_scan`` / ``withdrawn_by_verification`` (9)
    a registration withdrawn by a verification: the verification scan, and the stored
    verification when it could be computed (NULL: the error was beyond what matching can bridge).
``joint_snapshots.verdict`` (10)
    the typed stillness verdict the registration gate reads (backfilled from the reason text once).
"""

from __future__ import annotations

import logging
import sqlite3
from pathlib import Path

from registration.errors import ConfigError

log = logging.getLogger(__name__)

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
    # 2: identity row and audit log
    """
    CREATE TABLE oarmreg_identity (
        singleton INTEGER PRIMARY KEY CHECK (singleton = 1),
        application TEXT NOT NULL CHECK (application = 'oarmreg'),
        database_id TEXT NOT NULL,
        created_at TEXT NOT NULL,
        schema_version INTEGER NOT NULL
    );
    INSERT INTO oarmreg_identity (singleton, application, database_id, created_at, schema_version)
        VALUES (1, 'oarmreg', lower(hex(randomblob(16))), strftime('%Y-%m-%dT%H:%M:%fZ', 'now'), 2);
    CREATE TABLE audit_log (
        id INTEGER PRIMARY KEY,
        at TEXT NOT NULL,
        principal TEXT NOT NULL,
        action TEXT NOT NULL,
        target TEXT NOT NULL,
        target_id INTEGER,
        outcome TEXT NOT NULL,
        detail TEXT NOT NULL DEFAULT ''
    );
    """,
    # 3: what the DICOM Spatial Registration object needs of a scan
    """
    CREATE TABLE scan_instances (
        series_uid TEXT PRIMARY KEY,
        headers_json TEXT NOT NULL,
        updated_at TEXT NOT NULL
    );
    """,
)

CALIBRATIONS_MIGRATION = """
    CREATE TABLE calibrations (
        id INTEGER PRIMARY KEY,
        created_at TEXT NOT NULL,
        status TEXT NOT NULL CHECK (status IN ('running', 'done', 'refused')),
        reason TEXT NOT NULL DEFAULT '',
        problem_title TEXT NOT NULL DEFAULT '',
        scan_ids_json TEXT NOT NULL,
        frame_of_reference_uid TEXT NOT NULL DEFAULT '',
        params_json TEXT NOT NULL,
        result_json TEXT,
        urdf_text TEXT,
        urdf_path TEXT,
        calibration_hash TEXT NOT NULL DEFAULT '',
        config_hash TEXT NOT NULL,
        software_version TEXT NOT NULL,
        finished_at TEXT,
        duration_s REAL
    );
    CREATE TABLE active_calibration (
        singleton INTEGER PRIMARY KEY CHECK (singleton = 1),
        calibration_id INTEGER NOT NULL REFERENCES calibrations(id),
        set_at TEXT NOT NULL
    );
    ALTER TABLE registrations ADD COLUMN retired_at TEXT;
    ALTER TABLE registrations ADD COLUMN retired_by_calibration INTEGER REFERENCES calibrations(id);
"""
"""Calibration sessions (:mod:`service.store.calibrations`), the active one, and
registrations retired by activating a calibration (design.md §9).  SQLite cannot widen the CHECK on
``registrations.status`` in place, so "retired" is an accepted row with ``retired_at`` set; the store
reports its status as ``retired``.  Appended after the tuple so branches adding their own migrations
merge without reordering: it is always the last one."""
MIGRATIONS = (*MIGRATIONS, CALIBRATIONS_MIGRATION)

WITHDRAWN_AND_RETENTION_MIGRATION = """
    ALTER TABLE registrations ADD COLUMN withdrawn_at TEXT;
    ALTER TABLE registrations ADD COLUMN withdrawn_reason TEXT NOT NULL DEFAULT '';
    ALTER TABLE scans ADD COLUMN reopened_count INTEGER NOT NULL DEFAULT 0;
    ALTER TABLE scans ADD COLUMN files_deleted_at TEXT;
    ALTER TABLE scans ADD COLUMN files_deleted_reason TEXT NOT NULL DEFAULT '';
    CREATE TABLE retention_log (
        id INTEGER PRIMARY KEY,
        deleted_at TEXT NOT NULL,
        scan_id INTEGER REFERENCES scans(id),
        folder TEXT NOT NULL,
        bytes INTEGER NOT NULL,
        reason TEXT NOT NULL
    );
"""
"""A registration can be withdrawn (its scan turned out incomplete, design §9), a scan
reopened (late slices) and its files deleted by the retention policy (the row stays).  SQLite cannot
widen the CHECK on ``registrations.status`` in place (the table would have to be rebuilt under
foreign keys), so "withdrawn" is an accepted row with ``withdrawn_at`` set; the store reports its
status as ``withdrawn`` (before ``retired``)."""
MIGRATIONS = (*MIGRATIONS, WITHDRAWN_AND_RETENTION_MIGRATION)

SCAN_LIFECYCLE_MIGRATION = """
    -- foreign_keys=off: rebuilds scans (the 12-step table change of https://sqlite.org/lang_altertable.html)
    CREATE TABLE scans_new (
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
        status TEXT NOT NULL
            CHECK (status IN ('receiving', 'complete', 'reopened', 'replaced', 'invalid')),
        reason TEXT NOT NULL DEFAULT '',
        seen_count INTEGER NOT NULL DEFAULT 1,
        updated_at TEXT NOT NULL,
        reopened_count INTEGER NOT NULL DEFAULT 0,
        files_deleted_at TEXT,
        files_deleted_reason TEXT NOT NULL DEFAULT ''
    );
    INSERT INTO scans_new (id, series_uid, frame_of_reference_uid, folder, arrived_at, n_files, n_slices,
        rows, columns, geometry_json, status, reason, seen_count, updated_at, reopened_count,
        files_deleted_at, files_deleted_reason)
        SELECT id, series_uid, frame_of_reference_uid, folder, arrived_at, n_files, n_slices, rows, columns,
        geometry_json, status, reason, seen_count, updated_at, reopened_count, files_deleted_at,
        files_deleted_reason FROM scans;
    DROP TABLE scans;
    ALTER TABLE scans_new RENAME TO scans;
    CREATE TABLE scan_files (
        scan_id INTEGER NOT NULL REFERENCES scans(id) ON DELETE CASCADE,
        name TEXT NOT NULL,
        sha256 TEXT NOT NULL,
        bytes INTEGER NOT NULL,
        PRIMARY KEY (scan_id, name)
    );
    CREATE TABLE scan_changes (
        id INTEGER PRIMARY KEY,
        scan_id INTEGER NOT NULL REFERENCES scans(id) ON DELETE CASCADE,
        at TEXT NOT NULL,
        from_status TEXT NOT NULL,
        to_status TEXT NOT NULL,
        reason TEXT NOT NULL
    );
    CREATE INDEX scan_changes_scan ON scan_changes(scan_id);
    ALTER TABLE verifications ADD COLUMN withdrawn_at TEXT;
    ALTER TABLE verifications ADD COLUMN withdrawn_reason TEXT NOT NULL DEFAULT '';
    ALTER TABLE calibrations ADD COLUMN withdrawn_at TEXT;
    ALTER TABLE calibrations ADD COLUMN withdrawn_reason TEXT NOT NULL DEFAULT ''
"""
"""One scan lifecycle for both intakes (:mod:`service.intake.scan_lifecycle`).  ``scans.status``
takes ``receiving`` / ``reopened`` / ``replaced``: SQLite cannot widen a CHECK in place, so the table
is rebuilt (foreign keys off for this migration only, checked with ``PRAGMA foreign_key_check``
before the commit).  ``scan_files``: the SHA-256 of every stored instance of a scan;
``scan_changes``: every state change of a scan and why; verifications and calibrations made from a
scan whose content changed are withdrawn like registrations."""
MIGRATIONS = (*MIGRATIONS, SCAN_LIFECYCLE_MIGRATION)

FOREIGN_KEYS_OFF = "-- foreign_keys=off"
"""A migration whose first line is this runs with ``PRAGMA foreign_keys=OFF`` (a table rebuild: with
them on, ``DROP TABLE`` would cascade into the rows that reference it)."""

PACS_EXPORTS_MIGRATION = """
    CREATE TABLE pacs_exports (
        id INTEGER PRIMARY KEY,
        registration_id INTEGER NOT NULL UNIQUE REFERENCES registrations(id),
        destination TEXT NOT NULL,
        state TEXT NOT NULL CHECK (state IN ('pending', 'sent', 'failed')),
        attempts INTEGER NOT NULL DEFAULT 0,
        dimse_status INTEGER,
        reason TEXT NOT NULL DEFAULT '',
        sop_instance_uid TEXT NOT NULL DEFAULT '',
        queued_at TEXT NOT NULL,
        updated_at TEXT NOT NULL,
        next_attempt_unix_s REAL NOT NULL
    );
    CREATE INDEX pacs_exports_due ON pacs_exports (state, next_attempt_unix_s);
"""
"""The PACS archive queue, one row per accepted registration (service.navigation.pacs).  A row stays
``pending`` while it is being sent, so a service killed mid-send sends it again after restart."""
MIGRATIONS = (*MIGRATIONS, PACS_EXPORTS_MIGRATION)

QA_PROTOCOLS_MIGRATION = """
    CREATE TABLE qa_protocols (
        id INTEGER PRIMARY KEY,
        name TEXT NOT NULL UNIQUE,
        description TEXT NOT NULL DEFAULT '',
        poses_json TEXT NOT NULL,
        created_at TEXT NOT NULL
    );
    CREATE TABLE qa_checks (
        verification_id INTEGER PRIMARY KEY REFERENCES verifications(id),
        protocol_id INTEGER NOT NULL REFERENCES qa_protocols(id),
        pose TEXT NOT NULL
    );
    CREATE INDEX qa_checks_protocol ON qa_checks (protocol_id)
"""
"""QA protocols (a named set of verification poses, :mod:`service.store.qa`) and which
verification was taken at which pose of which protocol."""
MIGRATIONS = (*MIGRATIONS, QA_PROTOCOLS_MIGRATION)

VERIFICATION_WITHDRAWAL_MIGRATION = """
    ALTER TABLE registrations ADD COLUMN withdrawn_by_scan INTEGER REFERENCES scans(id);
    ALTER TABLE registrations ADD COLUMN withdrawn_by_verification INTEGER REFERENCES verifications(id)
"""
"""A failed verification withdraws the registration it verified (docs/safety.md "Which
registration may be current"): ``withdrawn_at`` / ``withdrawn_reason`` as for a scan withdrawal, plus
the verification scan and, when the error could be computed, the stored verification.  A row with
``withdrawn_by_scan`` set was withdrawn by a verification; without it, by its own scan's change."""
MIGRATIONS = (*MIGRATIONS, VERIFICATION_WITHDRAWAL_MIGRATION)

STILLNESS_VERDICT_MIGRATION = """
    ALTER TABLE joint_snapshots ADD COLUMN verdict TEXT NOT NULL DEFAULT 'incomplete'
        CHECK (verdict IN ('still', 'moved', 'incomplete'));
    -- the only place the reason text decides a verdict: rows written before the column existed, once
    UPDATE joint_snapshots SET verdict = CASE
        WHEN still <> 0 THEN 'still'
        WHEN substr(stillness_reason, 1, 11) = 'robot moved' THEN 'moved'
        ELSE 'incomplete'
    END
"""
"""The stillness verdict (``still`` / ``moved`` / ``incomplete``) is a column written from the typed
:attr:`service.records.JointSnapshot.verdict`, and the registration gate reads only it.
Rows stored before it are backfilled here, once, the way the software that wrote them read them:
``still`` set is ``still``; every ``moved`` reason of registration.model.stillness starts with
"robot moved"; anything else (no samples, a gap, a reconnect, a series already there) is
``incomplete``.  The default refuses a row that somehow lacks one."""
MIGRATIONS = (*MIGRATIONS, STILLNESS_VERDICT_MIGRATION)

SCHEMA_VERSION = len(MIGRATIONS)
"""The schema version this software writes."""


def schema_version(conn: sqlite3.Connection) -> int:
    return int(conn.execute("PRAGMA user_version").fetchone()[0])


def migrate(conn: sqlite3.Connection, path: Path) -> None:
    """Apply the missing migrations, each in its own transaction.

    Raises
    ------
    ConfigError
        The database was written by a newer version of the software.
    """
    version = schema_version(conn)
    if version > SCHEMA_VERSION:
        raise ConfigError(
            f"{path}: schema version {version} is newer than this software knows "
            f"({SCHEMA_VERSION}); upgrade oarmreg or use another data_dir"
        )
    for i in range(version, SCHEMA_VERSION):
        fk_off = MIGRATIONS[i].lstrip().startswith(FOREIGN_KEYS_OFF)
        fk_was = int(conn.execute("PRAGMA foreign_keys").fetchone()[0])
        if fk_off:
            conn.execute("PRAGMA foreign_keys=OFF")  # a no-op inside a transaction: set before BEGIN
        conn.execute("BEGIN IMMEDIATE")
        try:
            for stmt in split_sql(MIGRATIONS[i]):
                conn.execute(stmt)
            if fk_off:
                bad = conn.execute("PRAGMA foreign_key_check").fetchall()
                if bad:
                    raise ConfigError(
                        f"{path}: migration {i + 1} breaks {len(bad)} foreign key(s): {bad[:4]}"
                    )
            conn.execute(f"PRAGMA user_version = {i + 1}")
            conn.execute("COMMIT")
        except BaseException:
            conn.execute("ROLLBACK")
            raise
        finally:
            if fk_off:
                conn.execute(f"PRAGMA foreign_keys={'ON' if fk_was else 'OFF'}")
        log.info("database %s: migrated to schema version %d", path, i + 1)


def split_sql(script: str) -> list[str]:
    """Split a migration script into statements (no semicolons inside our literals; ``--`` comment
    lines dropped)."""
    out = []
    for stmt in script.split(";"):
        text = "\n".join(ln for ln in stmt.splitlines() if not ln.strip().startswith("--")).strip()
        if text:
            out.append(text)
    return out
