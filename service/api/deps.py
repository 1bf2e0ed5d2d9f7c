"""Dependencies as ``Annotated`` aliases (tests can override them)."""

from __future__ import annotations

import hmac
from typing import Annotated

from fastapi import Depends, Request
from fastapi.security import HTTPAuthorizationCredentials, HTTPBearer
from pydantic import SecretStr

from service.context import ServiceContext
from service.errors import AuthError


async def get_ctx(request: Request) -> ServiceContext:
    ctx: ServiceContext = request.app.state.ctx
    return ctx


CtxDep = Annotated[ServiceContext, Depends(get_ctx)]

_bearer = HTTPBearer(auto_error=False, description="API token (settings: api_token / OARMREG_API_TOKEN)")


def token_ok(settings_token: SecretStr | None, presented: str | None) -> bool:
    """True if ``presented`` (the Bearer credentials) matches the API token, in constant time
    (``hmac.compare_digest``); always True when no token is configured (loopback only)."""
    if settings_token is None:
        return True
    if presented is None:
        return False
    secret = settings_token.get_secret_value()
    return hmac.compare_digest(presented.encode(), secret.encode())


async def require_token(
    request: Request,
    credentials: Annotated[HTTPAuthorizationCredentials | None, Depends(_bearer)],
) -> None:
    """Check ``Authorization: Bearer <token>`` in constant time (``hmac.compare_digest``)."""
    ctx: ServiceContext = request.app.state.ctx
    token = ctx.settings.api_token
    if token is None:
        return  # authentication disabled (loopback only; refused by the settings otherwise)
    if credentials is None or credentials.scheme.lower() != "bearer":
        raise AuthError("missing 'Authorization: Bearer <token>' header; the API token is set in api_token")
    if not token_ok(token, credentials.credentials):
        raise AuthError("the Bearer token does not match the service's api_token")


AuthDep = Depends(require_token)
