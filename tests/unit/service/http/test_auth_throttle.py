"""The failed-authentication throttle (service.http.security.AuthThrottle) on a controlled clock:
allowance, doubling lock-outs capped at api.auth_lockout_max_s, one audit entry per burst, a burst
forgotten after api.auth_failure_memory_s, addresses independent."""

from __future__ import annotations

from pathlib import Path
from types import SimpleNamespace

import pytest

from service.errors import AuthThrottledError
from service.http.security import AuthThrottle
from service.settings import load_settings
from service.store import Database
from tests.helpers.tokens import make_token


class Clock:
    def __init__(self) -> None:
        self.now_s = 1000.0

    def __call__(self) -> float:
        return self.now_s


def _attempt(throttle: AuthThrottle, ctx: SimpleNamespace, address: str) -> int | None:
    """One wrong token from ``address``: None for a plain 401, else the Retry-After of the 429."""
    try:
        throttle.check(ctx.settings.api, address)
        throttle.failed(ctx, address)  # type: ignore[arg-type]
    except AuthThrottledError as r:
        return int(r.headers["Retry-After"])
    return None


def test_backoff_cap_burst_and_independence(tmp_path: Path) -> None:
    settings = load_settings(None, {"api_token": make_token(), "data_dir": tmp_path / "d"})
    cfg = settings.api
    db = Database.open(tmp_path / "oarmreg.sqlite3")
    ctx = SimpleNamespace(settings=settings, db=db)
    clock = Clock()
    throttle = AuthThrottle(clock)
    try:
        assert [_attempt(throttle, ctx, "10.0.0.1") for _ in range(cfg.auth_failures_before_throttle)] == [
            None
        ] * cfg.auth_failures_before_throttle
        waits = []
        for _ in range(8):  # each after its lock-out ended: 1, 2, 4, ... capped at 30
            waits.append(_attempt(throttle, ctx, "10.0.0.1"))
            clock.now_s += cfg.auth_lockout_max_s + 1
        assert waits == [1, 2, 4, 8, 16, 30, 30, 30]
        assert _attempt(throttle, ctx, "10.0.0.2") is None  # another address: its own allowance
        clock.now_s += cfg.auth_failure_memory_s + cfg.auth_lockout_max_s + 1
        assert _attempt(throttle, ctx, "10.0.0.1") is None  # forgotten: a new burst
        entries = [e for e in db.audit.list() if e.action == "auth_throttle"]
        assert [e.principal for e in entries] == ["client:10.0.0.1"]  # one entry for the first burst
    finally:
        db.close()


@pytest.mark.parametrize("value", [31.0, 0.0])
def test_lockout_max_is_at_most_30_s(value: float) -> None:
    from registration.errors import ConfigError

    with pytest.raises(ConfigError, match="auth_lockout_max_s"):
        load_settings(None, {"api.auth_lockout_max_s": value})
