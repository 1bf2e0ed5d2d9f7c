"""The FastAPI app factory.

``create_app(settings)`` validates what can fail early (phantom file, robot model, link
URL) and returns an app whose lifespan opens the database, connects the robot link,
starts the DICOM watcher, and stops them again.  No settings or resources exist at
import time; tests inject settings, a robot link, or override dependencies.

Routers (``service/api``): ``/health`` (no auth) · ``/status`` · ``/robot/joints`` ·
``/scans`` · ``/register`` · ``/registration/current`` · ``/registrations`` · ``/verify`` ·
``/verifications`` · ``/events``.  Every route but ``/health`` needs
``Authorization: Bearer <api_token>`` when a token is configured.
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
from registration.kinematics import RobotModel
from registration.phantom import Phantom
from service.capture import Capture
from service.context import ServiceContext
from service.event_bus import EventBus
from service.intake import Intake
from service.orchestrator import Orchestrator
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
* **Auth**: `Authorization: Bearer <token>` on everything but `/health`.
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
        Pre-loaded :class:`registration.phantom.Phantom` / :class:`registration.kinematics.RobotModel`.
    start_watcher : bool
        False to run without the folder watcher (tests that record scans themselves).

    Raises
    ------
    ConfigError, RobotLinkError
        Bad phantom file, robot model or link URL (fail at start-up, naming the setting).
    """
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

    app = FastAPI(title="oarmreg", version=__version__, description=API_DESCRIPTION, lifespan=lifespan)
    app.state.ctx = ctx
    _install_routes(app)
    app.add_middleware(CurrentRegistrationFastPath)
    return app


def _load_phantom(settings: Settings) -> Phantom:
    from registration.phantom import load_phantom

    return load_phantom(settings.phantom_file)


def _load_robot_model(settings: Settings) -> RobotModel:
    from registration.errors import ConfigError

    try:
        return RobotModel.load(settings.robot.model)
    except ConfigError as e:
        raise ConfigError(f"setting 'robot.model' ({settings.robot.model!r}): {e}") from None


def _open_link(settings: Settings) -> RobotLink:
    from drivers.factory import open_link

    return open_link(settings.robot.link_url)


async def _start(ctx: ServiceContext, *, start_watcher: bool) -> None:
    """Open the database, connect the robot link, start the watcher."""
    settings = ctx.settings
    ctx.bus.bind(asyncio.get_running_loop())
    settings.data_dir.mkdir(parents=True, exist_ok=True)
    ctx.db = Database.open(settings.db_path)
    ctx.orchestrator = Orchestrator(
        settings, ctx.db, ctx.phantom, ctx.robot_model, ctx.bus.publish, volumes=ctx.volumes
    )
    ctx.capture = Capture(ctx.robot_link, settings, ctx.bus.publish)
    await ctx.capture.start()
    if start_watcher:
        w = settings.watcher
        ctx.watcher = SeriesWatcher(
            settings.watch_dir,
            on_series=Intake(
                ctx.db, ctx.capture, ctx.volumes, ctx.bus.publish, withdraw=ctx.orchestrator.withdraw_scan
            ),
            is_known=ctx.db.scans.has_complete,
            recorded_slices=ctx.db.scans.recorded_slices,
            quiet_period_s=w.quiet_period_s,
            poll_interval_s=w.poll_interval_s,
            use_polling_only=w.use_polling_only,
        )
        ctx.watcher.start()
    ctx.retention_task = asyncio.create_task(_retention_loop(ctx), name="oarmreg-retention")
    log.info(
        "oarmreg %s serving: watch %s, data %s, robot %s (%s), auth %s",
        __version__, settings.watch_dir, settings.data_dir, settings.robot.link_url, settings.robot.model,
        "on" if settings.auth_enabled else "OFF (loopback only)",
    )  # fmt: skip


async def _retention_loop(ctx: ServiceContext) -> None:
    """Run the retention policy at start-up, then every ``retention.interval_s``; never dies."""
    from service.retention import run_retention

    r = ctx.settings.retention
    while True:
        try:
            await asyncio.to_thread(
                run_retention, ctx.db, ctx.settings.watch_dir, ctx.bus.publish,
                max_age_days=r.max_age_days, max_disk_mb=r.max_disk_mb,
            )  # fmt: skip
        except Exception:
            log.exception("retention: the policy run failed; retrying in %.0f s", r.interval_s)
        await asyncio.sleep(r.interval_s)  # a period, not synchronisation


async def _stop(ctx: ServiceContext) -> None:
    if ctx.retention_task is not None:
        ctx.retention_task.cancel()
        with contextlib.suppress(asyncio.CancelledError):
            await ctx.retention_task
    ctx.bus.close()
    if ctx.watcher is not None:
        await asyncio.to_thread(ctx.watcher.stop)
    await ctx.capture.stop()
    # a registration still running on a worker thread finishes before the database closes
    await asyncio.to_thread(ctx.orchestrator.wait_idle)
    ctx.db.close()


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
    from service.api import events, health, problems, registrations, scans, status, verifications
    from service.api.deps import AuthDep

    problems.install(app)
    app.include_router(health.router)
    for r in (status.router, scans.router, registrations.router, verifications.router, events.router):
        app.include_router(r, dependencies=[AuthDep])
