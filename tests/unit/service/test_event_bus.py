"""The bus's in-process listeners: called with the published data, by name, until removed."""

from __future__ import annotations

from typing import Any

import pytest

from service.event_bus import EventBus


def test_listener_gets_its_event_only_until_removed() -> None:
    bus = EventBus()
    got: list[dict[str, Any]] = []
    bus.listen("registration_done", got.append)
    bus.publish("registration_done", {"registration_id": 1})
    bus.publish("registration_refused", {"registration_id": 2})
    bus.unlisten("registration_done", got.append)
    bus.publish("registration_done", {"registration_id": 3})
    assert got == [{"registration_id": 1}]
    assert [name for _, name, _ in bus.recent()] == [
        "registration_done",
        "registration_refused",
        "registration_done",
    ]


def test_listening_to_an_unknown_event_is_refused() -> None:
    with pytest.raises(ValueError, match="unknown event 'registration_accepted'"):
        EventBus().listen("registration_accepted", lambda data: None)
