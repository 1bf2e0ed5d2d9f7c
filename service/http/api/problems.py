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
INTERNAL_DETAIL = (
    "the service failed on this request (a bug, logged with its traceback); records already stored are "
    "kept; retry, and report it if it persists"
)
"""The detail of every 500: no exception text, which can quote row contents or paths."""


def problem_kind(exc: BaseException) -> str:
    """The last part of the problem ``type`` of ``exc``: its class name in kebab case without ``Error``
    (``UnauthorizedError`` → ``unauthorized``), the same from the gate and from the routes."""
    name = re.sub(r"Error$", "", type(exc).__name__) or type(exc).__name__
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
    return problem_for(request, exc)


def problem_for(
    request: Request, exc: Exception, *, registration_id: int | None = None, calibration_id: int | None = None
) -> JSONResponse:
    """The problem-details answer for ``exc`` (status, title and exit code from
    :mod:`service.error_map`),
    naming the stored record it refers to when there is one."""
    entry = classify(exc)
    status = entry.http_status if entry is not None and entry.http_status >= 400 else 422
    headers = getattr(exc, "headers", None)
    detail = str(exc)
    if status == 500:  # a bug: its text may quote internals; the log has it
        log.error("internal error on %s %s: %s", request.method, request.url.path, exc)
        detail = INTERNAL_DETAIL
        headers = {**(headers or {}), "Connection": "close"}
    return problem_response(
        status,
        title_of(exc),
        detail,
        request.url.path,
        type_=TYPE_PREFIX + problem_kind(exc),
        headers=headers,
        exit_code=exit_code_of(exc),
        registration_id=registration_id,
        calibration_id=calibration_id,
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
    # No exception text in the body (it can quote row contents); the log has the traceback.
    log.error("unhandled %s on %s %s", type(exc).__name__, request.method, request.url.path, exc_info=exc)
    return problem_response(
        500, "Internal error", INTERNAL_DETAIL, request.url.path, type_=TYPE_PREFIX + "internal",
        headers={"Connection": "close"},
    )  # fmt: skip


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
        413: "request body over api.max_body_bytes",
        415: "a mutating request without Content-Type: application/json",
        422: "invalid request or unusable scan (problem details)",
        429: "too many outstanding tickets",
        500: "internal error",
        503: "the database is unavailable (file deleted or replaced); see GET /health",
    }
    return {c: {"description": desc.get(c, "error"), **PROBLEM_SCHEMA} for c in codes}
