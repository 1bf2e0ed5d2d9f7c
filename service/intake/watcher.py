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
(an unloadable series is recorded as ``invalid`` with the reason; so is a folder
with no readable series at all, under the key ``folder:<path>``).  Series
already present when the watcher starts are flagged ``preexisting``: the joints
at their acquisition are unknown.

A quiet period alone does not make a series complete.  The loader
refuses a stack with fewer slices than its ImagesInAcquisition announces, and
late slices of a series already recorded *reopen* it (delivered ``reopened``;
the intake replaces the record and withdraws the registrations made from the
short version) instead of being dropped as a re-export.  Nothing but regular
files is ever opened (``registration.dicom.files``); one folder that raises is
recorded invalid and never stops the others; :meth:`SeriesWatcher.health` says
``stopped`` / ``stalled`` / ``erroring`` when the watcher is not doing its job.
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
from service.intake.recording import SeriesArrival

log = logging.getLogger(__name__)

WATCHDOG_STOP_RACE = "InotifyEmitter.queue_events() called when the thread is inactive"
"""What watchdog (≥ 3, watchdog PR #963) logs at ERROR when its emitter reads once more after
``Observer.stop()`` closed it: a shutdown race inside watchdog that loses nothing (no event can
arrive on a stopped watch).  An ERROR line at every clean stop would teach operators to ignore
ERROR lines, so it is logged at DEBUG instead (:func:`demote_watchdog_stop_race`)."""


def demote_watchdog_stop_race(record: logging.LogRecord) -> bool:
    """Logger filter: :data:`WATCHDOG_STOP_RACE` becomes a DEBUG record; everything else passes."""
    if record.levelno >= logging.ERROR and record.getMessage() == WATCHDOG_STOP_RACE:
        record.levelno, record.levelname = logging.DEBUG, "DEBUG"
        return logging.getLogger(record.name).isEnabledFor(logging.DEBUG)
    return True


EVENT_DEBOUNCE_S = 0.05
"""After a file-system event, wait this long for more before rescanning (a 192-file export fires
hundreds of events)."""


FOLDER_UID_PREFIX = "folder:"
"""Series UID under which a folder with no readable series is recorded (``folder:<path>``)."""


def folder_hashes(folder: Path) -> dict[str, tuple[str, int]]:
    """SHA-256 and size of the regular files directly in ``folder`` (links, FIFOs and devices are never
    opened; hidden temp files skipped): what a folder recorded ``invalid`` is compared with at the next
    start-up, so an unchanged one is not reported as changed."""
    from service.intake.scan_lifecycle import sha256_file

    out: dict[str, tuple[str, int]] = {}
    try:
        entries = sorted(os.scandir(folder), key=lambda e: e.name)
    except OSError:
        return out
    for entry in entries:
        try:
            if entry.name.startswith(".") or not entry.is_file(follow_symlinks=False):
                continue
            out[entry.name] = sha256_file(Path(entry.path))
        except OSError:
            continue  # unreadable: left out, as the loader left it out
    return out


def folder_uid(folder: Path) -> str:
    """The scan key of a folder that holds no readable series (junk, NUL files, link loops, ...)."""
    return FOLDER_UID_PREFIX + str(folder)


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
    folder_errors: int = 0
    reopened: int = 0
    failed_ticks: int = 0
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


def _n_slices(summary: Any) -> int:
    v = getattr(summary, "n_slices", None)
    return int(v) if v is not None else _n_files(summary)


def snapshot_dir(path: Path) -> tuple[frozenset[tuple[str, int, int]], int]:
    """Non-folder entries of one folder as ``(name, size, mtime_ns)`` from ``lstat`` (nothing is opened);
    returns (snapshot, n_visible_files).

    Hidden entries (``.*``, e.g. ``.x.dcm.part`` temp files) are part of the snapshot, so an
    export in progress is never stable, but are not counted as series files.
    """
    entries = []
    visible = 0
    try:
        with os.scandir(path) as it:
            for e in it:
                try:
                    if e.is_dir(follow_symlinks=False):
                        continue
                    # files, links, FIFOs, devices: lstat only (never opened), so a folder holding only
                    # hostile entries is still seen and recorded invalid
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
    recorded_slices : callable, optional
        ``recorded_slices(series_uid)`` → slices of its complete record, or None.  When given, a
        recorded series that grew (late slices) is reloaded and delivered ``reopened`` instead of
        being dropped as a re-export.
    recorded_content : callable, optional
        ``recorded_content(series_uid)`` → ``{name: (sha256, bytes)}`` of its complete record, or None.
    stall_after_s : float
        :meth:`state` reports ``health = "stalled"`` while one folder has been processed for longer.
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
        recorded_slices: Callable[[str], int | None] | None = None,
        stall_after_s: float = 120.0,
        recorded_content: Callable[[str], dict[str, tuple[str, int]] | None] | None = None,
    ) -> None:
        self.watch_dir = Path(watch_dir)
        self.on_series = on_series
        self.is_known = is_known
        self.quiet_period_s = quiet_period_s
        self.poll_interval_s = poll_interval_s
        self.use_polling_only = use_polling_only
        self.recorded_slices = recorded_slices
        self.recorded_content = recorded_content
        """``recorded_content(series_uid)`` → the instance hashes of its complete record, or None; when
        given it replaces ``recorded_slices`` (:mod:`service.intake.scan_lifecycle`: any change of content,
        not only growth, makes the series be judged again)."""
        self.stall_after_s = stall_after_s
        self._busy: tuple[Path, float] | None = None
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

                inotify_log = logging.getLogger("watchdog.observers.inotify")
                if demote_watchdog_stop_race not in inotify_log.filters:
                    inotify_log.addFilter(demote_watchdog_stop_race)
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

    def health(self) -> tuple[str, str]:
        """``(health, why)``: ``ok``, ``stopped`` (thread not alive), ``stalled`` (one folder busy for
        more than ``stall_after_s``) or ``erroring`` (the last scan of the tree failed)."""
        if self._thread is None or not self._thread.is_alive():
            return "stopped", "the watcher thread is not running; restart the service"
        busy = self._busy
        if busy is not None and time.monotonic() - busy[1] > self.stall_after_s:
            return "stalled", (
                f"processing {busy[0]} for {time.monotonic() - busy[1]:.0f} s "
                f"(more than {self.stall_after_s:g} s); "
                "no other folder is scanned meanwhile: check that folder for files that cannot be read"
            )
        if self.stats.failed_ticks:
            return "erroring", f"the last scan of {self.watch_dir} failed: {self.stats.last_error}"
        return "ok", ""

    def state(self) -> dict[str, Any]:
        health, why = self.health()
        busy = self._busy
        with self._lock:
            return {
                "watch_dir": str(self.watch_dir),
                "mode": self.mode,
                "running": health in ("ok", "erroring"),
                "health": health,
                "health_reason": why,
                "busy_folder": "" if busy is None else str(busy[0]),
                "folder_errors": self.stats.folder_errors,
                "junk_folders": self.stats.junk_folders,
                "reopened": self.stats.reopened,
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
                with self._lock:
                    self.stats.failed_ticks = 0
            except Exception as e:  # never let the watcher die; /status says "erroring"
                log.exception("watcher: unexpected error while scanning %s", self.watch_dir)
                with self._lock:
                    self.stats.last_error = f"{type(e).__name__}: {e}"
                    self.stats.failed_ticks += 1
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
            self._busy = (folder, time.monotonic())
            try:
                due = self._tick_folder(folder, now_t_s, first, seen)
            except Exception as e:  # one bad folder never stops the others (MemoryError included)
                due = None
                self._folder_failed(folder, e)
            finally:
                self._busy = None
            if due is not None:
                next_due = due if next_due is None else min(next_due, due)
        for gone in set(self._dirs) - seen:
            del self._dirs[gone]
        with self._lock:
            self.stats.pending = sorted(str(p) for p, s in self._dirs.items() if s.processed != s.snapshot)
            self.stats.last_scan_at = datetime.now(UTC).isoformat()
        return next_due

    def _tick_folder(self, folder: Path, now_t_s: float, first: bool, seen: set[Path]) -> float | None:
        """Snapshot one folder, process it once quiet; the time its quiet period ends (None: done)."""
        snap, n_visible = snapshot_dir(folder)
        if n_visible == 0:
            return None
        seen.add(folder)
        st = self._dirs.get(folder)
        if st is None:
            st = _DirState(snap, now_t_s, now_t_s, datetime.now(UTC), preexisting=first)
            self._dirs[folder] = st
            if not first:
                log.info("watcher: new files in %s", folder)
        elif snap != st.snapshot:
            if st.processed is not None and st.processed != snap and st.snapshot == st.processed:
                # new content after a processed state: a new arrival (late slices, a re-export)
                st.first_seen_t_s = now_t_s
                st.first_seen_at = datetime.now(UTC)
                st.preexisting = False
            st.snapshot = snap
            st.changed_t_s = now_t_s
        if st.processed == st.snapshot:
            return None
        due = st.changed_t_s + self.quiet_period_s
        if now_t_s < due:
            return due
        self._process(folder, st)
        return st.changed_t_s + self.quiet_period_s if st.processed != st.snapshot else None

    def _folder_failed(self, folder: Path, e: BaseException) -> None:
        """Record a folder whose processing raised as ``invalid`` (not retried until it changes)."""
        log.exception("watcher: processing %s failed", folder)
        why = (
            f"processing the folder failed ({type(e).__name__}: {e}); the watcher carries on with the other "
            "folders. Remove or re-export this folder."
        )
        with self._lock:
            self.stats.folder_errors += 1
            self.stats.last_error = f"{folder}: {type(e).__name__}: {e}"
        st = self._dirs.get(folder)
        if st is None:
            return
        st.processed = st.snapshot
        self._deliver_folder_invalid(folder, st, why)

    def _deliver_folder_invalid(self, folder: Path, st: _DirState, reason: str) -> None:
        """Record a folder with no readable series as an ``invalid`` scan (key :func:`folder_uid`)."""
        self._deliver(
            SeriesArrival(
                series_uid=folder_uid(folder),
                folder=folder,
                first_seen_t_s=st.first_seen_t_s,
                last_change_t_s=st.changed_t_s,
                first_seen_at=st.first_seen_at,
                n_files=snapshot_dir(folder)[1],
                error=reason,
                preexisting=st.preexisting,
                files=folder_hashes(folder),
            )
        )

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
        from registration.dicom import read_series_headers

        before = st.snapshot
        try:
            scan = read_series_headers(folder)
        except DicomSeriesError as e:
            if snapshot_dir(folder)[0] != before:
                self._retry_later(folder, st, f"files in {folder} changed while listing ({e})")
                return
            log.warning("watcher: %s holds no usable DICOM series (%s)", folder, e)
            self._junk(folder, st, before, f"no usable DICOM series: {e}")
            return
        except OSError as e:
            self._retry_later(folder, st, f"cannot list {folder}: {e}")
            return
        summaries = list(scan.series)
        if not summaries:
            shown = "; ".join(f"{sk.path.name}: {sk.reason}" for sk in scan.skipped[:4])
            more = f" (+{len(scan.skipped) - 4} more)" if len(scan.skipped) > 4 else ""
            log.info("watcher: %s holds no DICOM series (junk files only?)", folder)
            self._junk(
                folder, st, before,
                f"no readable CT series in {folder}: {len(scan.skipped)} file(s) skipped: {shown}{more}. "
                "Remove the folder or export the series again.",
            )  # fmt: skip
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

    def _junk(self, folder: Path, st: _DirState, before: frozenset[tuple[str, int, int]], why: str) -> None:
        with self._lock:
            self.stats.junk_folders += 1
        st.processed = before
        self._deliver_folder_invalid(folder, st, why)

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
        if self.recorded_content is not None and self.recorded_content(uid) != {}:  # {}: hashes not kept
            return self._process_recorded(folder, st, summary, before, arrival_kw)
        recorded = self._recorded(uid)
        if recorded is not None and _n_slices(summary) <= recorded:
            log.info("watcher: series %s in %s is already recorded (re-export); not reloaded", uid, folder)
            with self._lock:
                self.stats.duplicates += 1
            return self._deliver(SeriesArrival(**arrival_kw, duplicate=True))
        if recorded is not None:  # late slices of a recorded series: it was incomplete
            log.warning(
                "watcher: series %s in %s grew from %d to %d slices after it was recorded; reopening it",
                uid, folder, recorded, _n_slices(summary),
            )  # fmt: skip
            with self._lock:
                self.stats.reopened += 1
            arrival_kw.update(reopened=True, previous_slices=recorded)
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

    def _process_recorded(
        self,
        folder: Path,
        st: _DirState,
        summary: Any,
        before: frozenset[tuple[str, int, int]],
        arrival_kw: dict[str, Any],
    ) -> bool | None:
        """:meth:`_process_series` with the lifecycle's content rule: a series recorded
        complete is a duplicate only if every recorded instance still has its hash and no instance was
        added; any other difference is delivered ``reopened`` with the change, loaded or not."""
        from registration.dicom import load_series
        from service.intake.scan_lifecycle import diff, hash_files, rehash

        assert self.recorded_content is not None
        uid = str(arrival_kw["series_uid"])
        recorded = self.recorded_content(uid)
        if recorded is not None:
            change = rehash(folder, recorded)
            if not change.changed and _n_files(summary) == len(recorded):
                log.info(
                    "watcher: series %s in %s unchanged since it was recorded; not reloaded", uid, folder
                )
                with self._lock:
                    self.stats.duplicates += 1
                return self._deliver(SeriesArrival(**arrival_kw, duplicate=True))
            log.warning(
                "watcher: series %s in %s changed after it was recorded; judging it again", uid, folder
            )
            with self._lock:
                self.stats.reopened += 1
            arrival_kw.update(reopened=True, previous_slices=len(recorded), change=change)
        problem = str(getattr(summary, "problem", "") or "")
        volume = None
        try:
            if problem:
                raise DicomSeriesError(problem)
            volume = load_series(folder, series_uid=uid)
            error = ""
        except (OarmRegError, OSError) as e:
            if snapshot_dir(folder)[0] != before or isinstance(e, FileNotFoundError):
                self._retry_later(
                    folder, st, f"files of series {uid} in {folder} changed while loading ({e})"
                )
                return None
            log.warning("watcher: series %s in %s is not usable: %s", uid, folder, e)
            error = str(e)
        if snapshot_dir(folder)[0] != before:
            self._retry_later(folder, st, f"files of series {uid} in {folder} changed while loading")
            return None
        files = hash_files(Path(f) for f in volume.meta.get("files", ())) if volume is not None else None
        if recorded is not None and files is not None:
            arrival_kw["change"] = diff(recorded, files)
        with self._lock:
            if error:
                self.stats.invalid += 1
            else:
                self.stats.series_recorded += 1
        return self._deliver(SeriesArrival(**arrival_kw, volume=volume, error=error, files=files))

    def _recorded(self, uid: str) -> int | None:
        """Slices of the complete record of ``uid`` (None: not recorded; huge: recorded, count unknown)."""
        if self.recorded_slices is not None:
            return self.recorded_slices(uid)
        return 1 << 30 if self.is_known(uid) else None

    def _deliver(self, arrival: SeriesArrival) -> bool:
        try:
            self.on_series(arrival)
            return True
        except Exception as e:
            log.exception("watcher: recording series %s failed", arrival.series_uid)
            with self._lock:
                self.stats.last_error = f"recording series {arrival.series_uid} failed: {e}"
            return False
