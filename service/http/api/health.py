"""``GET /health``: liveness and database health, no authentication.

200 ``{"status": "ok"}``, or 503 ``{"status": "unhealthy", "problems": [...]}`` when the service
cannot keep records (its database file was deleted or replaced; the problem says what to do).
"""

from __future__ import annotations

from fastapi import APIRouter, Response

from registration import __version__
from service.http.api.deps import CtxDep
from service.http.api.models import Health

router = APIRouter(tags=["health"])


@router.get(
    "/health",
    response_model=Health,
    summary="Liveness and database health (no authentication)",
    responses={503: {"model": Health, "description": "unhealthy: see problems"}},
)
def health(ctx: CtxDep, response: Response) -> Health:
    problem = ctx.db.health_problem()
    if problem is None:
        return Health(version=__version__)
    response.status_code = 503
    return Health(status="unhealthy", version=__version__, problems=[problem])
