"""The bytes of ``GET /events`` stay what navigation clients parse.

A fixed sequence (a registration accepted, a refusal, a withdrawal, a verification) goes through
the real bus and the real ``/events`` route on uvicorn; the bytes read on a loopback socket are
compared with ``golden/events.sse``, captured from the service before its events became typed.
The payloads are the ones the orchestrator publishes for each event, with their fields in the
order it publishes them.
"""

from __future__ import annotations

import threading
from collections.abc import AsyncIterator, Iterator
from contextlib import asynccontextmanager
from pathlib import Path
from types import SimpleNamespace

import httpx
import pytest
from fastapi import FastAPI

from tests.integration.polling import poll_until

GOLDEN = Path(__file__).parent / "golden" / "events.sse"
DEADLINE_S = 30.0
N_EVENTS = 4


@pytest.fixture
def served_bus() -> Iterator[tuple[httpx.Client, object]]:
    import asyncio

    from service.cli.commands.serve import serve_in_thread
    from service.event_bus import EventBus
    from service.http.api.events import router

    bus = EventBus()

    @asynccontextmanager
    async def lifespan(app: FastAPI) -> AsyncIterator[None]:
        bus.bind(asyncio.get_running_loop())
        yield
        bus.close()

    app = FastAPI(lifespan=lifespan)
    app.state.ctx = SimpleNamespace(bus=bus)
    app.include_router(router)
    with serve_in_thread(app) as server, httpx.Client(base_url=server.base_url, timeout=DEADLINE_S) as client:
        yield client, bus


def publish_sequence(bus: object) -> None:
    """The four events, as their producers publish them."""
    from service.event_bus import EventBus
    from service.events import RegistrationDone, RegistrationRefused, RegistrationWithdrawn, VerificationDone

    assert isinstance(bus, EventBus)
    bus.publish(
        RegistrationDone(registration_id=3, scan_id=2, series_uid="1.2.826.0.1.3680043.8.498.1",
                         fre_mm=0.0812345678901, n_matched=8)
    )  # fmt: skip
    bus.publish(
        RegistrationRefused(registration_id=4, scan_id=5, series_uid="1.2.826.0.1.3680043.8.498.2",
                            title="Robot moving during scan",
                            reason="joint 6 moved 0.31° during the scan (\"J6\")")
    )  # fmt: skip
    bus.publish(
        RegistrationWithdrawn(registration_ids=(3,), scan_id=2, was_current=True,
                              reason="scan 2 reopened: 1 instance added (ünïcode)")
    )  # fmt: skip
    bus.publish(
        VerificationDone(verification_id=1, registration_id=6, scan_id=7, mean_mm=0.21,
                         max_mm=0.4000000000000001, passed=False)
    )  # fmt: skip


def record_stream(client: httpx.Client, bus: object) -> bytes:
    chunks: list[bytes] = []
    with client.stream("GET", "/events") as stream:
        it = stream.iter_bytes()
        chunks.append(next(it))  # ": connected"
        poll_until(lambda: bus.n_subscribers == 1, "the SSE subscriber", DEADLINE_S, interval_s=0.01)
        producer = threading.Thread(target=publish_sequence, args=(bus,))  # not the loop's thread
        producer.start()
        producer.join(DEADLINE_S)
        got = b"".join(chunks)
        while got.count(b"\nevent: ") < N_EVENTS or not got.endswith(b"\n\n"):
            chunks.append(next(it))
            got = b"".join(chunks)
    return b"".join(chunks)


def test_events_bytes_match_the_golden_file(served_bus: tuple[httpx.Client, object]) -> None:
    client, bus = served_bus
    got = record_stream(client, bus)
    assert got == GOLDEN.read_bytes()
