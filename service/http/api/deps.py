"""Dependencies as ``Annotated`` aliases (tests can override them)."""

from __future__ import annotations

from typing import Annotated

from fastapi import Depends, Path, Query, Request
from fastapi.security import HTTPAuthorizationCredentials, HTTPBearer

from service.errors import UnauthorizedError
from service.http.state import HttpState
from service.runtime.context import ServiceContext


async def get_ctx(request: Request) -> ServiceContext:
    ctx: ServiceContext = request.app.state.ctx
    return ctx


CtxDep = Annotated[ServiceContext, Depends(get_ctx)]


async def get_http(request: Request) -> HttpState:
    http: HttpState = request.app.state.http
    return http


HttpDep = Annotated[HttpState, Depends(get_http)]
"""What only HTTP keeps (:mod:`service.http.state`): event tickets, connection counters."""

_bearer = HTTPBearer(auto_error=False, description="API token (settings: api_token / OARMREG_API_TOKEN)")


async def require_token(
    request: Request,
    credentials: Annotated[HTTPAuthorizationCredentials | None, Depends(_bearer)],
) -> None:
    """Admit only requests the gate (:class:`service.http.security.SecurityGate`) authenticated.

    The gate checks the token (or an event ticket) before the body is read and records the
    principal in ``request.state``; this dependency documents the scheme in OpenAPI and refuses a
    request that somehow bypassed the gate (defence in depth).
    """
    if getattr(request.state, "principal", None) is None:
        raise UnauthorizedError(
            "missing 'Authorization: Bearer <token>' header; the API token is set in api_token"
        )


async def get_principal(request: Request) -> str:
    """Who is asking, for the audit log (``token:<hash>``, never the token)."""
    principal = getattr(request.state, "principal", None)
    if not isinstance(principal, str):
        raise UnauthorizedError(
            "missing 'Authorization: Bearer <token>' header; the API token is set in api_token"
        )
    return principal


AuthDep = Depends(require_token)
PrincipalDep = Annotated[str, Depends(get_principal)]

RecordId = Annotated[int, Path(ge=1, le=2**63 - 1, description="Record id (1 … 2^63 − 1)")]
"""A record id in a path: SQLite's row-id range, so 2^63 answers 422, not 500."""
Limit = Annotated[int, Query(ge=1, le=1000)]
Offset = Annotated[int, Query(ge=0, le=2**63 - 1)]
