"""CORS for a navigation UI served from another origin, Starlette's CORSMiddleware.

Installed only when ``api.allowed_origins`` lists origins (the default allows same-origin only,
and a same-origin page needs no CORS).  It sits outside :class:`service.http.security.SecurityGate`,
so a pre-flight (``OPTIONS`` with ``Access-Control-Request-Method``) from a listed origin is
answered without a token — browsers never send credentials on a pre-flight — while the real
request still passes the gate: Host, Origin, the Bearer token, Content-Type.  A pre-flight from an
unlisted origin gets 400 without ``Access-Control-Allow-*``, so the browser blocks the request.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from starlette.middleware.cors import CORSMiddleware

if TYPE_CHECKING:
    from fastapi import FastAPI

    from service.settings import Settings

ALLOWED_METHODS = ("GET", "POST")
"""Every method the API has (no PUT / PATCH / DELETE routes)."""
ALLOWED_HEADERS = ("Authorization", "Content-Type")
PREFLIGHT_MAX_AGE_S = 600
"""How long a browser may cache a pre-flight answer, s (Chromium caps it at 7200)."""


def cors_origins(settings: Settings) -> list[str]:
    return [o.strip().lower().rstrip("/") for o in settings.api.allowed_origins if o.strip()]


def install_cors(app: FastAPI, settings: Settings) -> None:
    """Add CORSMiddleware as the outermost middleware when origins are listed (call it last)."""
    origins = cors_origins(settings)
    if not origins:
        return
    app.add_middleware(
        CORSMiddleware,
        allow_origins=origins,
        allow_methods=list(ALLOWED_METHODS),
        allow_headers=list(ALLOWED_HEADERS),
        allow_credentials=False,  # the token travels in Authorization, never in a cookie
        max_age=PREFLIGHT_MAX_AGE_S,
    )
