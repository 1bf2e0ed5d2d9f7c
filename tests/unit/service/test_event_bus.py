"""The bus's in-process listeners: called with the typed event, by class, until removed."""

from __future__ import annotations

import json

import pytest

from service.event_bus import EventBus, Subscriptions
from service.events import Event, LinkState, RegistrationDone, RegistrationRefused, ScanArrived


def done(reg_id: int) -> RegistrationDone:
    return RegistrationDone(registration_id=reg_id, scan_id=1, series_uid="1.2", fre_mm=0.1, n_matched=8)


def test_listener_gets_its_event_only_until_removed() -> None:
    bus = EventBus()
    got: list[RegistrationDone] = []
    bus.listen(RegistrationDone, got.append)
    bus.publish(done(1))
    bus.publish(RegistrationRefused(registration_id=2, scan_id=1, series_uid="1.2", title="T", reason="r"))
    bus.unlisten(RegistrationDone, got.append)
    bus.publish(done(3))
    assert got == [done(1)]
    recent = bus.recent()
    assert [p.event.name for p in recent] == [
        "registration_done",
        "registration_refused",
        "registration_done",
    ]
    assert [p.seq for p in recent] == [1, 2, 3]
    assert json.loads(recent[0].data_json) == done(1).payload()


def test_listening_to_a_class_that_is_not_an_event_is_refused() -> None:
    from service.events import _ScanRecorded

    with pytest.raises(TypeError, match="_ScanRecorded is not a service event"):
        EventBus().listen(_ScanRecorded, lambda event: None)


def test_publishing_an_unregistered_event_is_refused() -> None:
    class Stray(Event):  # no name: not one of service.events
        pass

    with pytest.raises(TypeError, match="Stray is not a service event"):
        EventBus().publish(Stray())


def test_subscriptions_close_removes_every_listener_once() -> None:
    bus = EventBus()
    seen: list[Event] = []
    subs = Subscriptions(bus)
    subs.listen(RegistrationDone, seen.append)
    subs.listen(LinkState, seen.append)
    bus.publish(done(1))
    subs.close()
    subs.close()  # idempotent: the app pushes it twice on its exit stack
    bus.publish(done(2))
    bus.publish(LinkState(url="u", state="down", reason="r"))
    assert seen == [done(1)]


def test_a_listener_of_one_class_does_not_see_another() -> None:
    bus = EventBus()
    seen: list[ScanArrived] = []
    bus.listen(ScanArrived, seen.append)
    bus.publish(done(1))
    assert seen == []
