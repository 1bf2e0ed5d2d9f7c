"""The C-STORE intake: scans the O-arm sends by DICOM, recorded like the folder's (``[dicom]``).

Instances land in ``<data_dir>/dicom-intake/<Study>/<Series>/`` (outside the watched folder, so the
folder watcher never sees them) and are decoded as they arrive (:mod:`service.intake.series_accumulator`).
At association release each series it touched goes through the same checks and records as the
folder path (:class:`service.intake.recording.Intake`): complete once the loader's checks pass and every
instance the association offered for it was stored, no quiet period (:mod:`service.intake.scan_lifecycle`).
An instance added to or replacing one of a judged series moves it to ``reopened`` / ``replaced`` and
withdraws what was made from it *before* the file is renamed into place
(:meth:`CStoreIntake._before_replace`); the series is judged again at release (same id); an identical
re-send changes nothing; an aborted association records its partial series ``invalid`` with the
reason (a complete series it did not change stays complete); a refusal (peer, calling AE, an MR
context, a bad dataset) is logged and published.  pynetdicom's threads hop to the service loop with
``call_soon_threadsafe``; loading and recording run on a worker thread.

Events: :class:`~service.events.DicomAssociationReleased`,
:class:`~service.events.DicomAssociationAborted`, :class:`~service.events.DicomRefused`, plus the
intake's ``scan_arrived`` / ``scan_invalid`` (with ``"source": "dicom"``).  It listens to nothing.
"""

from __future__ import annotations

import asyncio
import logging
import time
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from datetime import UTC, datetime
from pathlib import Path
from typing import TYPE_CHECKING, Any

from registration.errors import OarmRegError
from service.events import (
    DicomAssociationAborted,
    DicomAssociationReleased,
    DicomRefused,
    Publish,
    ReleaseOutcome,
)
from service.intake.recording import Intake, SeriesArrival
from service.intake.scan_lifecycle import ContentChange, OfferTally, ScanLifecycle, hash_files
from service.intake.series_accumulator import SeriesAccumulator
from service.intake.storage_scp import ScpCallbacks, ScpRefusal, StorageScp
from service.workers import started_executor

if TYPE_CHECKING:
    from registration.imaging.volume import Volume
    from service.settings import DicomSettings
    from service.store import Database

log = logging.getLogger(__name__)

INTAKE_FOLDER = "dicom-intake"
"""Under ``data_dir``: where C-STORE instances are written."""

DECODE_WORKERS = 2
"""Threads decoding C-STORE instances as they arrive (one per core of the 2-core reference machine:
under load one fell behind the SCU, so release waited for its backlog)."""


class CStoreIntake:
    """The DICOM Storage SCP feeding :class:`service.intake.recording.Intake` (see the module docstring).

    Built with everything it needs; :meth:`start` opens the port (on the service loop),
    :meth:`stop` stops accepting and finishes the series being recorded.
    """

    def __init__(
        self,
        settings: DicomSettings,
        intake_dir: Path,
        db: Database,
        intake: Intake,
        lifecycle: ScanLifecycle,
        publish: Publish,
    ) -> None:
        self.settings = settings
        self.intake_dir = intake_dir
        self.db = db
        self.intake = intake
        self.lifecycle = lifecycle
        self.publish = publish
        self._loop: asyncio.AbstractEventLoop | None = None
        self._accumulators: dict[Path, SeriesAccumulator] = {}
        self._decoder: ThreadPoolExecutor | None = None
        self._tasks: set[asyncio.Task[None]] = set()
        callbacks = ScpCallbacks(
            on_series_settled=self._hop(self._on_released),
            before_replace=self._before_replace,
            on_association_aborted=self._hop(self._on_aborted),
            on_refused=self._hop(self._on_refused),
            on_instance_stored=self._on_instance_stored,
        )
        self.scp = StorageScp(settings, intake_dir, callbacks)

    async def start(self) -> None:
        self._loop = asyncio.get_running_loop()
        self._decoder = started_executor(DECODE_WORKERS, "oarmreg-dicom-decode")
        try:
            await asyncio.to_thread(self.scp.start)
        except BaseException:
            await asyncio.to_thread(self._decoder.shutdown, True, cancel_futures=True)
            raise

    async def stop(self) -> None:
        """Stop accepting, finish the series being recorded, stop the decoders."""
        await asyncio.to_thread(self.scp.stop)
        if self._tasks:
            await asyncio.gather(*list(self._tasks), return_exceptions=True)
        if self._decoder is not None:
            await asyncio.to_thread(self._decoder.shutdown, True, cancel_futures=True)

    def status(self) -> dict[str, Any]:
        """For ``GET /status`` (``listeners.dicom``)."""
        d = self.settings
        return {
            "enabled": d.enabled, "host": d.host, "ae_title": d.ae_title, "port": self.scp.port,
            "associations": self.scp.active_associations, "counters": dict(self.scp.counters),
            "pending_series": len(self._accumulators),
            "allowed_callers": self.scp.allow_list,
        }  # fmt: skip

    # ---- pynetdicom's threads -------------------------------------------------------------

    def _hop(self, fn: Callable[..., None]) -> Callable[..., None]:
        """A callback for pynetdicom's threads that runs ``fn`` on the service loop."""

        def on_thread(*args: Any) -> None:
            loop = self._loop
            if loop is not None and not loop.is_closed():
                try:
                    loop.call_soon_threadsafe(fn, *args)
                except RuntimeError:  # the loop closed meanwhile (shutdown)
                    log.warning("DICOM: %s dropped at shutdown", getattr(fn, "__name__", fn))

        return on_thread

    def _on_instance_stored(self, path: Path, outcome: str) -> None:
        # on the association thread: only queue the decode
        acc = self._accumulators.get(path.parent)
        if acc is None:
            assert self._decoder is not None
            acc = self._accumulators.setdefault(path.parent, SeriesAccumulator(path.parent, self._decoder))
        acc.add(path, outcome)

    def _before_replace(self, path: Path, outcome: str) -> None:
        """On the association thread, before a new or different instance is renamed into place: the
        series' first instance opens a ``receiving`` record; an instance added to or replacing one of a
        judged series moves it to ``reopened`` / ``replaced`` and withdraws what was made from it,
        committed before the file is in place (the crash order of docs/safety.md, "Scan lifecycle")."""
        db, series_dir = self.db, path.parent
        known = db.scans.status_of(series_dir.name)
        if known is None:
            db.scans.start_receiving(series_dir.name, str(series_dir))
            return
        scan_id, status = known
        if status == "receiving" or status == "replaced" or (status == "reopened" and outcome == "stored"):
            return
        scan = db.scans.get(scan_id)
        assert scan is not None
        change = (
            ContentChange(replaced=(path.name,))
            if outcome == "replaced"
            else ContentChange(added=(path.name,))
        )
        self.lifecycle.changing(scan, change, f"C-STORE into {series_dir}")

    # ---- the service loop -----------------------------------------------------------------

    def _spawn(self, name: str, fn: Callable[[], None]) -> None:
        async def run() -> None:
            try:
                await asyncio.to_thread(fn)
            except Exception:
                log.exception("DICOM intake: %s failed", name)

        task = asyncio.get_running_loop().create_task(run(), name=name)
        self._tasks.add(task)
        task.add_done_callback(self._tasks.discard)

    def _on_released(self, series_dir: Path, n_instances: int, calling_ae: str, tally: OfferTally) -> None:
        acc = self._accumulators.pop(series_dir, None)
        self._spawn(
            f"dicom-release-{series_dir.name}",
            lambda: self._record_released(series_dir, n_instances, calling_ae, acc, tally),
        )

    def _on_aborted(self, series_dirs: list[Path], reason: str) -> None:
        accs = [(d, self._accumulators.pop(d, None)) for d in series_dirs]
        self._spawn("dicom-abort", lambda: self._record_aborted(accs, reason))

    def _on_refused(self, refusal: ScpRefusal) -> None:
        self.publish(
            DicomRefused(kind=refusal.kind, reason=refusal.reason, calling_ae=refusal.calling_ae,
                         peer=refusal.peer, sop_instance_uid=refusal.sop_instance_uid, status=refusal.status)
        )  # fmt: skip

    # ---- recording (worker thread) --------------------------------------------------------

    def _record_released(
        self, series_dir: Path, n: int, calling_ae: str, acc: SeriesAccumulator | None, tally: OfferTally
    ) -> None:
        """The lifecycle's verdict on one series at the end of an association (worker thread)."""
        from registration.dicom import load_series

        uid, db = series_dir.name, self.db
        prev = db.scans.by_series_uid(uid)
        problem = tally.problem(uid)

        def released(outcome: ReleaseOutcome, scan_id: int | None, reason: str) -> None:
            self.publish(
                DicomAssociationReleased(series_uid=uid, calling_ae=calling_ae, n_instances=n,
                                         outcome=outcome, scan_id=scan_id, reason=reason)
            )  # fmt: skip

        unchanged = acc is None or acc.new_instances == 0
        if prev is not None and prev.status == "complete" and unchanged:
            log.info("DICOM: series %s re-sent unchanged by %s; nothing to do%s", uid, calling_ae,
                     f" ({problem})" if problem else "")  # fmt: skip
            released("unchanged", prev.id, problem)
            return
        if n == 0 and prev is None:  # every instance refused: nothing on disk, nothing to record
            released("refused", None, problem)
            return
        volume: Volume | None = None
        error = ""
        try:
            volume = acc.assemble(uid) if acc is not None else load_series(series_dir, series_uid=uid)
        except (OarmRegError, OSError) as e:
            error = str(e)
        if problem:
            error = problem if not error else f"{problem}. Also: {error}"
        files = hash_files(series_dir.glob("*.dcm"))
        self.intake(_arrival(series_dir, n, acc, volume=volume, error=error, files=files))
        outcome: ReleaseOutcome = "invalid" if error else "complete"
        if prev is not None and prev.status != "receiving":
            outcome = "reopened_invalid" if error else "reopened"
        scan = db.scans.by_series_uid(uid)
        released(outcome, scan.id if scan else None, error)

    def _record_aborted(self, accs: list[tuple[Path, SeriesAccumulator | None]], reason: str) -> None:
        for series_dir, acc in accs:
            n = sum(1 for _ in series_dir.glob("*.dcm"))
            prev = self.db.scans.status_of(series_dir.name)
            if prev is not None and prev[1] == "complete" and (acc is None or acc.new_instances == 0):
                continue  # nothing of a complete series changed: it stays complete
            files = hash_files(series_dir.glob("*.dcm"))
            self.intake(_arrival(series_dir, n, acc, error=reason, files=files))
            self.publish(DicomAssociationAborted(series_uid=series_dir.name, n_instances=n, reason=reason))


def _arrival(
    series_dir: Path,
    n: int,
    acc: SeriesAccumulator | None,
    *,
    volume: Volume | None = None,
    error: str = "",
    files: dict[str, tuple[str, int]] | None = None,
) -> SeriesArrival:
    """The arrival the intake judges, timed by the accumulator (or now, when nothing was decoded)."""
    now = time.monotonic()
    return SeriesArrival(
        series_uid=series_dir.name,
        folder=series_dir,
        first_seen_t_s=acc.first_t_s if acc is not None else now,
        last_change_t_s=acc.last_t_s if acc is not None else now,
        first_seen_at=acc.first_at if acc is not None else datetime.now(UTC),
        n_files=n,
        volume=volume,
        error=error,
        files=files,
        source="dicom",
    )
