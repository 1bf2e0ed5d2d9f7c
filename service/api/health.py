"""``GET /health``: liveness, no authentication."""

from __future__ import annotations

from fastapi import APIRouter

from registration import __version__
from service.api.models import Health

router = APIRouter(tags=["health"])


@router.get("/health", response_model=Health, summary="Liveness (no authentication)")
def health() -> Health:
    return Health(version=__version__)
