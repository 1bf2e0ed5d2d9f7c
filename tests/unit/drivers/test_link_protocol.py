"""Every controller link, and the process-isolated proxy the service runs, offers the whole
:class:`drivers.base.RobotLink` protocol, what the stillness judgement relies on included (the
service's capture calls these directly, without probing with ``getattr``)."""

from __future__ import annotations

import inspect

import pytest

from drivers.base import RobotLink
from drivers.factory import open_link
from drivers.link_process import ProcessLink

URLS = ("simple-message://127.0.0.1:1", "modbus://127.0.0.1:1", "serial:///dev/null")
STILLNESS = ("streamed", "wait_past", "sessions", "status_history", "joint_resolution_rad")


@pytest.mark.parametrize("url", URLS)
@pytest.mark.parametrize("kind", ["link", "process"])
def test_every_link_offers_the_protocol(url: str, kind: str) -> None:
    link = open_link(url) if kind == "link" else ProcessLink(url)
    assert isinstance(link, RobotLink)
    for name in STILLNESS:
        assert hasattr(link, name), (url, kind, name)
    assert isinstance(link.streamed, bool)
    assert link.sessions() == [] and link.status_history(0.0) == []  # never started: nothing yet
    assert len(link.joint_resolution_rad([0.0] * 6)) == 6


def test_the_protocol_declares_what_stillness_uses() -> None:
    members = set(RobotLink.__annotations__) | {
        n for n, _ in inspect.getmembers(RobotLink, inspect.isfunction)
    }
    assert set(STILLNESS) <= members
