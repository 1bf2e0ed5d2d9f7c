"""The browser tests' console check forgives only the failed loads a test says it provoked (issue #42
item 8: a page test failed under load on the 409 its own withdrawal causes).  No browser needed:
the messages are recorded as ``PageWatch.on_console`` records Chromium's."""

from __future__ import annotations

from dataclasses import dataclass

from tests.browser import harness as h

ORIGIN = "http://127.0.0.1:8123"
PROVOKED = (("/registration/current", 409),)


@dataclass
class _Msg:
    """What Playwright's ConsoleMessage gives: type, text and the source location."""

    type: str
    text: str
    location: dict[str, object]


def _watch(*msgs: _Msg) -> h.PageWatch:
    w = h.PageWatch(page=None, origin=ORIGIN)
    for m in msgs:
        w.on_console(m)
    return w


def _load_error(status: str, url: str) -> _Msg:
    return _Msg("error", f"{h.FAILED_LOAD} {status}", {"url": url, "lineNumber": 0})


def test_the_provoked_409_on_the_current_registration_is_forgiven() -> None:
    w = _watch(_load_error("409 (Conflict)", f"{ORIGIN}/registration/current"))
    assert w.console_errors(PROVOKED) == []
    assert w.console_errors() == [f"{h.FAILED_LOAD} 409 (Conflict)"]  # not unless the test says so


def test_every_other_error_still_counts() -> None:
    others = (
        _load_error("500 (Internal Server Error)", f"{ORIGIN}/registration/current"),
        _load_error("409 (Conflict)", f"{ORIGIN}/register"),
        _load_error("409 (Conflict)", f"{ORIGIN}/registration/current/extra"),
        _load_error("409 (Conflict)", "http://127.0.0.1:9/registration/current"),  # another origin
        _Msg("error", "Uncaught TypeError: x is undefined", {"url": f"{ORIGIN}/static/app.js"}),
    )
    w = _watch(*others)
    w.page_errors.append("ReferenceError: y is not defined")
    assert w.console_errors(PROVOKED) == [m.text for m in others] + w.page_errors
    assert _watch(_Msg("warning", "slow", {"url": ORIGIN + "/"})).console_errors() == []
