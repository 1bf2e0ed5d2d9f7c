"""Settings overrides that make the service react at test speed (shared by the service-loop and
fault suites): short stillness window, quiet period and poll interval, a test token."""

from __future__ import annotations

from pathlib import Path
from typing import Any


def fast_overrides(
    watch: Path, data: Path, link_url: str, token: str, window_s: float, **kw: Any
) -> dict[str, Any]:
    """``load_settings`` overrides for a service on ``watch`` / ``data`` reading ``link_url``."""
    return {
        "watch_dir": watch,
        "data_dir": data,
        "api_token": token,
        "robot.link_url": link_url,
        "robot.connect_timeout_s": 2.0,
        "stillness.window_s": window_s,
        "stillness.max_gap_s": 0.25,
        "watcher.quiet_period_s": 0.3,
        "watcher.poll_interval_s": 0.2,
        **kw,
    }
