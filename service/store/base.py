"""The shared SQLite connection: one lock, one transaction helper, JSON columns."""

from __future__ import annotations

import contextlib
import errno
import json
import sqlite3
import threading
from collections.abc import Iterator
from contextlib import contextmanager
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

from service.errors import StorageFullError

SQLITE_FULL = 13
"""SQLite's primary result code for "database or disk is full"."""


def _is_disk_full(e: BaseException) -> bool:
    if isinstance(e, OSError):
        return e.errno == errno.ENOSPC
    code = getattr(e, "sqlite_errorcode", None)
    return (code is not None and code & 0xFF == SQLITE_FULL) or "disk is full" in str(e)


SQLITE_BUSY, SQLITE_LOCKED, SQLITE_READONLY = 5, 6, 8
"""SQLite's primary result codes for "database is locked" and "attempt to write a readonly database"."""


def _is_busy_or_readonly(e: BaseException) -> bool:
    code = getattr(e, "sqlite_errorcode", None)
    if code is not None and code & 0xFF in (SQLITE_BUSY, SQLITE_LOCKED, SQLITE_READONLY):
        return True
    return "database is locked" in str(e) or "readonly database" in str(e)


def utc_now() -> str:
    """ISO 8601 UTC timestamp with microseconds."""
    return datetime.now(UTC).isoformat()


def loads(s: str | None) -> Any:
    return None if s is None else json.loads(s)


def dumps(v: object) -> str | None:
    return None if v is None else json.dumps(v)


class Connection:
    """One ``sqlite3`` connection shared by the service's threads under a lock.

    Every write is one transaction (``BEGIN IMMEDIATE`` … ``COMMIT``); a failure rolls back, so
    nothing already stored is lost or half-written.  WAL keeps readers cheap.
    """

    def __init__(self, conn: sqlite3.Connection, path: Path) -> None:
        from service.store.integrity import FileWatch

        self.raw = conn
        self.path = path
        self.lock = threading.RLock()
        self.watch = FileWatch(path, conn, self.lock)

    @contextmanager
    def transaction(self) -> Iterator[sqlite3.Connection]:
        """``BEGIN IMMEDIATE`` … ``COMMIT``; rolls back on any exception.

        Raises
        ------
        StorageFullError
            The disk holding the database is full (``SQLITE_FULL``, ``ENOSPC``); rolled back.
        DatabaseBusyError
            Another process holds the database past the busy timeout, or it is read-only; rolled back.
        DatabaseUnavailableError
            The database file was deleted or replaced since it was opened (nothing is written).
        """
        problem = self.watch.check()
        if problem is not None:
            from service.errors import DatabaseUnavailableError

            raise DatabaseUnavailableError(problem)
        with self.lock:
            try:
                self.raw.execute("BEGIN IMMEDIATE")
                try:
                    yield self.raw
                except BaseException:
                    if self.raw.in_transaction:
                        self.raw.execute("ROLLBACK")
                    raise
                self.raw.execute("COMMIT")
            except (sqlite3.OperationalError, OSError) as e:
                if not (_is_disk_full(e) or _is_busy_or_readonly(e)):
                    raise
                with contextlib.suppress(sqlite3.Error):
                    if self.raw.in_transaction:
                        self.raw.execute("ROLLBACK")
                if _is_busy_or_readonly(e):
                    from service.errors import DatabaseBusyError

                    raise DatabaseBusyError(
                        f"the database {self.path} cannot be written now ({e}): another process holds it "
                        "(a backup, an sqlite3 shell) or its file, WAL or folder is read-only; nothing was "
                        "written. Retry after Retry-After; if it persists, find what holds the file "
                        "(fuser) or fix its permissions."
                    ) from e
                raise StorageFullError(
                    f"the data folder {self.path.parent} is full ({e}); the write was rolled back, nothing "
                    "stored before is lost. Free disk space there (or lower retention.max_disk_mb) and retry."
                ) from e

    def query(self, sql: str, args: tuple[object, ...] = ()) -> list[sqlite3.Row]:
        with self.lock:
            return list(self.raw.execute(sql, args).fetchall())

    def close(self) -> None:
        with self.lock:
            self.raw.close()
