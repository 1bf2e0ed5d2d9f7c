"""A database as an older release left it: the migrations before ``until`` applied, nothing after, for
the tests that open it with today's code and check what the later migrations do to its rows."""

from __future__ import annotations

import sqlite3
from pathlib import Path

from service.store.integrity import APPLICATION_ID
from service.store.migrations import MIGRATIONS, split_sql


def database_before(path: Path, until: str) -> sqlite3.Connection:
    """An autocommit connection to a new database at ``path`` whose schema stops just before the
    migration ``until`` (one of :data:`service.store.migrations.MIGRATIONS`); the caller adds the old
    rows and closes it."""
    n = MIGRATIONS.index(until)
    c = sqlite3.connect(path, isolation_level=None)
    c.execute(f"PRAGMA application_id = {APPLICATION_ID}")
    c.execute("PRAGMA foreign_keys=ON")
    for script in MIGRATIONS[:n]:
        for stmt in split_sql(script):
            c.execute(stmt)
    c.execute(f"PRAGMA user_version = {n}")
    c.execute(f"UPDATE oarmreg_identity SET schema_version = {n}")
    return c
