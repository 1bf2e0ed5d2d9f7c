"""Server-sent events: ``GET /events`` (the bus: :class:`service.event_bus.EventBus`).

Event names: ``scan_arrived``, ``scan_invalid``, ``registration_done``, ``registration_refused``,
``verification_done``, ``link_state``, ... (every class of :mod:`service.events`, with its
fields).  Each SSE message is::

    id: <sequence number>
    event: <name>
    data: <JSON object>

A comment line (``: keep-alive``) is sent every :data:`service.event_bus.KEEPALIVE_S` seconds.
"""

from __future__ import annotations

from collections.abc import AsyncIterator

from fastapi import APIRouter, Request
from fastapi.responses import JSONResponse, StreamingResponse

from service.event_bus import Published
from service.http.api.deps import CtxDep, HttpDep, PrincipalDep
from service.http.api.models import EventTicketOut
from service.http.api.problems import problem_response, problem_responses
from service.http.security import EVENTS_PATH
from service.http.tickets import MAX_OUTSTANDING_TICKETS


def format_sse(item: Published | None) -> str:
    """One SSE message (``None``: the keep-alive comment)."""
    if item is None:
        return ": keep-alive\n\n"
    return f"id: {item.seq}\nevent: {item.event.name}\ndata: {item.data_json}\n\n"


router = APIRouter(tags=["events"])


@router.get(
    "/events",
    summary="Server-sent events",
    description=(
        "Authenticate with the Bearer header or, from a browser's `EventSource` (which cannot send "
        "headers), with `?ticket=` from `POST /events/ticket`.  "
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


@router.post(
    "/events/ticket",
    response_model=EventTicketOut,
    summary="A single-use, short-lived ticket for GET /events?ticket=… (for EventSource)",
    description=(
        "Browsers' `EventSource` cannot send `Authorization`; an authenticated client asks for a ticket "
        "(valid `api.event_ticket_ttl_s` seconds, usable once) and opens `/events?ticket=…`.  Bodiless, "
        "but like every mutating request it needs `Content-Type: application/json`."
    ),
    responses=problem_responses(401, 429),
)
async def event_ticket(
    request: Request, ctx: CtxDep, http: HttpDep, principal: PrincipalDep
) -> EventTicketOut | JSONResponse:
    ttl_s = ctx.settings.api.event_ticket_ttl_s
    ticket = http.tickets.mint(principal, ttl_s)
    if ticket is None:
        return problem_response(
            429, "Too many tickets", f"{MAX_OUTSTANDING_TICKETS} event tickets are outstanding; use them or "
            "let them expire before asking for more", request.url.path,
        )  # fmt: skip
    return EventTicketOut(ticket=ticket, expires_in_s=ttl_s, url=f"{EVENTS_PATH}?ticket={ticket}")
