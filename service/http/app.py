"""The FastAPI app factory: HTTP is one door of the service, not the house.

``create_app(settings)`` validates what can fail early (phantom file, robot model, link URL:
:func:`service.runtime.inputs.prepare_inputs`) and returns an app whose lifespan runs the service
(:func:`service.runtime.assembly.running_service`: every part started in order and bound to the bus,
stopped in reverse) and puts its :class:`service.runtime.context.ServiceContext` on ``app.state.ctx``.
No settings or resources exist at import time; tests inject settings, a robot link, or override
dependencies.

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

import logging
from collections.abc import AsyncIterator
from contextlib import asynccontextmanager

from fastapi import FastAPI
from starlette.types import ASGIApp, Receive, Scope, Send

from drivers.base import RobotLink
from registration import __version__
from registration.model.kinematics import RobotModel
from registration.model.phantom import Phantom
from service.http.security import SecurityGate
from service.http.state import HttpState
from service.runtime.assembly import running_service
from service.runtime.context import ServiceContext
from service.runtime.inputs import prepare_inputs
from service.settings import Settings

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

    ``settings``, ``robot_link``, ``phantom`` and ``robot_model`` are checked and loaded by
    :func:`service.runtime.inputs.prepare_inputs` (which raises ``ConfigError`` / ``RobotLinkError``
    for a bad phantom file, robot model or link URL, naming the setting); ``start_watcher`` False
    runs without the folder watcher (tests that record scans themselves).
    """
    inputs = prepare_inputs(settings, robot_link=robot_link, phantom=phantom, robot_model=robot_model)

    @asynccontextmanager
    async def lifespan(app: FastAPI) -> AsyncIterator[None]:
        async with running_service(inputs, start_watcher=start_watcher) as ctx:
            app.state.ctx = ctx
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
