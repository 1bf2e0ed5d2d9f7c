"""The OpenIGTLink listener's per-address share setting and the coalescing of query answers
(service/navigation/igtl/server.py); the listener's behaviour under a flood and with its slots taken
is tested against the real service in tests/faults/test_igtl_flood.py."""

from __future__ import annotations

import time
from types import SimpleNamespace
from typing import Any

import pytest
from pydantic import ValidationError

from service.navigation.igtl.server import _AnswerKey, _Client, _Out
from service.settings import IgtlSettings


def test_an_explicit_share_above_max_clients_is_refused_and_the_default_is_capped() -> None:
    with pytest.raises(ValidationError, match="max_clients_per_address"):
        IgtlSettings(max_clients=4, max_clients_per_address=5)
    assert IgtlSettings(max_clients=4).address_share == 4
    assert IgtlSettings().address_share == 8
    assert IgtlSettings(max_clients=16, max_clients_per_address=2).address_share == 2


def _client(queue_max: int) -> tuple[_Client, dict[str, int]]:
    counters: dict[str, int] = {"dropped": 0, "answers_coalesced": 0}
    server: Any = SimpleNamespace(config=IgtlSettings(client_queue_max=queue_max), counters=counters)
    writer: Any = SimpleNamespace(get_extra_info=lambda name: ("127.0.0.1", 5000))
    return _Client(server, None, writer), counters  # type: ignore[arg-type]


def _answer(typ: str, device: str, tag: bytes) -> _Out:
    return _Out(typ, device, tag, {}, time.time())


def test_a_newer_answer_replaces_the_pending_one_of_its_type_and_device() -> None:
    client, counters = _client(queue_max=8)
    for i in range(5):
        client.offer_answer(_answer("POINT", "PhantomSpheres", bytes([i])))
    client.offer_answer(_answer("TRANSFORM", "ToolToImage", b"t"))
    assert client.queue.qsize() == 2
    assert client.answers[_AnswerKey("POINT", "PhantomSpheres")].content == bytes([4])  # the latest
    assert counters["answers_coalesced"] == 4


def test_an_answer_dropped_from_a_full_queue_is_forgotten() -> None:
    client, counters = _client(queue_max=1)
    client.offer_answer(_answer("STATUS", "oarmreg", b"s"))
    client.offer(_answer("TRANSFORM", "ToolToImage", b"push"))  # full: the answer's key is dropped
    assert counters["dropped"] == 1
    assert client.answers == {}
    client.offer_answer(_answer("STATUS", "oarmreg", b"s2"))  # queued again, not coalesced into nothing
    assert client.queue.qsize() == 1 and counters["answers_coalesced"] == 0


def test_the_client_list_is_read_from_a_copy_while_clients_connect() -> None:
    """GET /status reads the clients on a worker thread while the event loop adds them: under load
    (200 clients connecting, ``.ci/run`` beside stress-ng) iterating the live set raised "Set changed
    size during iteration" and /status answered 500."""
    from service.navigation.igtl.server import IgtlServer

    server = IgtlServer(IgtlSettings(enabled=True, port=0), source=None)  # type: ignore[arg-type]

    class Joining:
        """A client whose ``info()`` lets another client connect, as the loop does meanwhile."""

        def __init__(self, n: int) -> None:
            self.n = n

        def info(self) -> dict[str, object]:
            server._clients.add(Joining(self.n + 100))  # type: ignore[arg-type]
            return {"peer": f"127.0.0.{self.n}:5000"}

    server._clients.update(Joining(k) for k in range(3))  # type: ignore[misc]
    assert [d["peer"] for d in server.client_info()] == [f"127.0.0.{k}:5000" for k in range(3)]
