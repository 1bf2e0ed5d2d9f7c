"""Open, migrate and close the service's database; the per-table stores hang off it."""

from __future__ import annotations

import sqlite3
from pathlib import Path

from registration.errors import ConfigError
from service.store import migrations
from service.store.base import Connection
from service.store.calibrations import CalibrationStore
from service.store.registrations import RegistrationStore
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
        self.calibrations = CalibrationStore(conn)

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
        unusable = f"{p} is not a usable oarmreg database: {{}}; move it away or fix data_dir"
        try:
            p.parent.mkdir(parents=True, exist_ok=True)
            raw = sqlite3.connect(p, timeout=BUSY_TIMEOUT_S, isolation_level=None, check_same_thread=False)
            raw.row_factory = sqlite3.Row
            raw.execute("PRAGMA journal_mode=WAL")
            raw.execute("PRAGMA foreign_keys=ON")
            raw.execute("PRAGMA synchronous=NORMAL")
        except sqlite3.DatabaseError as e:
            raise ConfigError(unusable.format(e)) from None
        except (OSError, sqlite3.Error) as e:
            raise ConfigError(
                f"cannot open the database {p}: {e}; check data_dir and its permissions"
            ) from None
        try:
            migrations.migrate(raw, p)
        except sqlite3.DatabaseError as e:
            raw.close()
            raise ConfigError(unusable.format(e)) from None
        except ConfigError:
            raw.close()
            raise
        return cls(Connection(raw, p))

    def close(self) -> None:
        self._conn.close()

    @property
    def schema_version(self) -> int:
        with self._conn.lock:
            return migrations.schema_version(self._conn.raw)

    def counts(self) -> dict[str, int]:
        return {
            table: int(self._conn.query(f"SELECT COUNT(*) FROM {table}")[0][0])
            for table in ("scans", "registrations", "verifications", "calibrations")
        }
