"""Server-sent events: ``GET /events`` (the bus: :class:`service.event_bus.EventBus`).

Event names: ``scan_arrived``, ``scan_invalid``, ``registration_done``, ``registration_refused``,
``verification_done``, ``link_state``.  Each SSE message is::

    id: <sequence number>
    event: <name>
    data: <JSON object>

A comment line (``: keep-alive``) is sent every :data:`service.event_bus.KEEPALIVE_S` seconds.
"""

from __future__ import annotations

import json
from collections.abc import AsyncIterator
from typing import Any

from fastapi import APIRouter, Request
from fastapi.responses import StreamingResponse

from service.api.deps import CtxDep


def format_sse(item: tuple[int, str, dict[str, Any]] | None) -> str:
    if item is None:
        return ": keep-alive\n\n"
    seq, event, data = item
    return f"id: {seq}\nevent: {event}\ndata: {json.dumps(data)}\n\n"


router = APIRouter(tags=["events"])


@router.get(
    "/events",
    summary="Server-sent events",
    description=(
        "A `text/event-stream` of service events: `scan_arrived`, `scan_invalid`, `registration_done`, "
        "`registration_refused`, `verification_done`, `link_state`, `scan_reopened`, "
        "`registration_withdrawn`, `scan_files_deleted`.  `data` is a JSON object, e.g. "
        '`event: registration_done` / `data: {"registration_id": 3, "scan_id": 2, "fre_mm": 0.08}`.'
    ),
    response_class=StreamingResponse,
    responses={200: {"content": {"text/event-stream": {}}, "description": "event stream"}},
)
async def events(request: Request, ctx: CtxDep) -> StreamingResponse:
    bus = ctx.bus

    async def gen() -> AsyncIterator[str]:
        yield ": connected\n\n"
        async for item in bus.subscribe():
            if await request.is_disconnected():
                return
            yield format_sse(item)

    return StreamingResponse(
        gen(),
        media_type="text/event-stream",
        headers={"Cache-Control": "no-cache", "X-Accel-Buffering": "no"},
    )
