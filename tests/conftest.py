"""Shared fixtures.  An autouse fixture fails any test that leaves threads behind."""

from __future__ import annotations

import threading
import time
from collections.abc import Iterator
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
CONFIGS = REPO / "configs"
THREAD_LEAK_GRACE_S = 5.0
"""A thread still alive this long after its test ended counts as leaked."""


@pytest.fixture(autouse=True)
def no_leaked_threads() -> Iterator[None]:
    before = set(threading.enumerate())
    yield
    deadline = time.monotonic() + THREAD_LEAK_GRACE_S
    while True:
        leaked = [t for t in threading.enumerate() if t not in before and t.is_alive() and not t.daemon]
        if not leaked or time.monotonic() > deadline:
            break
        leaked[0].join(timeout=0.05)
    assert not leaked, f"test left threads running: {[t.name for t in leaked]}"


@pytest.fixture(scope="session")
def phantom_path() -> Path:
    return CONFIGS / "phantoms" / "bai2018_cube.toml"


@pytest.fixture(scope="session")
def phantom(phantom_path: Path):  # type: ignore[no-untyped-def]
    from registration.phantom import load_phantom

    return load_phantom(phantom_path)
