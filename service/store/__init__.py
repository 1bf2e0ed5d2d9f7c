"""SQLite persistence (stdlib ``sqlite3``, WAL): one store per table family.

:class:`Database` opens and migrates the file (:mod:`service.store.migrations`) and holds
``scans`` (:class:`~service.store.scans.ScanStore`), ``registrations``
(:class:`~service.store.registrations.RegistrationStore`) and ``verifications``
(:class:`~service.store.verifications.VerificationStore`), all sharing one connection and lock
(:class:`~service.store.base.Connection`).  They read and write the records of
:mod:`service.records`.

Enters: the records of :mod:`service.records` from every room.
Leaves: the same records read back; the SQLite file in ``data_dir``, migrated and integrity-checked.
"""

from __future__ import annotations

from service.store.database import BUSY_TIMEOUT_S, Database
from service.store.migrations import MIGRATIONS, SCHEMA_VERSION

__all__ = ["BUSY_TIMEOUT_S", "MIGRATIONS", "SCHEMA_VERSION", "Database"]
