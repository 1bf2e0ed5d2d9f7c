"""Is this file our database, is it intact, and is it still there?

* **Before opening** (:func:`preflight`): only a path that does not exist is initialised.  A
  0-byte file, a file without the SQLite header, or anything that is not a regular file is
  refused — never silently re-initialised over (a truncated database once came back empty).
* **After opening** (:func:`verify_existing`): ``PRAGMA quick_check`` must answer ``ok``; the file
  must carry our ``PRAGMA application_id`` (:data:`APPLICATION_ID`) or be a pre-#13 oarmreg
  database (``user_version`` ≥ 1 and our tables); the ``oarmreg_identity`` row must agree with
  ``user_version``.  :func:`stamp` writes both after migrating.
* **While running** (:class:`FileWatch`): the file's (device, inode) is recorded at open and
  compared on every write transaction and every health check.  A deleted or replaced file is
  reported once, the still-open connection is copied next to it with the SQLite online backup
  API (nothing written so far is lost), and the service stays unhealthy until restarted.
* **Who holds it** (:func:`hold_shared` / :func:`hold_exclusive`): a running service keeps a
  shared ``flock`` on ``<db>.lock``; ``oarmreg restore`` needs it exclusively.
"""

from __future__ import annotations

import fcntl
import logging
import os
import sqlite3
import stat
import threading
from datetime import UTC, datetime
from pathlib import Path
from typing import IO

from registration.errors import ConfigError
from service.store.migrations import SCHEMA_VERSION

log = logging.getLogger(__name__)

APPLICATION_ID = 0x4F41524D
"""``PRAGMA application_id`` of an oarmreg database: ASCII 'OARM' (sqlite.org/fileformat2.html §1.3.18)."""
SQLITE_HEADER = b"SQLite format 3\x00"
"""The first 16 bytes of every SQLite 3 database file (fileformat2.html §1.3)."""
OUR_TABLES = frozenset({"scans", "registrations", "verifications", "current_registration"})
MAX_CHECK_MESSAGES = 3
"""quick_check lines quoted in the refusal (SQLite's own text: page numbers, never row contents)."""

WHAT_TO_DO = (
    "stop the service and restore the last backup (oarmreg restore BACKUP --data DATA_DIR), or move the "
    "file away to start a new, empty database"
)


def unusable(path: Path, why: str) -> ConfigError:
    return ConfigError(f"{path} is not a usable oarmreg database: {why}; {WHAT_TO_DO}")


def preflight(path: Path) -> bool:
    """True if ``path`` does not exist (a new database will be created there), False if it exists.

    Raises
    ------
    ConfigError
        The path exists but is not a regular file, is empty, or lacks the SQLite header.
    """
    try:
        st = path.stat()
    except FileNotFoundError:
        return True
    except OSError as e:
        raise ConfigError(
            f"cannot read the database {path}: {e}; check data_dir and its permissions"
        ) from None
    if not stat.S_ISREG(st.st_mode):
        raise unusable(path, "it is not a regular file")
    if st.st_size == 0:
        raise unusable(path, "the file is empty (0 bytes: truncated or never written); it is refused "
                       "rather than re-initialised so no records are silently lost")  # fmt: skip
    try:
        with path.open("rb") as f:
            head = f.read(len(SQLITE_HEADER))
    except OSError as e:
        raise ConfigError(f"cannot read the database {path}: {e}; check its permissions") from None
    if head != SQLITE_HEADER:
        raise unusable(path, "it is not an SQLite database (wrong file header)")
    return False


def verify_existing(conn: sqlite3.Connection, path: Path) -> None:
    """Integrity and identity of an existing database (before migrating).

    Raises
    ------
    ConfigError
        ``quick_check`` fails, or the file belongs to another application.
    sqlite3.DatabaseError
        The file is too damaged to read at all (the caller maps it to ConfigError).
    """
    rows = [str(r[0]) for r in conn.execute("PRAGMA quick_check").fetchall()]
    if rows != ["ok"]:
        quoted = "; ".join(rows[:MAX_CHECK_MESSAGES]) + (" …" if len(rows) > MAX_CHECK_MESSAGES else "")
        raise unusable(path, f"PRAGMA quick_check found damage ({quoted})")
    app_id = int(conn.execute("PRAGMA application_id").fetchone()[0])
    version = int(conn.execute("PRAGMA user_version").fetchone()[0])
    if app_id == APPLICATION_ID:
        if version <= SCHEMA_VERSION:  # a newer schema is refused by migrate(), naming the versions
            _check_identity_row(conn, path)
        return
    tables = {str(r[0]) for r in conn.execute("SELECT name FROM sqlite_master WHERE type = 'table'")}
    if app_id == 0 and version >= 1 and tables >= OUR_TABLES:
        log.info("database %s: an oarmreg database from before application_id; stamping it", path)
        return
    raise unusable(
        path, f"it belongs to another application (application_id {app_id:#x}, expected {APPLICATION_ID:#x}, "
        f"schema version {version}, {len(tables)} tables)",
    )  # fmt: skip


def _check_identity_row(conn: sqlite3.Connection, path: Path) -> None:
    version = int(conn.execute("PRAGMA user_version").fetchone()[0])
    try:
        row = conn.execute(
            "SELECT application, schema_version FROM oarmreg_identity WHERE singleton = 1"
        ).fetchone()
    except sqlite3.OperationalError:
        row = None
    if row is None or str(row[0]) != "oarmreg":
        raise unusable(path, "its oarmreg_identity row is missing")
    if int(row[1]) != version:
        raise unusable(path, f"oarmreg_identity says schema version {row[1]} but the file says {version}")


def stamp(conn: sqlite3.Connection) -> None:
    """Write ``application_id`` and the identity row's schema version (after migrating)."""
    version = int(conn.execute("PRAGMA user_version").fetchone()[0])
    conn.execute(f"PRAGMA application_id = {APPLICATION_ID}")
    conn.execute("UPDATE oarmreg_identity SET schema_version = ? WHERE singleton = 1", (version,))


def file_id(path: Path) -> tuple[int, int] | None:
    try:
        st = os.stat(path)
    except OSError:
        return None
    return (st.st_dev, st.st_ino)


class FileWatch:
    """Notices the database file being deleted or replaced under an open connection."""

    def __init__(self, path: Path, raw: sqlite3.Connection, lock: threading.RLock) -> None:
        self.path = path
        self._raw = raw
        self._lock = lock
        self._id = file_id(path)
        self.problem: str | None = None

    def check(self) -> str | None:
        """None while the file is the one opened; else what happened and what to do (sticky)."""
        if self.problem is not None:
            return self.problem
        now = file_id(self.path)
        if now == self._id:
            return None
        with self._lock:
            if self.problem is None:
                what = "was deleted" if now is None else "was replaced by another file"
                self.problem = f"the database file {self.path} {what} while the service was running; " + (
                    self._rescue()
                )
                log.error("%s", self.problem)
        return self.problem

    def _rescue(self) -> str:
        """Copy the still-open connection next to the lost file (online backup API)."""
        stamp_ = datetime.now(UTC).strftime("%Y%m%dT%H%M%SZ")
        target = self.path.with_name(f"{self.path.name}.recovered-{stamp_}")
        try:
            self.path.parent.mkdir(parents=True, exist_ok=True)
            dest = sqlite3.connect(target)
            try:
                self._raw.backup(dest)
            finally:
                dest.close()
        except (OSError, sqlite3.Error) as e:
            return (
                f"no new records are accepted and copying the open database failed ({type(e).__name__}); "
                "keep the service running while you copy its data folder's open files, then restart it"
            )
        return (
            f"no new records are accepted; every record so far was saved to {target}: stop the service, "
            f"run 'oarmreg restore {target} --data {self.path.parent}' (or move the file into place as "
            f"{self.path.name}) and start it again"
        )


def lock_path(db_path: Path) -> Path:
    return db_path.with_name(db_path.name + ".lock")


def hold_shared(db_path: Path) -> IO[bytes]:
    """Take the service's shared lock (kept until the returned file is closed).

    Raises
    ------
    ConfigError
        A restore holds the database exclusively.
    """
    f = lock_path(db_path).open("a+b")
    try:
        fcntl.flock(f.fileno(), fcntl.LOCK_SH | fcntl.LOCK_NB)
    except BlockingIOError:
        f.close()
        raise ConfigError(f"{db_path} is being restored (oarmreg restore holds {lock_path(db_path)}); "
                          "start the service when it has finished") from None  # fmt: skip
    return f


def hold_exclusive(db_path: Path) -> IO[bytes]:
    """Take the database exclusively (restore); kept until the returned file is closed.

    Raises
    ------
    ConfigError
        A service (or another restore) holds the database.
    """
    db_path.parent.mkdir(parents=True, exist_ok=True)
    f = lock_path(db_path).open("a+b")
    try:
        fcntl.flock(f.fileno(), fcntl.LOCK_EX | fcntl.LOCK_NB)
    except BlockingIOError:
        f.close()
        raise ConfigError(
            f"{db_path} is in use by a running oarmreg service (it holds {lock_path(db_path)}); "
            "stop the service before restoring"
        ) from None
    return f
