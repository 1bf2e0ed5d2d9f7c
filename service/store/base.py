"""The shared SQLite connection: one lock, one transaction helper, JSON columns."""

from __future__ import annotations

import json
import sqlite3
import threading
from collections.abc import Iterator
from contextlib import contextmanager
from datetime import UTC, datetime
from pathlib import Path
from typing import Any


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
        DatabaseGoneError
            The database file was deleted or replaced since it was opened (nothing is written).
        """
        problem = self.watch.check()
        if problem is not None:
            from service.errors import DatabaseGoneError

            raise DatabaseGoneError(problem)
        with self.lock:
            self.raw.execute("BEGIN IMMEDIATE")
            try:
                yield self.raw
            except BaseException:
                self.raw.execute("ROLLBACK")
                raise
            self.raw.execute("COMMIT")

    def query(self, sql: str, args: tuple[object, ...] = ()) -> list[sqlite3.Row]:
        with self.lock:
            return list(self.raw.execute(sql, args).fetchall())

    def close(self) -> None:
        with self.lock:
            self.raw.close()
