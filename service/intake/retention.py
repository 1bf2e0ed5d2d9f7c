"""Data lifecycle: delete old intake scans (their DICOM folders) by age or disk quota, oldest first.

Runs at start-up and every ``retention.interval_s`` (``service.runtime.loops``).  A scan's *files*
are deleted, never its row: the record, its joint snapshot, its registrations and verifications
stay, marked with ``files_deleted_at`` and a ``retention_log`` row, and a ``scan_files_deleted``
event is published.
Never deleted: the folders of the scans :func:`protected_scan_ids` names (the current registration's
scan; the active calibration's scans once calibrations exist), folders outside ``watch_dir`` and the
C-STORE intake folder (``dicom-intake/``; never the database, audit log or calibrations),
and those roots themselves.  Several series in one folder share its fate: the folder is kept while any of
them is protected.
"""

from __future__ import annotations

import contextlib
import logging
import os
import shutil
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from datetime import UTC, datetime, timedelta
from pathlib import Path

from registration.dicom.files import is_inside
from service.events import Publish, ScanFilesDeleted
from service.store import Database

log = logging.getLogger(__name__)

Protector = Callable[[Database], set[int]]
"""``protector(db)`` → scan ids whose files must be kept."""


def current_registration_scans(db: Database) -> set[int]:
    """The scan behind the current registration (its volume may be needed again: verify, re-detect)."""
    cur = db.registrations.current()
    return {cur.scan_id} if cur is not None and cur.scan_id is not None else set()


def active_calibration_scans(db: Database) -> set[int]:
    """The scans behind the active calibration (keep their files: the calibration's provenance)."""
    act = db.calibrations.active()
    return set(act.scan_ids) if act is not None else set()


PROTECTORS: list[Protector] = [current_registration_scans, active_calibration_scans]
"""What retention never deletes: the current registration's scan and the active calibration's."""


def protected_scan_ids(db: Database) -> set[int]:
    """Every scan id a :data:`PROTECTORS` entry protects."""
    out: set[int] = set()
    for protect in PROTECTORS:
        out |= protect(db)
    return out


@dataclass(frozen=True)
class Deletion:
    folder: Path
    scan_ids: tuple[int, ...]
    n_bytes: int
    reason: str


def folder_bytes(folder: Path) -> int:
    """Bytes of the regular files under ``folder`` (links not followed)."""
    total = 0
    for dirpath, _dirs, files in os.walk(folder):
        for name in files:
            try:
                st = os.lstat(os.path.join(dirpath, name))
            except OSError:
                continue
            total += st.st_size if not os.path.islink(os.path.join(dirpath, name)) else 0
    return total


def _candidates(db: Database) -> list[tuple[Path, list[int], datetime]]:
    """Scan folders not deleted yet, oldest arrival first: (folder, scan ids, arrived)."""
    by_folder: dict[Path, tuple[list[int], datetime]] = {}
    for scan_id, folder, arrived_at in db.scans.with_files():
        p = Path(folder)
        try:
            arrived = datetime.fromisoformat(arrived_at)
        except ValueError:
            arrived = datetime.now(UTC)
        if arrived.tzinfo is None:
            arrived = arrived.replace(tzinfo=UTC)
        ids, first = by_folder.get(p, ([], arrived))
        by_folder[p] = ([*ids, scan_id], max(first, arrived))  # a folder is as young as its newest scan
    return sorted(((p, ids, t) for p, (ids, t) in by_folder.items()), key=lambda c: c[2])


def _inside_a_root(folder: Path, roots: Sequence[Path]) -> bool:
    """Strictly inside one of ``roots`` (a root itself is never deleted)."""
    real = os.path.realpath(folder)
    return any(is_inside(folder, r) and real != os.path.realpath(r) for r in roots if r.is_dir())


def plan(
    db: Database,
    watch_dir: Path,
    *,
    max_age_days: float | None,
    max_disk_mb: float | None,
    now: datetime,
    extra_roots: Sequence[Path] = (),
) -> list[Deletion]:
    """What :func:`run_retention` would delete (nothing is touched)."""
    return _plan(db, (watch_dir, *extra_roots), max_age_days, max_disk_mb, now)[0]


def _plan(
    db: Database, roots: Sequence[Path], max_age_days: float | None, max_disk_mb: float | None, now: datetime
) -> tuple[list[Deletion], int]:
    """The deletions and the bytes the scan folders would still use after them."""
    protected = protected_scan_ids(db)
    cands = [c for c in _candidates(db) if c[0].is_dir() and _inside_a_root(c[0], roots)]
    sizes = {c[0]: folder_bytes(c[0]) for c in cands}
    total = sum(sizes.values())
    out: list[Deletion] = []
    for folder, ids, arrived in cands:
        if protected & set(ids):
            continue
        reason = ""
        if max_age_days is not None and now - arrived > timedelta(days=max_age_days):
            reason = f"older than retention.max_age_days = {max_age_days:g} (arrived {arrived.isoformat()})"
        elif max_disk_mb is not None and total > max_disk_mb * 1024**2:
            reason = (
                f"intake scans use {total / 1024**2:.1f} MB, more than "
                f"retention.max_disk_mb = {max_disk_mb:g}; "
                "oldest first"
            )
        if reason:
            out.append(Deletion(folder, tuple(ids), sizes[folder], reason))
            total -= sizes[folder]
    return out, total


def quota_problem(
    db: Database, watch_dir: Path, *, max_disk_mb: float | None, extra_roots: Sequence[Path] = ()
) -> str | None:
    """None while the scan folders fit ``retention.max_disk_mb`` once retention has run; else why
    not (what is kept is protected: the current registration's scan, the active calibration's)."""
    if max_disk_mb is None:
        return None
    _, left = _plan(db, (watch_dir, *extra_roots), None, max_disk_mb, datetime.now(UTC))
    if left <= max_disk_mb * 1024**2:
        return None
    return (
        f"retention cannot keep the quota: the scan folders use {left / 1024**2:.1f} MB after deleting "
        f"every unprotected scan, more than retention.max_disk_mb = {max_disk_mb:g} (the rest is protected: "
        "the current registration's and the active calibration's scans); raise the quota or free disk space"
    )


def run_retention(
    db: Database,
    watch_dir: Path,
    publish: Publish,
    *,
    max_age_days: float | None,
    max_disk_mb: float | None,
    now: datetime | None = None,
    extra_roots: Sequence[Path] = (),
) -> list[Deletion]:
    """Delete what :func:`plan` says; log, record and publish each deletion.  Returns them.

    ``extra_roots``: scan folders outside ``watch_dir`` that the service keeps (``dicom-intake/``).
    A deletion is not a change of the scan's content: nothing is withdrawn."""
    if max_age_days is None and max_disk_mb is None:
        return []
    done: list[Deletion] = []
    for d in plan(
        db, watch_dir, max_age_days=max_age_days, max_disk_mb=max_disk_mb, now=now or datetime.now(UTC),
        extra_roots=extra_roots,
    ):  # fmt: skip
        try:
            shutil.rmtree(d.folder)
        except OSError as e:
            log.error("retention: cannot delete %s (%s); kept", d.folder, e)
            continue
        if any(is_inside(d.folder.parent, r) and d.folder.parent != r for r in extra_roots):
            with contextlib.suppress(OSError):
                d.folder.parent.rmdir()  # a C-STORE study folder left empty
        for scan_id in d.scan_ids:
            db.scans.mark_files_deleted(scan_id, str(d.folder), d.n_bytes, d.reason)
        log.warning(
            "retention: deleted %s (%d bytes, scans %s): %s", d.folder, d.n_bytes, list(d.scan_ids), d.reason
        )
        publish(ScanFilesDeleted(scan_ids=d.scan_ids, folder=str(d.folder), bytes=d.n_bytes, reason=d.reason))
        done.append(d)
    return done
