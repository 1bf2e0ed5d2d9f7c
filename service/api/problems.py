"""Problem details (RFC 9457, ``application/problem+json``) for every error.

One handler maps both exception families (:class:`registration.errors.OarmRegError`,
:class:`drivers.errors.RobotLinkError`) through :mod:`service.error_map`; request
validation errors become 422 with the offending fields; unknown routes 404; bugs 500.
"""

from __future__ import annotations

import logging
import re
from typing import Any

from fastapi import FastAPI, Request
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse
from starlette.exceptions import HTTPException as StarletteHTTPException

from service.error_map import FAMILIES, classify, exit_code_of, title_of

log = logging.getLogger(__name__)

PROBLEM_MEDIA_TYPE = "application/problem+json"
TYPE_PREFIX = "urn:oarmreg:problem:"


def _kebab(name: str) -> str:
    name = re.sub(r"Error$", "", name) or name
    return re.sub(r"(?<!^)(?=[A-Z])", "-", name).lower()


def problem_response(
    status: int, title: str, detail: str, instance: str, *, type_: str = "about:blank",
    headers: dict[str, str] | None = None, **extra: Any,
) -> JSONResponse:  # fmt: skip
    body: dict[str, Any] = {
        "type": type_,
        "title": title,
        "status": status,
        "detail": detail,
        "instance": instance,
    }
    body.update({k: v for k, v in extra.items() if v is not None})
    return JSONResponse(body, status_code=status, media_type=PROBLEM_MEDIA_TYPE, headers=headers)


async def _family_handler(request: Request, exc: Exception) -> JSONResponse:
    entry = classify(exc)
    status = entry.http_status if entry is not None and entry.http_status >= 400 else 422
    return problem_response(
        status,
        title_of(exc),
        str(exc),
        request.url.path,
        type_=TYPE_PREFIX + _kebab(type(exc).__name__),
        headers=getattr(exc, "headers", None),
        exit_code=exit_code_of(exc),
        registration_id=getattr(exc, "registration_id", None),
        calibration_id=getattr(exc, "calibration_id", None),
    )


async def _validation_handler(request: Request, exc: Exception) -> JSONResponse:
    assert isinstance(exc, RequestValidationError)
    errors = [
        {
            "loc": [str(p) for p in e.get("loc", ())],
            "msg": str(e.get("msg", "")),
            "type": str(e.get("type", "")),
        }
        for e in exc.errors()
    ]
    detail = "; ".join(f"{'.'.join(e['loc'])}: {e['msg']}" for e in errors) or "invalid request"
    return problem_response(
        422, "Invalid request", detail, request.url.path, type_=TYPE_PREFIX + "invalid-request", errors=errors
    )


async def _http_handler(request: Request, exc: Exception) -> JSONResponse:
    assert isinstance(exc, StarletteHTTPException)
    from http import HTTPStatus

    try:
        title = HTTPStatus(exc.status_code).phrase
    except ValueError:
        title = "Error"
    return problem_response(
        exc.status_code, title, str(exc.detail), request.url.path, headers=getattr(exc, "headers", None)
    )


async def _unexpected_handler(request: Request, exc: Exception) -> JSONResponse:
    log.exception("unhandled error on %s %s", request.method, request.url.path, exc_info=exc)
    return problem_response(
        500, "Internal error", f"{type(exc).__name__}: {exc}; see the service log", request.url.path
    )


def install(app: FastAPI) -> None:
    for family in FAMILIES:
        app.add_exception_handler(family, _family_handler)
    app.add_exception_handler(RequestValidationError, _validation_handler)
    app.add_exception_handler(StarletteHTTPException, _http_handler)
    app.add_exception_handler(Exception, _unexpected_handler)


PROBLEM_SCHEMA: dict[str, Any] = {
    "content": {
        PROBLEM_MEDIA_TYPE: {
            "schema": {
                "type": "object",
                "properties": {
                    "type": {"type": "string"},
                    "title": {"type": "string"},
                    "status": {"type": "integer"},
                    "detail": {"type": "string"},
                    "instance": {"type": "string"},
                },
            }
        }
    }
}


def problem_responses(*codes: int) -> dict[int | str, dict[str, Any]]:
    """OpenAPI ``responses=`` entries for the given error codes."""
    desc = {
        401: "missing or wrong Bearer token",
        404: "no such resource",
        409: "refused (robot moved, robot link down, too few spheres, ambiguous, FRE over the gate)",
        422: "invalid request or unusable scan (problem details)",
        500: "internal error",
    }
    return {c: {"description": desc.get(c, "error"), **PROBLEM_SCHEMA} for c in codes}
