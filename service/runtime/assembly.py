"""Start every part of the service in order, bind them to the bus, stop them in reverse.

:func:`running_service` is the whole service as an async context manager, with no web server:
the HTTP app's lifespan (:func:`service.http.app.create_app`) enters it, and it runs without HTTP
too.  The table of who listens to which event is :func:`_start_outputs`
(and :class:`~service.intake.cstore_intake.CStoreIntake` / :class:`~service.intake.recording.Intake`
publish what arrives).
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
from collections.abc import AsyncIterator, Coroutine
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from registration import __version__
from service.data_dir import hold_serve_lock, make_private
from service.event_bus import Subscriptions
from service.events import (
    Publish,
    RegistrationDone,
    RegistrationRefused,
    RegistrationWithdrawn,
    ScanArrived,
    VerificationDone,
)
from service.intake.capture import Capture
from service.intake.cstore_intake import INTAKE_FOLDER, CStoreIntake
from service.intake.recording import Intake
from service.intake.scan_lifecycle import ScanLifecycle
from service.intake.watcher import SeriesWatcher
from service.navigation.igtl.publisher import IgtlPublisher
from service.navigation.pacs.exporter import PacsExporter
from service.registrations.auto_register import AutoRegister
from service.registrations.calibration_jobs import CalibrationJobs
from service.registrations.orchestrator import Orchestrator
from service.runtime.context import ServiceContext, ServiceInputs
from service.runtime.loops import retention_loop, watch_database
from service.settings import Settings
from service.store import Database

log = logging.getLogger(__name__)


@contextlib.asynccontextmanager
async def running_service(
    inputs: ServiceInputs, *, start_watcher: bool = True
) -> AsyncIterator[ServiceContext]:
    """The service, started (:func:`start_service`) and, on leaving, stopped in reverse order.

    ``start_watcher``: False to run without the folder watcher (tests that record scans themselves).
    """
    async with contextlib.AsyncExitStack() as stack:
        yield await start_service(inputs, stack, start_watcher=start_watcher)


async def start_service(
    inputs: ServiceInputs,
    stack: contextlib.AsyncExitStack,
    *,
    start_watcher: bool,
) -> ServiceContext:
    """Start the parts in order, each one's stop pushed on ``stack`` as soon as it runs (a failure
    half-way stops what had started); then build the context, complete.

    Open the database, recover interrupted scan changes, connect the robot link, start the optional
    operating-room pieces and bind them to the bus, start the intakes last (they deliver scans the
    others react to).  Shutdown runs in reverse, except that the SSE streams end and the bus
    listeners are removed first: a series the intakes finish while stopping is recorded but not
    pushed or auto-registered.
    """
    settings, bus = inputs.settings, inputs.bus
    bus.bind(asyncio.get_running_loop())
    db = _open_database(settings, stack)
    core = await _start_core(inputs, db, stack)
    outputs = await _start_outputs(inputs, core, stack)
    watcher = _start_watcher(settings, core, stack) if start_watcher else None
    cstore = await _start_cstore(settings, core, stack, bus.publish)
    stack.callback(outputs.subs.close)  # at shutdown, before the intakes stop (see the docstring)
    stack.callback(bus.close)  # first of all: end the SSE streams

    ctx = ServiceContext(
        settings=settings, bus=bus, phantom=inputs.phantom, robot_model=inputs.robot_model,
        robot_link=inputs.robot_link, volumes=inputs.volumes, started_at=inputs.started_at, db=db,
        capture=core.capture, orchestrator=core.orchestrator,
        calibrations=core.calibrations, watcher=watcher, cstore=cstore, igtl=outputs.igtl,
        pacs=outputs.pacs, auto_register=outputs.auto_register,
    )  # fmt: skip
    if settings.api.auth == "none-loopback-only":
        log.warning(
            "authentication is OFF (api.auth = 'none-loopback-only'): any local process or user can change "
            "the current registration; set api_token and api.auth = 'token' for clinical use"
        )
    _task(stack, retention_loop(ctx), "oarmreg-retention")
    log.info("oarmreg %s: %s", __version__, startup_line(ctx))
    return ctx


@dataclass(frozen=True)
class _Core:
    """What every service runs: the database and what records scans and registrations in it."""

    db: Database
    orchestrator: Orchestrator
    calibrations: CalibrationJobs
    lifecycle: ScanLifecycle
    capture: Capture
    intake: Intake
    intake_dir: Path


@dataclass(frozen=True)
class _Outputs:
    """The bus listeners: auto-registration and the operating-room outputs (each optional)."""

    subs: Subscriptions
    auto_register: AutoRegister | None
    igtl: IgtlPublisher | None
    pacs: PacsExporter | None


def _open_database(settings: Settings, stack: contextlib.AsyncExitStack) -> Database:
    """The private data folder, its serve lock (a second serve on it: exit 3) and the database,
    watched for integrity."""
    make_private(settings.data_dir)  # umask 077, folder 0700, files 0600
    serve_lock = hold_serve_lock(settings.data_dir)
    stack.callback(serve_lock.close)
    db = Database.open(settings.db_path, busy_timeout_s=settings.database.busy_timeout_s)
    stack.callback(db.close)
    _task(stack, watch_database(db, settings.database.integrity_check_interval_s), "oarmreg-db-watch")
    return db


async def _start_core(inputs: ServiceInputs, db: Database, stack: contextlib.AsyncExitStack) -> _Core:
    """The orchestrator and calibration jobs, scan-change recovery after a crash, the joint capture
    and the intake that records scans."""
    settings, publish = inputs.settings, inputs.bus.publish
    orchestrator = Orchestrator(
        settings, db, inputs.phantom, inputs.robot_model, publish, volumes=inputs.volumes
    )
    # a registration still running on a worker thread finishes before the database closes
    stack.push_async_callback(asyncio.to_thread, orchestrator.wait_idle)
    calibrations = CalibrationJobs(
        settings, db, orchestrator, inputs.phantom, inputs.robot_model, inputs.volumes, publish
    )
    stack.push_async_callback(asyncio.to_thread, calibrations.stop)
    calibrations.restore()
    orchestrator.withdraw_if_robot_side_changed()  # after the calibration in force is known
    lifecycle = ScanLifecycle(db, inputs.volumes, publish, orchestrator.withdraw_scan)
    intake_dir = settings.data_dir / INTAKE_FOLDER
    await asyncio.to_thread(lifecycle.recover, cstore_root=intake_dir)  # after a crash
    capture = Capture(inputs.robot_link, settings, publish)
    await capture.start()
    stack.push_async_callback(capture.stop)
    intake = Intake(db, capture, inputs.volumes, publish, lifecycle)
    return _Core(db, orchestrator, calibrations, lifecycle, capture, intake, intake_dir)


async def _start_outputs(inputs: ServiceInputs, core: _Core, stack: contextlib.AsyncExitStack) -> _Outputs:
    """Auto-registration, the OpenIGTLink server and the PACS export, each bound to the bus."""
    settings, publish = inputs.settings, inputs.bus.publish
    subs = Subscriptions(inputs.bus)
    stack.callback(subs.close)
    auto_register: AutoRegister | None = None
    if settings.service.auto_register:
        auto_register = AutoRegister(core.orchestrator)
        await auto_register.start()
        stack.push_async_callback(auto_register.stop)
        subs.listen(ScanArrived, auto_register.on_scan_arrived)
    igtl: IgtlPublisher | None = None
    if settings.igtl.enabled:
        igtl = IgtlPublisher(
            settings.igtl, core.orchestrator, core.capture, inputs.robot_link, inputs.robot_model, publish
        )
        await igtl.start()
        stack.push_async_callback(igtl.stop)
        # safety: navigation must learn at once of a new, refused or withdrawn registration
        subs.listen(RegistrationDone, igtl.on_registration_done, safety=True)
        subs.listen(RegistrationRefused, igtl.on_registration_refused, safety=True)
        subs.listen(RegistrationWithdrawn, igtl.on_registration_withdrawn, safety=True)
        subs.listen(VerificationDone, igtl.on_verification_done)
    pacs: PacsExporter | None = None
    if settings.pacs.enabled:
        pacs = PacsExporter(core.db, settings.pacs, settings.data_dir, publish)
        await asyncio.to_thread(pacs.start)
        stack.push_async_callback(asyncio.to_thread, pacs.stop)
        subs.listen(RegistrationDone, pacs.on_registration_done)
    return _Outputs(subs, auto_register, igtl, pacs)


def _start_watcher(settings: Settings, core: _Core, stack: contextlib.AsyncExitStack) -> SeriesWatcher:
    """The folder watcher feeding the intake."""
    w, db = settings.watcher, core.db
    watcher = SeriesWatcher(
        settings.watch_dir,
        on_series=core.intake,
        is_known=db.scans.has_complete,
        recorded_slices=db.scans.recorded_slices,
        recorded_content=db.scans.recorded_content,
        quiet_period_s=w.quiet_period_s,
        poll_interval_s=w.poll_interval_s,
        use_polling_only=w.use_polling_only,
    )
    watcher.start()
    stack.push_async_callback(asyncio.to_thread, watcher.stop)
    return watcher


async def _start_cstore(
    settings: Settings, core: _Core, stack: contextlib.AsyncExitStack, publish: Publish
) -> CStoreIntake | None:
    """The DICOM Storage SCP feeding the intake, when ``[dicom] enabled``."""
    if not settings.dicom.enabled:
        return None
    cstore = CStoreIntake(settings.dicom, core.intake_dir, core.db, core.intake, core.lifecycle, publish)
    await cstore.start()
    stack.push_async_callback(cstore.stop)
    return cstore


def _task(stack: contextlib.AsyncExitStack, coro: Coroutine[Any, Any, None], name: str) -> None:
    """Run ``coro`` as a task until the stack unwinds (then cancelled and awaited)."""
    task = asyncio.create_task(coro, name=name)

    async def cancel() -> None:
        task.cancel()
        with contextlib.suppress(asyncio.CancelledError):
            await task

    stack.push_async_callback(cancel)


def startup_line(ctx: ServiceContext) -> str:
    """Every listener, the folders, the robot link and auth in one line (logged at INFO)."""
    st = ctx.settings
    scheme = "https" if st.tls.enabled else "http"
    host = f"[{st.host}]" if ":" in st.host else st.host
    parts = [f"HTTP {scheme}://{host}:{st.port} (status page /, API docs /docs)"]
    listeners = ctx.listeners()
    d, g = listeners.get("dicom", {}), listeners.get("igtl", {})
    parts.append(f"DICOM C-STORE {d.get('ae_title')}@{d.get('host')}:{d.get('port')}" if d.get("enabled")
                 else "DICOM C-STORE off")  # fmt: skip
    parts.append(f"OpenIGTLink {g.get('host')}:{g.get('port')}" if g.get("enabled") else "OpenIGTLink off")
    parts.append(f"watch folder {st.watch_dir.resolve()}" if ctx.watcher is not None else "watch folder off")
    parts.append(f"data folder {st.data_dir.resolve()}")
    parts.append(f"robot {st.robot.link_url} ({st.robot.model})")
    parts.append("auth " + ("on" if st.auth_enabled else "OFF (loopback only)"))
    return "listening: " + ", ".join(parts)
