"""Open, migrate and close the service's database; the per-table stores hang off it."""

from __future__ import annotations

import sqlite3
from pathlib import Path
from typing import IO

import service.store.integrity as integrity
import service.store.migrations as migrations
from registration.errors import ConfigError
from service.store.audit import AuditStore
from service.store.base import Connection
from service.store.calibrations import CalibrationStore
from service.store.pacs_exports import PacsExportStore
from service.store.qa import QaStore, QaTrendStore
from service.store.registrations import RegistrationStore
from service.store.scan_instances import ScanInstanceStore
from service.store.scans import ScanStore
from service.store.verifications import VerificationStore

BUSY_TIMEOUT_S = 10.0
"""How long a write waits for another process holding the database (sqlite3 ``timeout``)."""


class Database:
    """The service's store.  Thread-safe; open with :meth:`open`, close with :meth:`close`."""

    def __init__(self, conn: Connection) -> None:
        self._conn = conn
        self.path = conn.path
        self.scans = ScanStore(conn)
        self.registrations = RegistrationStore(conn)
        self.verifications = VerificationStore(conn)
        self.scan_instances = ScanInstanceStore(conn)
        self.audit = AuditStore(conn)
        self._lock_file: IO[bytes] | None = None
        self.calibrations = CalibrationStore(conn)
        self.pacs_exports = PacsExportStore(conn)  # the PACS archive queue
        self.qa = QaStore(conn)  # QA protocols and the checks taken at their poses
        self.qa_trend = QaTrendStore(conn)  # read-only: QA checks and FRE over time

    @classmethod
    def open(
        cls, path: str | Path, *, hold_lock: bool = True, busy_timeout_s: float = BUSY_TIMEOUT_S
    ) -> Database:
        """Open (creating only if the path does not exist), check and migrate the database at ``path``.

        ``busy_timeout_s``: how long a write waits for another process holding the file (then
        :class:`~service.errors.DatabaseBusyError`, 503).  ``hold_lock``: take the shared service lock
        (``<db>.lock``, see :mod:`service.store.integrity`) until :meth:`close`, so ``oarmreg
        restore`` refuses.

        Raises
        ------
        ConfigError
            The folder cannot be created; the file is empty, foreign or damaged
            (``PRAGMA quick_check``); or it was written by a newer version of the software.
        """
        p = Path(path)
        try:
            p.parent.mkdir(parents=True, exist_ok=True)
        except OSError as e:
            raise ConfigError(
                f"cannot create the folder of {p}: {e}; check data_dir and its permissions"
            ) from None
        is_new = integrity.preflight(p)
        lock = integrity.hold_shared(p) if hold_lock else None
        try:
            raw = _connect(p, is_new, busy_timeout_s)
        except BaseException:
            if lock is not None:
                lock.close()
            raise
        db = cls(Connection(raw, p))
        db._lock_file = lock
        return db

    def close(self) -> None:
        self._conn.close()
        if self._lock_file is not None:
            self._lock_file.close()
            self._lock_file = None

    def health_problem(self) -> str | None:
        """None while the database file is the one opened; else what happened and what to do."""
        return self._conn.watch.check()

    @property
    def schema_version(self) -> int:
        with self._conn.lock:
            return migrations.schema_version(self._conn.raw)

    def counts(self) -> dict[str, int]:
        return {
            table: int(self._conn.query(f"SELECT COUNT(*) FROM {table}")[0][0])
            for table in ("scans", "registrations", "verifications", "calibrations")
        }


def _connect(p: Path, is_new: bool, busy_timeout_s: float = BUSY_TIMEOUT_S) -> sqlite3.Connection:
    """Connect, check an existing file (integrity, identity), migrate, stamp; ConfigError on failure."""
    try:
        raw = sqlite3.connect(p, timeout=busy_timeout_s, isolation_level=None, check_same_thread=False)
    except (OSError, sqlite3.Error) as e:
        raise ConfigError(f"cannot open the database {p}: {e}; check data_dir and its permissions") from None
    try:
        raw.row_factory = sqlite3.Row
        if not is_new:
            integrity.verify_existing(raw, p)
        raw.execute("PRAGMA journal_mode=WAL")
        raw.execute("PRAGMA foreign_keys=ON")
        raw.execute("PRAGMA synchronous=NORMAL")
        migrations.migrate(raw, p)
        integrity.stamp(raw)
    except sqlite3.DatabaseError as e:
        raw.close()
        raise integrity.unusable(p, f"SQLite cannot read it ({e})") from None
    except BaseException:
        raw.close()
        raise
    return raw
