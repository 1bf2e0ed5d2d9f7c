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


def test_a_raising_listener_is_logged_counted_and_the_others_still_run(
    caplog: pytest.LogCaptureFixture,
) -> None:
    bus = EventBus()
    got: list[RegistrationDone] = []

    def broken(event: RegistrationDone) -> None:
        raise ValueError(f"bug on {event.registration_id}")

    bus.listen(RegistrationDone, broken)
    bus.listen(RegistrationDone, got.append)
    with caplog.at_level("ERROR", logger="service.event_bus"):
        bus.publish(done(1))  # the publisher does not see the exception
        bus.publish(done(2))
    assert got == [done(1), done(2)]
    [failed] = bus.listener_failures()
    assert failed.listener.endswith("broken") and failed.event == "registration_done"
    assert (failed.failures, failed.failing, failed.safety) == (2, True, False)
    assert failed.last_error == "ValueError: bug on 2"
    assert bus.failing_safety_listeners() == []
    logged = [r for r in caplog.records if "broken" in r.getMessage()]
    assert len(logged) == 2 and "registration_done" in logged[-1].getMessage()
    assert '"registration_id": 2' in logged[-1].getMessage() and logged[-1].exc_info is not None


def test_a_failing_safety_listener_is_failing_until_its_next_success() -> None:
    bus = EventBus()
    outcomes = iter([OSError("down"), None, RuntimeError("again")])

    def duty(event: RegistrationDone) -> None:
        e = next(outcomes)
        if e is not None:
            raise e

    subs = Subscriptions(bus)
    subs.listen(RegistrationDone, duty, safety=True)
    bus.publish(done(1))
    [failing] = bus.failing_safety_listeners()
    assert failing.listener.endswith("duty") and failing.safety and failing.failures == 1
    assert "failed 1 time(s) on registration_done" in failing.describe()
    bus.publish(done(2))
    assert bus.failing_safety_listeners() == []
    [kept] = bus.listener_failures()  # the count stays after the success
    assert (kept.failures, kept.failing) == (1, False)
    bus.publish(done(3))
    assert [f.failures for f in bus.failing_safety_listeners()] == [2]
    subs.close()
    bus.publish(done(4))  # unbound: not called (the iterator would be exhausted)
