"""Backup and restore of the service's data (``oarmreg backup OUT`` / ``oarmreg restore IN``).

A backup is a folder::

    OUT/oarmreg.sqlite3     the database, copied with SQLite's online backup API
                            (sqlite.org/backup.html): consistent even while the service writes
    OUT/calibrations/...    data_dir/calibrations, if present
    OUT/histograms/...      data_dir/histograms (verification PNGs), if present
    OUT/manifest.json       format, software and schema version, SHA-256 of every file

Restore checks the manifest's checksums and the copy's integrity and identity
(:mod:`service.store.integrity`) first, refuses while a service holds the database (its shared
lock on ``<db>.lock``), and moves whatever it replaces aside as ``*.before-restore-<UTC time>``
(nothing is deleted).
"""

from __future__ import annotations

import hashlib
import json
import shutil
import sqlite3
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import service.store.integrity as integrity
from registration import __version__
from registration.errors import ConfigError

BACKUP_FORMAT = "oarmreg-backup"
BACKUP_FORMAT_VERSION = 1
DB_NAME = "oarmreg.sqlite3"
MANIFEST = "manifest.json"
DATA_FOLDERS = ("calibrations", "histograms")
"""Folders of ``data_dir`` copied beside the database."""
SIDE_FILES = ("-wal", "-shm")


def _sha256(path: Path) -> str:
    h = hashlib.sha256()
    with path.open("rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def _check_copy(path: Path) -> int:
    """Integrity + identity of a database copy; its schema version."""
    integrity.preflight(path)
    conn = sqlite3.connect(path)
    try:
        integrity.verify_existing(conn, path)
        return int(conn.execute("PRAGMA user_version").fetchone()[0])
    except sqlite3.DatabaseError as e:
        raise integrity.unusable(path, f"SQLite cannot read it ({e})") from None
    finally:
        conn.close()


def backup(db_path: Path, out: Path) -> dict[str, Any]:
    """Write a backup of ``db_path`` (and its data folders) to the new or empty folder ``out``.

    Returns the manifest.

    Raises
    ------
    ConfigError
        No database, a damaged or foreign one, or ``out`` is not empty.
    """
    if integrity.preflight(db_path):
        raise ConfigError(f"there is no database at {db_path}; check --data / data_dir")
    if out.exists() and (not out.is_dir() or any(out.iterdir())):
        raise ConfigError(f"{out} exists and is not an empty folder; give a new folder for the backup")
    out.mkdir(parents=True, exist_ok=True)
    src = sqlite3.connect(db_path, timeout=10.0)
    try:
        integrity.verify_existing(src, db_path)
        dest = sqlite3.connect(out / DB_NAME)
        try:
            src.backup(dest)
        finally:
            dest.close()
    except sqlite3.DatabaseError as e:
        raise integrity.unusable(db_path, f"SQLite cannot read it ({e})") from None
    finally:
        src.close()
    schema = _check_copy(out / DB_NAME)
    for name in DATA_FOLDERS:
        if (db_path.parent / name).is_dir():
            shutil.copytree(db_path.parent / name, out / name)
    files = {
        str(p.relative_to(out)): _sha256(p)
        for p in sorted(out.rglob("*"))
        if p.is_file() and p.name != MANIFEST
    }
    manifest = {
        "format": BACKUP_FORMAT,
        "format_version": BACKUP_FORMAT_VERSION,
        "created_at": datetime.now(UTC).isoformat(),
        "software_version": __version__,
        "schema_version": schema,
        "source": str(db_path),
        "files": files,
    }
    (out / MANIFEST).write_text(json.dumps(manifest, indent=2) + "\n", encoding="utf-8")
    return manifest


def read_manifest(backup_dir: Path) -> dict[str, Any]:
    """The backup's manifest, its checksums verified.

    Raises
    ------
    ConfigError
        Not a backup folder, or a file is missing or changed.
    """
    try:
        manifest = json.loads((backup_dir / MANIFEST).read_text(encoding="utf-8"))
    except (OSError, ValueError) as e:
        raise ConfigError(f"{backup_dir} is not an oarmreg backup folder ({MANIFEST}: {e})") from None
    if not isinstance(manifest, dict) or manifest.get("format") != BACKUP_FORMAT:
        raise ConfigError(f"{backup_dir / MANIFEST} is not an oarmreg backup manifest")
    files = manifest.get("files")
    if not isinstance(files, dict) or DB_NAME not in files:
        raise ConfigError(f"{backup_dir / MANIFEST} lists no {DB_NAME}")
    for rel, digest in files.items():
        p = backup_dir / rel
        if not p.is_file() or _sha256(p) != digest:
            raise ConfigError(f"{p} is missing or differs from the backup's manifest; the backup is damaged")
    return manifest


def restore(backup_dir: Path, db_path: Path) -> list[Path]:
    """Replace the database (and data folders) at ``db_path`` by the backup; the paths moved aside.

    Raises
    ------
    ConfigError
        A damaged backup, or a service holds the database.
    """
    if (backup_dir / MANIFEST).is_file():
        read_manifest(backup_dir)
        source = backup_dir / DB_NAME
        folders = [backup_dir / n for n in DATA_FOLDERS if (backup_dir / n).is_dir()]
    else:  # a bare database file (e.g. a *.recovered-* copy the service saved)
        source, folders = backup_dir, []
    _check_copy(source)
    lock = integrity.hold_exclusive(db_path)
    try:
        return _swap_in(source, folders, db_path)
    finally:
        lock.close()


def _swap_in(source: Path, folders: list[Path], db_path: Path) -> list[Path]:
    stamp = datetime.now(UTC).strftime("%Y%m%dT%H%M%SZ")
    moved: list[Path] = []
    tmp = db_path.with_name(f".{db_path.name}.restoring")
    shutil.copyfile(source, tmp)
    for suffix in ("", *SIDE_FILES):
        old = db_path.with_name(db_path.name + suffix)
        if old.exists():
            aside = old.with_name(f"{db_path.name}.before-restore-{stamp}{suffix}")
            old.rename(aside)
            moved.append(aside)
    tmp.replace(db_path)
    for folder in folders:
        target = db_path.parent / folder.name
        if target.exists():
            aside = target.with_name(f"{folder.name}.before-restore-{stamp}")
            target.rename(aside)
            moved.append(aside)
        shutil.copytree(folder, target)
    return moved
