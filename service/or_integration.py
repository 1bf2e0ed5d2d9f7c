"""Operating-room integration: the DICOM Storage SCP and the OpenIGTLink server inside the service.

:class:`OrIntegration` is built by the app factory and started / stopped by its lifespan.  It
reacts to the bus (:meth:`service.event_bus.EventBus.listen`): ``registration_done`` /
``registration_refused`` push to the IGTL clients (and queue the PACS export), ``scan_arrived``
starts auto-register; everything else publishes on the bus directly.

* **C-STORE** (``[dicom]``): instances land in ``<data_dir>/dicom-intake/<Study>/<Series>/``
  (outside the watched folder, so the folder watcher never sees them) and are decoded as they
  arrive (:mod:`service.series_accumulator`).  At association release each series it touched
  goes through the same checks and records as the folder path (:class:`service.intake.Intake`):
  complete once the loader's checks pass and every instance the association offered for it was
  stored, no quiet period (:mod:`service.scan_lifecycle`).  An instance added to or replacing
  one of a judged series moves it to ``reopened`` / ``replaced`` and withdraws what was made from
  it *before* the file is renamed into place (:meth:`OrIntegration._before_replace`); the series is
  judged again at release (same id); an identical re-send changes nothing; an aborted association
  records its partial series ``invalid`` with the reason (a complete series it did not change
  stays complete); a refusal (peer, calling AE, an MR context, a bad dataset) is logged and
  published.  pynetdicom's threads hop to the service loop with
  ``call_soon_threadsafe``; loading and recording run on a worker thread.
* **OpenIGTLink** (``[igtl]``): :class:`service.igtl.server.IgtlServer` on the service loop, fed
  from the current registration (plus the last refusal), the live joints and link health, the
  robot model's forward kinematics and ``igtl.tool0_from_tcp``; pushed at once after a
  registration becomes current or is refused.
* **PACS archive** (``[pacs]``): :class:`service.pacs.exporter.PacsExporter` queues the
  Spatial Registration object of each accepted registration and sends it by C-STORE.
* **Auto-register** (``service.auto_register``): each scan recorded complete is registered on a
  worker thread; the result is pushed like any other.

Events (``GET /events``): ``dicom_association_released``, ``dicom_association_aborted``,
``dicom_refused``, ``igtl_client_connected``, ``igtl_client_header_version`` (it sent a version-2
message: answered in version 2 from then on), ``igtl_client_disconnected``, plus the intake's
``scan_arrived`` / ``scan_invalid`` (with ``"source": "dicom"``).
"""

from __future__ import annotations

import asyncio
import logging
import threading
from collections.abc import Callable, Sequence
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import TYPE_CHECKING, Any, Protocol

import numpy as np

from registration.errors import OarmRegError
from service.dicom_scp import DicomScpConfig, ScpCallbacks, ScpRefusal, StorageScp
from service.igtl.server import (
    IgtlServer,
    IgtlServerConfig,
    IgtlStateSource,
    JointView,
    Refusal,
    RegistrationState,
    RegistrationView,
)
from service.intake import Intake
from service.pacs.exporter import PacsExporter
from service.records import RegistrationRecord, RegistrationRefusal
from service.scan_lifecycle import ContentChange, OfferTally, ScanLifecycle, hash_files
from service.series_accumulator import SeriesAccumulator
from service.store.scan_instances import SRO_PATIENT_STUDY_KEYS, ScanInstances
from service.watcher import SeriesArrival

if TYPE_CHECKING:
    from drivers.base import RobotLink
    from registration.model.kinematics import RobotModel
    from service.capture import Capture
    from service.event_bus import EventBus
    from service.orchestrator import Orchestrator
    from service.settings import Settings
    from service.store import Database
    from service.volume_cache import VolumeCache


class ServiceParts(Protocol):
    """What this module uses of :class:`service.context.ServiceContext` (no import: no cycle)."""

    @property
    def settings(self) -> Settings: ...
    @property
    def bus(self) -> EventBus: ...
    @property
    def db(self) -> Database: ...
    @property
    def capture(self) -> Capture: ...
    @property
    def volumes(self) -> VolumeCache: ...
    @property
    def orchestrator(self) -> Orchestrator: ...
    @property
    def robot_model(self) -> RobotModel: ...
    @property
    def robot_link(self) -> RobotLink: ...


log = logging.getLogger(__name__)

INTAKE_FOLDER = "dicom-intake"
"""Under ``data_dir``: where C-STORE instances are written."""

DECODE_WORKERS = 2
"""Threads decoding C-STORE instances as they arrive (one per core of the 2-core reference machine:
under load one fell behind the SCU, so release waited for its backlog)."""


class OrIntegration:
    """The DICOM SCP, the OpenIGTLink server and auto-register of one service (see the module docstring)."""

    def __init__(self, ctx: ServiceParts) -> None:
        self.ctx = ctx
        self.settings = ctx.settings
        self.scp: StorageScp | None = None
        self.igtl: IgtlServer | None = None
        self._loop: asyncio.AbstractEventLoop | None = None
        self._accumulators: dict[Path, SeriesAccumulator] = {}
        self._decoder: ThreadPoolExecutor | None = None
        self._registrar: ThreadPoolExecutor | None = None
        self._tasks: set[asyncio.Task[None]] = set()
        self._last_refusal: Refusal | None = None
        self._view: tuple[RegistrationRecord, RegistrationView] | None = None
        self.intake: Intake | None = None
        self.lifecycle: ScanLifecycle | None = None
        """Set by the app before :meth:`start` (shared with the folder watcher's intake)."""
        self.pacs: PacsExporter | None = None
        for event, fn in self._listeners():  # until stop(): a restarted app builds a new one
            ctx.bus.listen(event, fn)

    @property
    def intake_dir(self) -> Path:
        return self.settings.data_dir / INTAKE_FOLDER

    # ---- events ---------------------------------------------------------------------------

    def _listeners(self) -> tuple[tuple[str, Callable[[dict[str, Any]], None]], ...]:
        return (
            ("registration_done", self._on_registration_done),
            ("registration_refused", self._on_registration_refused),
            ("scan_arrived", self._on_scan_arrived),
        )

    def _on_registration_done(self, data: dict[str, Any]) -> None:
        """IGTL push of the new current registration; its SRO queued for the PACS."""
        self._last_refusal = None
        self._notify()
        if self.pacs is not None:
            self._enqueue_export(int(data["registration_id"]))

    def _on_registration_refused(self, data: dict[str, Any]) -> None:
        """IGTL push of the refusal (the current registration, if any, stays)."""
        self._last_refusal = Refusal(str(data.get("registration_id")), str(data.get("reason", "")))
        self._notify()

    def _on_scan_arrived(self, data: dict[str, Any]) -> None:
        """Auto-register: each scan recorded complete, on a worker thread."""
        if self.settings.service.auto_register and self._registrar is not None:
            self._registrar.submit(self._auto_register, int(data["scan_id"]))

    def _enqueue_export(self, registration_id: int) -> None:
        assert self.pacs is not None
        try:
            self.pacs.enqueue(registration_id)
        except Exception:  # the registration stands; the worker's start-up sweep queues it later
            log.exception("PACS export: could not queue registration %d", registration_id)

    def _notify(self) -> None:
        if self.igtl is not None:
            self.igtl.notify()

    def _auto_register(self, scan_id: int) -> None:
        try:
            rec = self.ctx.orchestrator.register(scan_id)
        except Exception as e:  # nothing to register (the scan went away meanwhile)
            log.warning("auto-register: scan %d not registered: %s", scan_id, e)
            return
        if isinstance(rec, RegistrationRefusal):  # stored and published by the orchestrator
            log.warning("auto-register: scan %d refused (registration %s): %s", scan_id,
                        rec.registration_id, rec.error)  # fmt: skip
        else:
            log.info(
                "auto-register: scan %d → registration %d (FRE %.3f mm)", scan_id, rec.id, rec.fre_mm or 0
            )

    # ---- lifecycle ------------------------------------------------------------------------

    async def start(self) -> None:
        self._loop = asyncio.get_running_loop()
        if self.settings.service.auto_register:
            self._registrar = _started(ThreadPoolExecutor(1, thread_name_prefix="oarmreg-autoreg"))
        d = self.settings.dicom
        if d.enabled:
            if self.lifecycle is None:
                self.lifecycle = ScanLifecycle(
                    self.ctx.db, self.ctx.volumes, self.ctx.bus.publish, self.ctx.orchestrator.withdraw_scan
                )
            self.intake = Intake(
                self.ctx.db, self.ctx.capture, self.ctx.volumes, self.ctx.bus.publish,
                withdraw=self.ctx.orchestrator.withdraw_scan, lifecycle=self.lifecycle,
            )  # fmt: skip
            self._decoder = _started(
                ThreadPoolExecutor(DECODE_WORKERS, thread_name_prefix="oarmreg-dicom-decode")
            )
            cfg = DicomScpConfig(
                enabled=True, host=d.host, ae_title=d.ae_title, port=d.port,
                allowed_calling_ae_titles=d.allowed_calling_ae_titles,
                allowed_peer_addresses=d.allowed_peer_addresses,
                acse_timeout_s=d.acse_timeout_s, dimse_timeout_s=d.dimse_timeout_s,
                network_timeout_s=d.network_timeout_s, socket_timeout_s=d.socket_timeout_s,
                maximum_associations=d.maximum_associations, max_instance_mb=d.max_instance_mb,
            )  # fmt: skip
            callbacks = ScpCallbacks(
                on_series_settled=self._hop(self._on_released),
                before_replace=self._before_replace,
                on_association_aborted=self._hop(self._on_aborted),
                on_refused=self._hop(self._on_refused),
                on_instance_stored=self._on_instance_stored,
            )
            self.scp = StorageScp(cfg, self.intake_dir, callbacks)
            await asyncio.to_thread(self.scp.start)
        if self.settings.pacs.enabled:
            self.pacs = PacsExporter(
                self.ctx.db, self.settings.pacs, self.settings.data_dir, self.ctx.bus.publish
            )
            await asyncio.to_thread(self.pacs.start)
        g = self.settings.igtl
        if g.enabled:
            source = IgtlStateSource(
                registration=self._registration_state,
                joints=self._joints,
                robot_from_tool0=self.ctx.robot_model.robot_from_tool0,
                tool0_from_tcp=g.tool0_from_tcp.matrix(),
            )
            cfg_i = IgtlServerConfig(
                host=g.host, port=g.port, allowed_peer_addresses=g.allowed_peer_addresses, period_s=g.period_s
            )
            self.igtl = IgtlServer(cfg_i, source, on_client=self._on_igtl_client)
            await self.igtl.start()

    async def stop(self) -> None:
        """Stop accepting, finish the series being recorded, stop the servers."""
        for event, fn in self._listeners():
            self.ctx.bus.unlisten(event, fn)
        if self.scp is not None:
            await asyncio.to_thread(self.scp.stop)
        if self._tasks:
            await asyncio.gather(*list(self._tasks), return_exceptions=True)
        if self.igtl is not None:
            await self.igtl.stop()
        if self.pacs is not None:
            await asyncio.to_thread(self.pacs.stop)
        for ex in (self._decoder, self._registrar):
            if ex is not None:
                await asyncio.to_thread(ex.shutdown, True, cancel_futures=True)

    def status(self) -> dict[str, Any]:
        """For ``GET /status``: each listener's state."""
        d, g = self.settings.dicom, self.settings.igtl
        dicom: dict[str, Any] = {"enabled": d.enabled, "host": d.host, "ae_title": d.ae_title, "port": None}
        if self.scp is not None:
            dicom.update(
                port=self.scp.port,
                associations=self.scp.active_associations,
                counters=dict(self.scp.counters),
                pending_series=len(self._accumulators),
            )
        igtl: dict[str, Any] = {"enabled": g.enabled, "host": g.host, "port": None}
        if self.igtl is not None:
            igtl.update(
                port=self.igtl.port,
                clients=self.igtl.client_count,
                counters=dict(self.igtl.counters),
                peers=self.igtl.client_info(),  # per client: peer and header version
            )
        p = self.settings.pacs
        pacs: dict[str, Any] = {"enabled": p.enabled}
        if self.pacs is not None:
            pacs.update(destination=self.pacs.destination, calling_ae_title=p.calling_ae_title)
        return {
            "dicom": dicom,
            "igtl": igtl,
            "pacs": pacs,
            "tls": self.settings.tls.enabled,
            "auto_register": self.settings.service.auto_register,
        }

    # ---- DICOM callbacks --------------------------------------------------------------------

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

    def _spawn(self, name: str, fn: Callable[[], None]) -> None:
        async def run() -> None:
            try:
                await asyncio.to_thread(fn)
            except Exception:
                log.exception("DICOM intake: %s failed", name)

        task = asyncio.get_running_loop().create_task(run(), name=name)
        self._tasks.add(task)
        task.add_done_callback(self._tasks.discard)

    def _before_replace(self, path: Path, outcome: str) -> None:
        """On the association thread, before a new or different instance is renamed into place: the
        series' first instance opens a ``receiving`` record; an instance added to or replacing one of a
        judged series moves it to ``reopened`` / ``replaced`` and withdraws what was made from it,
        committed before the file is in place (the crash order of docs/safety.md, "Scan lifecycle")."""
        db, series_dir = self.ctx.db, path.parent
        known = db.scans.status_of(series_dir.name)
        if known is None:
            db.scans.start_receiving(series_dir.name, str(series_dir))
            return
        scan_id, status = known
        if status == "receiving" or status == "replaced" or (status == "reopened" and outcome == "stored"):
            return
        scan = db.scans.get(scan_id)
        assert scan is not None and self.lifecycle is not None
        change = (
            ContentChange(replaced=(path.name,))
            if outcome == "replaced"
            else ContentChange(added=(path.name,))
        )
        self.lifecycle.changing(scan, change, f"C-STORE into {series_dir}")

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
        self.ctx.bus.publish(
            "dicom_refused",
            {"kind": refusal.kind, "reason": refusal.reason, "calling_ae": refusal.calling_ae,
             "peer": refusal.peer, "sop_instance_uid": refusal.sop_instance_uid, "status": refusal.status},
        )  # fmt: skip

    def _on_igtl_client(self, event: str, peer: str, n_clients: int, header_version: int) -> None:
        self.ctx.bus.publish(
            f"igtl_client_{event}", {"peer": peer, "clients": n_clients, "header_version": header_version}
        )

    # ---- recording (worker thread) --------------------------------------------------------

    def _arrival(
        self,
        series_dir: Path,
        n: int,
        acc: SeriesAccumulator | None,
        *,
        volume: Any = None,
        error: str = "",
        files: dict[str, tuple[str, int]] | None = None,
    ) -> SeriesArrival:
        import time
        from datetime import UTC, datetime

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

    def _record_released(
        self, series_dir: Path, n: int, calling_ae: str, acc: SeriesAccumulator | None, tally: OfferTally
    ) -> None:
        """The lifecycle's verdict on one series at the end of an association (worker thread)."""
        from registration.dicom import load_series

        uid, db = series_dir.name, self.ctx.db
        prev = db.scans.by_series_uid(uid)
        problem = tally.problem(uid)
        data: dict[str, Any] = {"series_uid": uid, "calling_ae": calling_ae, "n_instances": n}
        unchanged = acc is None or acc.new_instances == 0
        if prev is not None and prev.status == "complete" and unchanged:
            log.info("DICOM: series %s re-sent unchanged by %s; nothing to do%s", uid, calling_ae,
                     f" ({problem})" if problem else "")  # fmt: skip
            self.ctx.bus.publish(
                "dicom_association_released",
                {**data, "outcome": "unchanged", "scan_id": prev.id, "reason": problem},
            )
            return
        if n == 0 and prev is None:  # every instance refused: nothing on disk, nothing to record
            self.ctx.bus.publish(
                "dicom_association_released",
                {**data, "outcome": "refused", "scan_id": None, "reason": problem},
            )
            return
        volume, error = None, ""
        try:
            volume = acc.assemble(uid) if acc is not None else load_series(series_dir, series_uid=uid)
        except (OarmRegError, OSError) as e:
            error = str(e)
        if problem:
            error = problem if not error else f"{problem}. Also: {error}"
        files = hash_files(series_dir.glob("*.dcm"))
        arrival = self._arrival(series_dir, n, acc, volume=volume, error=error, files=files)
        assert self.intake is not None
        self.intake(arrival)
        outcome = "invalid" if error else "complete"
        if prev is not None and prev.status != "receiving":
            outcome = "reopened_invalid" if error else "reopened"
        if volume is not None and not error:
            self.store_instances(
                uid, [Path(f) for f in volume.meta.get("files", ())], sop_uids=volume.meta.get("sop_uids")
            )
        scan = db.scans.by_series_uid(uid)
        self.ctx.bus.publish(
            "dicom_association_released",
            {**data, "outcome": outcome, "scan_id": scan.id if scan else None, "reason": error},
        )

    def _record_aborted(self, accs: list[tuple[Path, SeriesAccumulator | None]], reason: str) -> None:
        assert self.intake is not None
        for series_dir, acc in accs:
            n = sum(1 for _ in series_dir.glob("*.dcm"))
            prev = self.ctx.db.scans.status_of(series_dir.name)
            if prev is not None and prev[1] == "complete" and (acc is None or acc.new_instances == 0):
                continue  # nothing of a complete series changed: it stays complete
            files = hash_files(series_dir.glob("*.dcm"))
            self.intake(self._arrival(series_dir, n, acc, error=reason, files=files))
            self.ctx.bus.publish(
                "dicom_association_aborted",
                {"series_uid": series_dir.name, "n_instances": n, "reason": reason},
            )

    def store_instances(
        self, series_uid: str, files: list[Path], *, sop_uids: Sequence[tuple[str, str]] | None = None
    ) -> None:
        """Record what an SRO references of the series (logged, never raised: the scan is stored)."""
        try:
            self.ctx.db.scan_instances.put(scan_instances_from_files(series_uid, files, sop_uids=sop_uids))
        except Exception:
            log.exception(
                "series %s: could not store its instance UIDs; its SRO will be unavailable", series_uid
            )

    def folder_intake(self, intake: Callable[[SeriesArrival], None]) -> Callable[[SeriesArrival], None]:
        """Wrap the watcher's intake so folder series also store their instance UIDs."""

        def on_series(arrival: SeriesArrival) -> None:
            intake(arrival)
            if arrival.volume is not None and not arrival.error and not arrival.duplicate:
                self.store_instances(
                    arrival.series_uid, [Path(f) for f in arrival.volume.meta.get("files", ())]
                )

        return on_series

    # ---- OpenIGTLink state source (service loop) --------------------------------------------

    def _registration_state(self) -> RegistrationState:
        cur = self.ctx.orchestrator.current
        if cur is None or cur.image_from_robot is None:
            return RegistrationState(None, self._last_refusal)
        cached = self._view
        if cached is None or cached[0] is not cur:
            tre = cur.figures.predicted_tre_mm if cur.figures is not None else ()
            view = RegistrationView(
                image_from_robot=np.asarray(cur.image_from_robot, dtype=np.float64),
                registration_id=str(cur.id),
                fre_mm=float(cur.fre_mm or 0.0),
                tre_pred_mm=max(tre) if tre else None,
                chain_error_mm=None if cur.figures is None else cur.figures.predicted_chain_error_mm,
            )
            cached = self._view = (cur, view)
        return RegistrationState(cached[1], self._last_refusal)

    def _joints(self) -> JointView | None:
        latest = self.ctx.capture.latest()
        if latest is None:
            return None
        h = self.ctx.robot_link.health()
        return JointView(
            tuple(float(v) for v in latest.joints_rad), float(latest.t_s), str(h.state), str(h.reason)
        )


def _started(ex: ThreadPoolExecutor) -> ThreadPoolExecutor:
    """Start every worker of the executor now (each would start on first busy use), so they all live
    as long as the service: one blocking task per worker until all of them run."""
    n = int(getattr(ex, "_max_workers", 1))
    barrier = threading.Barrier(n + 1)
    futures = [ex.submit(barrier.wait, DEADLINE_START_S) for _ in range(n)]
    barrier.wait(DEADLINE_START_S)
    for f in futures:
        f.result()
    return ex


DEADLINE_START_S = 30.0
"""How long starting the executors' workers may take (threads: instant unless the machine is stuck)."""


def scan_instances_from_files(
    series_uid: str, files: list[Path], *, sop_uids: Sequence[tuple[str, str]] | None = None
) -> ScanInstances:
    """Read the headers an SRO needs from the series' files (slice order kept, multi-frame deduplicated).

    ``sop_uids``: the (SOP Instance UID, SOP Class UID) of each slice in slice order when the header
    pass already read them (:mod:`service.series_accumulator`); then only the first file is read, for
    the patient / study attributes (a 192-slice series: 1 file read instead of 192).
    """
    from pydicom import dcmread

    tags = [
        "SOPClassUID",
        "SOPInstanceUID",
        "StudyInstanceUID",
        "FrameOfReferenceUID",
        *SRO_PATIENT_STUDY_KEYS,
    ]
    seen: dict[str, str] = {}
    first: Any = None
    if sop_uids is not None:
        for inst, cls in sop_uids:
            seen.setdefault(inst, cls)
        files = files[:1]
    for f in dict.fromkeys(files):
        ds = dcmread(f, stop_before_pixels=True, specific_tags=tags)
        first = first if first is not None else ds
        if sop_uids is None:
            seen.setdefault(str(ds.SOPInstanceUID), str(ds.SOPClassUID))
    if first is None:
        raise OarmRegError(f"series {series_uid}: no files to read the instance UIDs from")
    attrs = {k: str(first.get(k, "")) for k in SRO_PATIENT_STUDY_KEYS if k in first}
    return ScanInstances(
        series_uid=series_uid,
        study_uid=str(first.get("StudyInstanceUID", "")),
        frame_of_reference_uid=str(first.get("FrameOfReferenceUID", "")),
        sop_class_uids=tuple(seen.values()),
        sop_instance_uids=tuple(seen),
        attributes=attrs,
    )
