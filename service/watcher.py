"""Watch the O-arm export folder and hand over every complete DICOM series.

A folder export (or a C-STORE receiver) has no end-of-series signal, so a
series counts as complete when (research note §5):

1. the folder's entries (names, sizes, mtimes, ``.*.part`` temp files
   included) have not changed for ``quiet_period_s``, and
2. :func:`registration.dicom.list_series` /
   :func:`~registration.dicom.load_series` build a consistent volume.

Changes are noticed through OS file-system events (watchdog) when available;
the folder tree is also rescanned every ``poll_interval_s`` (the polling
fallback for network shares, inotify limits and lost events).

Handled and logged: several series at once (one folder or many), a re-export
of a series already recorded (deduplicated by SeriesInstanceUID), files
vanishing while a series loads (retried after the next quiet period), junk
files (a folder with no DICOM is recorded nowhere; an unloadable series is
recorded as ``invalid`` with the reason).  Series already present when the
watcher starts are flagged ``preexisting``: the joints at their acquisition
are unknown.
"""

from __future__ import annotations

import logging
import os
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

from registration.errors import DicomSeriesError, OarmRegError
from registration.volume import Volume

log = logging.getLogger(__name__)

EVENT_DEBOUNCE_S = 0.05
"""After a file-system event, wait this long for more before rescanning (a 192-file export fires
hundreds of events)."""


@dataclass(frozen=True)
class SeriesArrival:
    """A series found complete (or found unusable) in the watch folder.

    ``first_seen_t_s`` / ``last_change_t_s`` are ``time.monotonic()`` values: when the
    watcher first saw the folder's current content appear and when it last changed.
    ``volume`` is the loaded :class:`registration.volume.Volume` (None when ``error`` is set
    or when ``duplicate``).
    """

    series_uid: str
    folder: Path
    first_seen_t_s: float
    last_change_t_s: float
    first_seen_at: datetime
    n_files: int
    volume: Volume | None = None
    error: str = ""
    duplicate: bool = False
    preexisting: bool = False


@dataclass
class _DirState:
    snapshot: frozenset[tuple[str, int, int]]
    changed_t_s: float
    first_seen_t_s: float
    first_seen_at: datetime
    preexisting: bool
    processed: frozenset[tuple[str, int, int]] | None = None
    attempts: int = 0


@dataclass
class WatcherStats:
    series_recorded: int = 0
    duplicates: int = 0
    invalid: int = 0
    retries: int = 0
    junk_folders: int = 0
    last_error: str = ""
    last_scan_at: str = ""
    pending: list[str] = field(default_factory=list)


def _series_uid(summary: Any) -> str:
    for attr in ("series_uid", "uid", "series_instance_uid"):
        v = getattr(summary, attr, None)
        if v:
            return str(v)
    if isinstance(summary, dict):
        return str(summary.get("series_uid") or summary.get("uid"))
    raise TypeError(f"series summary without a UID: {summary!r}")


def _n_files(summary: Any) -> int:
    v = getattr(summary, "n_files", None)
    if v is None and isinstance(summary, dict):
        v = summary.get("n_files")
    return int(v or 0)


def snapshot_dir(path: Path) -> tuple[frozenset[tuple[str, int, int]], int]:
    """Entries of one folder as ``(name, size, mtime_ns)``; returns (snapshot, n_visible_files).

    Hidden entries (``.*``, e.g. ``.x.dcm.part`` temp files) are part of the snapshot, so an
    export in progress is never stable, but are not counted as series files.
    """
    entries = []
    visible = 0
    try:
        with os.scandir(path) as it:
            for e in it:
                try:
                    if not e.is_file(follow_symlinks=False):
                        continue
                    st = e.stat(follow_symlinks=False)
                except FileNotFoundError:
                    continue  # vanished between listing and stat
                entries.append((e.name, st.st_size, st.st_mtime_ns))
                if not e.name.startswith("."):
                    visible += 1
    except (FileNotFoundError, NotADirectoryError):
        return frozenset(), 0
    return frozenset(entries), visible


class SeriesWatcher:
    """Background thread that finds complete series under ``watch_dir``.

    Parameters
    ----------
    watch_dir : Path
        Folder to watch (created if missing); every sub-folder is scanned.
    on_series : callable
        Called on the watcher thread with each :class:`SeriesArrival` (complete, invalid or
        duplicate).  An exception it raises is logged and the series retried later.
    is_known : callable
        ``is_known(series_uid)`` → True if a complete scan with that UID is already recorded
        (a re-export is then reported as a duplicate without loading the pixels).
    quiet_period_s, poll_interval_s : float
        Stability period and rescan interval, s.
    use_polling_only : bool
        Never use OS file-system events.
    """

    def __init__(
        self,
        watch_dir: Path,
        *,
        on_series: Callable[[SeriesArrival], None],
        is_known: Callable[[str], bool] = lambda uid: False,
        quiet_period_s: float = 2.0,
        poll_interval_s: float = 1.0,
        use_polling_only: bool = False,
    ) -> None:
        self.watch_dir = Path(watch_dir)
        self.on_series = on_series
        self.is_known = is_known
        self.quiet_period_s = quiet_period_s
        self.poll_interval_s = poll_interval_s
        self.use_polling_only = use_polling_only
        self.mode = "stopped"
        self.stats = WatcherStats()
        self._dirs: dict[Path, _DirState] = {}
        self._wake = threading.Event()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._observer: Any = None
        self._first_tick = True
        self._lock = threading.Lock()

    # ---- lifecycle ------------------------------------------------------------------------

    def start(self) -> None:
        """Create the folder if needed, start OS events (or fall back to polling) and the thread."""
        self.watch_dir.mkdir(parents=True, exist_ok=True)
        self._stop.clear()
        self.mode = "polling"
        if not self.use_polling_only:
            try:
                from watchdog.events import FileSystemEvent, FileSystemEventHandler
                from watchdog.observers import Observer

                wake = self._wake

                class _Handler(FileSystemEventHandler):
                    def on_any_event(self, event: FileSystemEvent) -> None:
                        wake.set()

                obs = Observer()
                obs.daemon = True
                obs.schedule(_Handler(), str(self.watch_dir), recursive=True)
                obs.start()
                self._observer = obs
                self.mode = "events+polling"
            except Exception as e:  # inotify limits, unsupported file systems, ...
                log.warning(
                    "watcher: file-system events unavailable for %s (%s); polling every %.2g s",
                    self.watch_dir,
                    e,
                    self.poll_interval_s,
                )
                self._observer = None
        self._thread = threading.Thread(target=self._run, name="oarmreg-watcher", daemon=True)
        self._thread.start()
        log.info(
            "watcher: watching %s (%s, quiet period %.2g s)", self.watch_dir, self.mode, self.quiet_period_s
        )

    def stop(self, timeout_s: float = 10.0) -> None:
        self._stop.set()
        self._wake.set()
        if self._observer is not None:
            try:
                self._observer.stop()
                self._observer.join(timeout_s)
            except Exception:  # pragma: no cover - shutdown best effort
                log.exception("watcher: stopping the observer failed")
            self._observer = None
        if self._thread is not None:
            self._thread.join(timeout_s)
            self._thread = None
        self.mode = "stopped"

    def state(self) -> dict[str, Any]:
        with self._lock:
            return {
                "watch_dir": str(self.watch_dir),
                "mode": self.mode,
                "running": self._thread is not None and self._thread.is_alive(),
                "quiet_period_s": self.quiet_period_s,
                "series_recorded": self.stats.series_recorded,
                "duplicates": self.stats.duplicates,
                "invalid": self.stats.invalid,
                "retries": self.stats.retries,
                "pending_folders": list(self.stats.pending),
                "last_error": self.stats.last_error,
                "last_scan_at": self.stats.last_scan_at,
            }

    # ---- loop -----------------------------------------------------------------------------

    def _run(self) -> None:
        while not self._stop.is_set():
            try:
                next_due = self.tick(time.monotonic())
            except Exception as e:  # never let the watcher die
                log.exception("watcher: unexpected error while scanning %s", self.watch_dir)
                with self._lock:
                    self.stats.last_error = f"{type(e).__name__}: {e}"
                next_due = None
            timeout = self.poll_interval_s
            if next_due is not None:
                timeout = max(0.01, min(timeout, next_due - time.monotonic()))
            if self._wake.wait(timeout):
                self._wake.clear()
                # coalesce a burst of events
                self._stop.wait(EVENT_DEBOUNCE_S)

    def tick(self, now_t_s: float) -> float | None:
        """One scan of the tree; returns the monotonic time of the next quiet-period expiry (or None).

        Public so tests can drive the watcher deterministically without the thread.
        """
        seen: set[Path] = set()
        next_due: float | None = None
        first = self._first_tick
        self._first_tick = False
        for folder in self._folders():
            snap, n_visible = snapshot_dir(folder)
            if n_visible == 0:
                continue
            seen.add(folder)
            st = self._dirs.get(folder)
            if st is None:
                st = _DirState(snap, now_t_s, now_t_s, datetime.now(UTC), preexisting=first)
                self._dirs[folder] = st
                if not first:
                    log.info("watcher: new files in %s", folder)
            elif snap != st.snapshot:
                if st.processed is not None and st.processed != snap and st.snapshot == st.processed:
                    # new content after a processed state: a new arrival (e.g. re-export)
                    st.first_seen_t_s = now_t_s
                    st.first_seen_at = datetime.now(UTC)
                    st.preexisting = False
                st.snapshot = snap
                st.changed_t_s = now_t_s
            if st.processed == st.snapshot:
                continue
            due = st.changed_t_s + self.quiet_period_s
            if now_t_s < due:
                next_due = due if next_due is None else min(next_due, due)
                continue
            self._process(folder, st)
            if st.processed != st.snapshot:
                due = st.changed_t_s + self.quiet_period_s
                next_due = due if next_due is None else min(next_due, due)
        for gone in set(self._dirs) - seen:
            del self._dirs[gone]
        with self._lock:
            self.stats.pending = sorted(str(p) for p, s in self._dirs.items() if s.processed != s.snapshot)
            self.stats.last_scan_at = datetime.now(UTC).isoformat()
        return next_due

    def _folders(self) -> list[Path]:
        out = []
        for root, dirs, _files in os.walk(self.watch_dir, onerror=lambda e: None):
            dirs[:] = [d for d in dirs if not d.startswith(".")]
            out.append(Path(root))
        return out

    def _retry_later(self, folder: Path, st: _DirState, why: str) -> None:
        st.changed_t_s = time.monotonic()
        st.snapshot, _ = snapshot_dir(folder)
        st.attempts += 1
        with self._lock:
            self.stats.retries += 1
            self.stats.last_error = why
        log.warning("watcher: %s; retrying %s after the next quiet period", why, folder)

    def _process(self, folder: Path, st: _DirState) -> None:
        from registration.dicom import list_series

        before = st.snapshot
        try:
            summaries = list_series(folder)
        except DicomSeriesError as e:
            if snapshot_dir(folder)[0] != before:
                self._retry_later(folder, st, f"files in {folder} changed while listing ({e})")
                return
            log.warning("watcher: ignoring %s: no usable DICOM series (%s)", folder, e)
            with self._lock:
                self.stats.junk_folders += 1
            st.processed = before
            return
        except OSError as e:
            self._retry_later(folder, st, f"cannot list {folder}: {e}")
            return
        if not summaries:
            log.info("watcher: %s holds no DICOM series (junk files only?); ignored", folder)
            with self._lock:
                self.stats.junk_folders += 1
            st.processed = before
            return
        retry = False
        for summary in summaries:
            outcome = self._process_series(folder, st, summary, before)
            if outcome is None:
                return  # the folder changed: retried after the next quiet period
            retry |= not outcome
        if retry:
            with self._lock:
                why = self.stats.last_error
            self._retry_later(folder, st, f"recording a series from {folder} failed ({why})")
        else:
            st.processed = before

    def _process_series(
        self, folder: Path, st: _DirState, summary: Any, before: frozenset[tuple[str, int, int]]
    ) -> bool | None:
        """Load and deliver one series of ``folder``: True if recorded, False if recording failed,
        None if the folder changed meanwhile (a retry is already scheduled)."""
        from registration.dicom import load_series

        uid = _series_uid(summary)
        arrival_kw: dict[str, Any] = {
            "series_uid": uid,
            "folder": folder,
            "first_seen_t_s": st.first_seen_t_s,
            "last_change_t_s": st.changed_t_s,
            "first_seen_at": st.first_seen_at,
            "n_files": _n_files(summary),
            "preexisting": st.preexisting,
        }
        if self.is_known(uid):
            log.info("watcher: series %s in %s is already recorded (re-export); not reloaded", uid, folder)
            with self._lock:
                self.stats.duplicates += 1
            return self._deliver(SeriesArrival(**arrival_kw, duplicate=True))
        problem = str(getattr(summary, "problem", "") or "")
        if problem:
            if snapshot_dir(folder)[0] != before:
                self._retry_later(folder, st, f"files of series {uid} in {folder} changed while listing")
                return None
            log.warning("watcher: series %s in %s is not usable: %s", uid, folder, problem)
            with self._lock:
                self.stats.invalid += 1
            return self._deliver(SeriesArrival(**arrival_kw, error=problem))
        try:
            volume = load_series(folder, series_uid=uid)
        except (OarmRegError, OSError) as e:
            if snapshot_dir(folder)[0] != before or isinstance(e, FileNotFoundError):
                why = f"files of series {uid} in {folder} changed while loading ({e})"
                self._retry_later(folder, st, why)
                return None
            log.warning("watcher: series %s in %s is not usable: %s", uid, folder, e)
            with self._lock:
                self.stats.invalid += 1
            return self._deliver(SeriesArrival(**arrival_kw, error=str(e)))
        if snapshot_dir(folder)[0] != before:
            self._retry_later(folder, st, f"files of series {uid} in {folder} changed while loading")
            return None
        log.info(
            "watcher: series %s complete in %s (%d slices, first seen %.2f s ago)",
            uid, folder, volume.shape[0], time.monotonic() - st.first_seen_t_s,
        )  # fmt: skip
        with self._lock:
            self.stats.series_recorded += 1
        return self._deliver(SeriesArrival(**arrival_kw, volume=volume))

    def _deliver(self, arrival: SeriesArrival) -> bool:
        try:
            self.on_series(arrival)
            return True
        except Exception as e:
            log.exception("watcher: recording series %s failed", arrival.series_uid)
            with self._lock:
                self.stats.last_error = f"recording series {arrival.series_uid} failed: {e}"
            return False
