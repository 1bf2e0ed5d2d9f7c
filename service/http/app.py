"""The FastAPI app factory.

``create_app(settings)`` validates what can fail early (phantom file, robot model, link
URL) and returns an app whose lifespan opens the database, connects the robot link,
starts the folder watcher and, when enabled, the operating-room pieces (each bound to the bus:
:mod:`service.intake.intake_scp`, :mod:`service.navigation.igtl.publisher`,
:mod:`service.navigation.pacs.exporter`,
:mod:`service.registrations.auto_register`; docs/or-integration.md), builds the
:class:`service.http.context.ServiceContext` and stops them again.  No settings or resources exist at
import time; tests inject settings, a robot link, or override dependencies.

Routers (``service/api``): ``/health`` (no auth) · ``/status`` · ``/robot/joints`` ·
``/scans`` · ``/register`` · ``/registration/current`` · ``/registrations`` ·
``/registrations/{id}/dicom`` · ``/verify`` ·
``/verifications`` · ``/events`` (+ ``/events/ticket``) · ``/audit`` · ``/calibrations``
(:mod:`service.http.api.calibrations`); the page ``/`` and ``/docs`` (:mod:`service.http.web`).  Every data
route
needs ``Authorization: Bearer <api_token>``, checked with Host, Origin, Content-Type and body size
by :class:`service.http.security.SecurityGate` before any body byte is read.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
from collections.abc import AsyncIterator, Coroutine
from contextlib import asynccontextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from fastapi import FastAPI
from starlette.types import ASGIApp, Receive, Scope, Send

from drivers.base import RobotLink
from registration import __version__
from registration.model.kinematics import RobotModel
from registration.model.phantom import Phantom
from service.data_dir import hold_serve_lock, make_private
from service.event_bus import EventBus, Subscriptions
from service.events import (
    Publish,
    RegistrationDone,
    RegistrationRefused,
    RegistrationWithdrawn,
    ScanArrived,
    VerificationDone,
)
from service.http.context import ServiceContext, ServiceInputs
from service.http.security import SecurityGate
from service.http.state import HttpState
from service.intake.intake_scp import INTAKE_FOLDER, CStoreIntake
from service.intake.recording import Intake
from service.intake.scan_lifecycle import ScanLifecycle
from service.intake.watcher import SeriesWatcher
from service.navigation.igtl.publisher import IgtlPublisher
from service.navigation.pacs.exporter import PacsExporter
from service.registrations.auto_register import AutoRegister
from service.registrations.calibration_jobs import CalibrationJobs
from service.registrations.capture import Capture
from service.registrations.orchestrator import Orchestrator
from service.settings import Settings
from service.store import Database

log = logging.getLogger(__name__)

API_DESCRIPTION = """
Registration of an O-arm cone-beam CT scan to a Stäubli robot (Bai et al. 2018,
doi:10.1088/1742-6596/1016/1/012006).

* **Frames and units**: millimetres, radians.  `image_from_robot` is a 4 × 4 row-major
  matrix mapping robot-frame points (Stäubli world frame, URDF `base`) to DICOM patient
  coordinates (LPS) of the scan: `p_image = image_from_robot @ p_robot`.  Slicer (RAS)
  clients convert with `diag(-1, -1, 1, 1) @ image_from_robot`.
* **Quality**: FRE is never an accuracy figure; use `predicted_tre_mm` at your targets and
  `POST /verify` with a second scan.
* **Errors**: problem details (RFC 9457, `application/problem+json`) with a 4xx status.
* **Auth**: `Authorization: Bearer <token>` on every data route and `/openapi.json`; public: `/health`,
  the status page `/` with its `/static/` files and `/favicon.ico`, and this `/docs` shell.
"""


def create_app(
    settings: Settings,
    *,
    robot_link: RobotLink | None = None,
    phantom: Phantom | None = None,
    robot_model: RobotModel | None = None,
    start_watcher: bool = True,
) -> FastAPI:
    """Build the app.

    Parameters
    ----------
    settings : Settings
        From :func:`service.settings.load_settings`.
    robot_link : RobotLink, optional
        Default: :func:`drivers.factory.open_link` on ``settings.robot.link_url``, or a
        :class:`drivers.link_process.ProcessLink` when ``robot.link_process`` is set (``_open_link``;
        not connected until start-up).
    phantom, robot_model : optional
        Pre-loaded :class:`registration.model.phantom.Phantom` /
        :class:`registration.model.kinematics.RobotModel`.
    start_watcher : bool
        False to run without the folder watcher (tests that record scans themselves).

    Raises
    ------
    ConfigError, RobotLinkError
        Bad phantom file, robot model or link URL (fail at start-up, naming the setting).
    """
    settings.check_serving()
    phantom = phantom if phantom is not None else _load_phantom(settings)
    settings.check_robot_side(phantom.size_mm)
    inputs = ServiceInputs(
        settings=settings,
        bus=EventBus(),
        phantom=phantom,
        robot_model=robot_model if robot_model is not None else _load_robot_model(settings),
        robot_link=robot_link if robot_link is not None else _open_link(settings),
    )

    @asynccontextmanager
    async def lifespan(app: FastAPI) -> AsyncIterator[None]:
        async with contextlib.AsyncExitStack() as stack:
            app.state.ctx = await _start(inputs, stack, start_watcher=start_watcher)
            yield

    docs = settings.api.docs
    app = FastAPI(
        title="oarmreg", version=__version__, description=API_DESCRIPTION, lifespan=lifespan,
        docs_url=None, redoc_url=None,  # /docs: the self-hosted shell of service.http.web
        openapi_url="/openapi.json" if docs else None,
    )  # fmt: skip
    app.state.inputs = inputs  # app.state.ctx: set by the lifespan once every part runs
    app.state.http = HttpState()  # what only HTTP keeps (tickets, connection counters), across restarts
    _install_routes(app)
    app.add_middleware(CurrentRegistrationFastPath)
    app.add_middleware(SecurityGate)  # nothing is read before it admits the request
    _install_browser_layer(app, settings)  # CSP headers, then CORS outermost
    return app


def _install_browser_layer(app: FastAPI, settings: Settings) -> None:
    from service.http.web.cors import install_cors
    from service.http.web.headers import SecurityHeaders
    from service.http.web.routes import build_router

    app.include_router(build_router(docs=settings.api.docs))
    app.add_middleware(SecurityHeaders)
    install_cors(app, settings)  # outside the gate: pre-flights carry no token


def _load_phantom(settings: Settings) -> Phantom:
    from registration.model.phantom import load_phantom

    return load_phantom(settings.phantom_file)


def _load_robot_model(settings: Settings) -> RobotModel:
    from registration.errors import ConfigError

    try:
        return RobotModel.load(settings.robot.model)
    except ConfigError as e:
        raise ConfigError(f"setting 'robot.model' ({settings.robot.model!r}): {e}") from None


def _open_link(settings: Settings) -> RobotLink:
    from drivers.factory import open_link
    from drivers.link_process import ProcessLink

    if settings.robot.link_process:  # the reader in a child process, out of the GIL's reach
        return ProcessLink(settings.robot.link_url)
    return open_link(settings.robot.link_url)


async def _start(
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
    _task(stack, _retention_loop(ctx), "oarmreg-retention")
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
    _task(stack, _watch_database(db, settings.database.integrity_check_interval_s), "oarmreg-db-watch")
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


async def _watch_database(db: Database, interval_s: float) -> None:
    """Every ``database.integrity_check_interval_s``: is the database file still the one opened?

    The check also runs on every write transaction and every ``GET /health``; this loop makes a
    vanished file show up in the log (and the rescue copy be taken) even when nothing writes.
    """
    while db.health_problem() is None:
        await asyncio.sleep(interval_s)


async def _retention_loop(ctx: ServiceContext) -> None:
    """Run the retention policy at start-up, then every ``retention.interval_s``; never dies."""
    from service.intake.retention import quota_problem, run_retention

    r = ctx.settings.retention
    roots = (ctx.settings.data_dir / INTAKE_FOLDER,)  # C-STORE scans too
    while True:
        try:
            await asyncio.to_thread(
                run_retention, ctx.db, ctx.settings.watch_dir, ctx.bus.publish,
                max_age_days=r.max_age_days, max_disk_mb=r.max_disk_mb, extra_roots=roots,
            )  # fmt: skip
            ctx.retention_problem = await asyncio.to_thread(
                quota_problem, ctx.db, ctx.settings.watch_dir, max_disk_mb=r.max_disk_mb, extra_roots=roots
            )
        except Exception:
            log.exception("retention: the policy run failed; retrying in %.0f s", r.interval_s)
        await asyncio.sleep(r.interval_s)  # a period, not synchronisation


class CurrentRegistrationFastPath:
    """Pure-ASGI fast path for the request the navigation UI polls, ``GET /registration/current``.

    It answers only the plain success case — the gate authenticated the request, a current
    registration exists — with the same pre-encoded JSON the route serves, skipping routing,
    dependency injection and response validation (about 2× the request rate on 2 cores).  Everything
    else (no current registration, other methods or paths) falls through to the FastAPI route, which
    gives the documented answers and problem details; a wrong token never gets here (the gate
    answered 401).
    """

    PATH = "/registration/current"

    def __init__(self, app: ASGIApp) -> None:
        self.app = app

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] == "http" and scope["method"] == "GET" and scope["path"] == self.PATH:
            state = scope["app"].state
            ctx: ServiceContext = state.ctx
            http: HttpState = state.http
            body = (
                http.current_registration_json(ctx.orchestrator.current) if self._authorized(scope) else None
            )
            if body is not None:
                await send(
                    {
                        "type": "http.response.start",
                        "status": 200,
                        "headers": [
                            (b"content-type", b"application/json"),
                            (b"content-length", str(len(body)).encode()),
                        ],
                    }
                )
                await send({"type": "http.response.body", "body": body})
                return
        await self.app(scope, receive, send)

    @staticmethod
    def _authorized(scope: Scope) -> bool:
        """The gate (outside this middleware) authenticated the request: it recorded the principal,
        as :func:`service.http.api.deps.require_token` reads it; the token is checked only there."""
        return scope.get("state", {}).get("principal") is not None


def _install_routes(app: FastAPI) -> None:
    from service.http.api import (
        audit,
        events,
        health,
        problems,
        registrations,
        scans,
        sro,
        status,
        verifications,
    )
    from service.http.api.calibrations import router as calibrations_router
    from service.http.api.deps import AuthDep

    problems.install(app)
    app.include_router(health.router)
    routers = (
        status.router,
        scans.router,
        registrations.router,
        sro.router,
        verifications.router,
        events.router,
        audit.router,
        calibrations_router,
    )
    from service.http.api.qa import router as qa_router

    for r in (*routers, qa_router):
        app.include_router(r, dependencies=[AuthDep])
