"""The FastAPI app factory.

``create_app(settings)`` validates what can fail early (phantom file, robot model, link
URL) and returns an app whose lifespan opens the database, connects the robot link,
starts the DICOM watcher (and, when enabled, the DICOM C-STORE SCP and the OpenIGTLink
server, :mod:`service.or_integration`), and stops them again.  No settings or resources exist at
import time; tests inject settings, a robot link, or override dependencies.

Routers (``service/api``): ``/health`` (no auth) · ``/status`` · ``/robot/joints`` ·
``/scans`` · ``/register`` · ``/registration/current`` · ``/registrations`` ·
``/registrations/{id}/dicom`` · ``/verify`` ·
``/verifications`` · ``/events`` (+ ``/events/ticket``) · ``/audit`` · ``/calibrations``
(:mod:`service.api.calibrations`); the page ``/`` and ``/docs`` (:mod:`service.web`).  Every data route
needs ``Authorization: Bearer <api_token>``, checked with Host, Origin, Content-Type and body size
by :class:`service.security.SecurityGate` before any body byte is read.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
from collections.abc import AsyncIterator
from contextlib import asynccontextmanager

from fastapi import FastAPI
from starlette.types import ASGIApp, Receive, Scope, Send

from drivers.base import RobotLink
from registration import __version__
from registration.model.kinematics import RobotModel
from registration.model.phantom import Phantom
from service.calibration_jobs import CalibrationJobs
from service.capture import Capture
from service.context import ServiceContext
from service.data_dir import hold_serve_lock, make_private
from service.event_bus import EventBus
from service.intake import Intake
from service.or_integration import OrIntegration
from service.orchestrator import Orchestrator
from service.scan_lifecycle import ScanLifecycle
from service.security import SecurityGate
from service.settings import Settings
from service.store import Database
from service.watcher import SeriesWatcher

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
        Default: ``drivers.base.open_link(settings.robot.link_url)`` (not connected until start-up).
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
    ctx = ServiceContext(
        settings=settings,
        bus=EventBus(),
        phantom=phantom if phantom is not None else _load_phantom(settings),
        robot_model=robot_model if robot_model is not None else _load_robot_model(settings),
        robot_link=robot_link if robot_link is not None else _open_link(settings),
    )

    @asynccontextmanager
    async def lifespan(app: FastAPI) -> AsyncIterator[None]:
        await _start(ctx, start_watcher=start_watcher)
        try:
            yield
        finally:
            await _stop(ctx)

    docs = settings.api.docs
    app = FastAPI(
        title="oarmreg", version=__version__, description=API_DESCRIPTION, lifespan=lifespan,
        docs_url=None, redoc_url=None,  # /docs: the self-hosted shell of service.web
        openapi_url="/openapi.json" if docs else None,
    )  # fmt: skip
    app.state.ctx = ctx
    _install_routes(app)
    app.add_middleware(CurrentRegistrationFastPath)
    app.add_middleware(SecurityGate)  # nothing is read before it admits the request
    _install_browser_layer(app, settings)  # CSP headers, then CORS outermost
    return app


def _install_browser_layer(app: FastAPI, settings: Settings) -> None:
    from service.web.cors import install_cors
    from service.web.headers import SecurityHeaders
    from service.web.routes import build_router

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


async def _start(ctx: ServiceContext, *, start_watcher: bool) -> None:
    """Open the database, connect the robot link, start the watcher."""
    settings = ctx.settings
    ctx.bus.bind(asyncio.get_running_loop())
    make_private(settings.data_dir)  # umask 077, folder 0700, files 0600
    ctx.serve_lock = hold_serve_lock(settings.data_dir)  # a second serve on this folder: exit 3
    try:
        ctx.db = Database.open(settings.db_path)
    except BaseException:
        ctx.serve_lock.close()
        raise
    or_int = ctx.or_integration = OrIntegration(ctx)
    ctx.db_watch_task = asyncio.create_task(_watch_database(ctx), name="oarmreg-db-watch")
    ctx.orchestrator = Orchestrator(
        settings, ctx.db, ctx.phantom, ctx.robot_model, ctx.bus.publish, volumes=ctx.volumes
    )
    ctx.calibrations = CalibrationJobs(
        settings, ctx.db, ctx.orchestrator, ctx.phantom, ctx.robot_model, ctx.volumes, ctx.bus.publish
    )
    ctx.calibrations.restore()
    or_int.lifecycle = ScanLifecycle(ctx.db, ctx.volumes, ctx.bus.publish, ctx.orchestrator.withdraw_scan)
    await asyncio.to_thread(or_int.lifecycle.recover, cstore_root=or_int.intake_dir)  # after a crash
    ctx.capture = Capture(ctx.robot_link, settings, ctx.bus.publish)
    await ctx.capture.start()
    if start_watcher:
        w = settings.watcher
        ctx.watcher = SeriesWatcher(
            settings.watch_dir,
            on_series=or_int.folder_intake(
                Intake(
                    ctx.db,
                    ctx.capture,
                    ctx.volumes,
                    ctx.bus.publish,
                    withdraw=ctx.orchestrator.withdraw_scan,
                    lifecycle=or_int.lifecycle,
                )
            ),
            is_known=ctx.db.scans.has_complete,
            recorded_slices=ctx.db.scans.recorded_slices,
            recorded_content=ctx.db.scans.recorded_content,
            quiet_period_s=w.quiet_period_s,
            poll_interval_s=w.poll_interval_s,
            use_polling_only=w.use_polling_only,
        )
        ctx.watcher.start()
    await or_int.start()  # DICOM C-STORE SCP and OpenIGTLink server, when enabled
    if settings.api.auth == "none-loopback-only":
        log.warning(
            "authentication is OFF (api.auth = 'none-loopback-only'): any local process or user can change "
            "the current registration; set api_token and api.auth = 'token' for clinical use"
        )
    ctx.retention_task = asyncio.create_task(_retention_loop(ctx), name="oarmreg-retention")
    log.info("oarmreg %s: %s", __version__, startup_line(ctx))


def startup_line(ctx: ServiceContext) -> str:
    """Every listener, the folders, the robot link and auth in one line (logged at INFO)."""
    st = ctx.settings
    scheme = "https" if st.tls.enabled else "http"
    host = f"[{st.host}]" if ":" in st.host else st.host
    parts = [f"HTTP {scheme}://{host}:{st.port} (status page /, API docs /docs)"]
    listeners = ctx.or_integration.status() if ctx.or_integration is not None else {}
    d, g = listeners.get("dicom", {}), listeners.get("igtl", {})
    parts.append(f"DICOM C-STORE {d.get('ae_title')}@{d.get('host')}:{d.get('port')}" if d.get("enabled")
                 else "DICOM C-STORE off")  # fmt: skip
    parts.append(f"OpenIGTLink {g.get('host')}:{g.get('port')}" if g.get("enabled") else "OpenIGTLink off")
    parts.append(f"watch folder {st.watch_dir.resolve()}" if ctx.watcher is not None else "watch folder off")
    parts.append(f"data folder {st.data_dir.resolve()}")
    parts.append(f"robot {st.robot.link_url} ({st.robot.model})")
    parts.append("auth " + ("on" if st.auth_enabled else "OFF (loopback only)"))
    return "listening: " + ", ".join(parts)


async def _watch_database(ctx: ServiceContext) -> None:
    """Every ``database.integrity_check_interval_s``: is the database file still the one opened?

    The check also runs on every write transaction and every ``GET /health``; this loop makes a
    vanished file show up in the log (and the rescue copy be taken) even when nothing writes.
    """
    interval_s = ctx.settings.database.integrity_check_interval_s
    while ctx.db.health_problem() is None:
        await asyncio.sleep(interval_s)


async def _retention_loop(ctx: ServiceContext) -> None:
    """Run the retention policy at start-up, then every ``retention.interval_s``; never dies."""
    from service.or_integration import INTAKE_FOLDER
    from service.retention import quota_problem, run_retention

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


async def _stop(ctx: ServiceContext) -> None:
    if ctx.retention_task is not None:
        ctx.retention_task.cancel()
        with contextlib.suppress(asyncio.CancelledError):
            await ctx.retention_task
    ctx.bus.close()
    if ctx.or_integration is not None:
        await ctx.or_integration.stop()
    if ctx.db_watch_task is not None:
        ctx.db_watch_task.cancel()
        with contextlib.suppress(asyncio.CancelledError):
            await ctx.db_watch_task
    if ctx.watcher is not None:
        await asyncio.to_thread(ctx.watcher.stop)
    await ctx.capture.stop()
    await asyncio.to_thread(ctx.calibrations.stop)
    # a registration still running on a worker thread finishes before the database closes
    await asyncio.to_thread(ctx.orchestrator.wait_idle)
    ctx.db.close()
    if ctx.serve_lock is not None:
        ctx.serve_lock.close()


class CurrentRegistrationFastPath:
    """Pure-ASGI fast path for the request the navigation UI polls, ``GET /registration/current``.

    It answers only the plain success case — right token, a current registration exists — with the
    same pre-encoded JSON the route serves, skipping routing, dependency injection and response
    validation (about 2× the request rate on 2 cores).  Everything else (no or wrong token, no
    current registration, other methods or paths) falls through to the FastAPI route, which gives
    the documented answers and problem details.
    """

    PATH = "/registration/current"

    def __init__(self, app: ASGIApp) -> None:
        self.app = app

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] == "http" and scope["method"] == "GET" and scope["path"] == self.PATH:
            ctx: ServiceContext = scope["app"].state.ctx
            body = ctx.current_registration_json() if self._authorized(ctx, scope) else None
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
    def _authorized(ctx: ServiceContext, scope: Scope) -> bool:
        from service.api.deps import token_ok

        token = ctx.settings.api_token
        if token is None:
            return True
        for name, value in scope["headers"]:
            if name == b"authorization":
                scheme, _, credentials = value.decode("latin-1").partition(" ")
                return scheme.lower() == "bearer" and token_ok(token, credentials.strip())
        return False


def _install_routes(app: FastAPI) -> None:
    from service.api import audit, events, health, problems, registrations, scans, sro, status, verifications
    from service.api.calibrations import router as calibrations_router
    from service.api.deps import AuthDep

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
    from service.api.qa import router as qa_router

    for r in (*routers, qa_router):
        app.include_router(r, dependencies=[AuthDep])
