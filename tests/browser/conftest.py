"""Fixtures every browser test module shares: one headless Chromium per module (the
distribution's ``chromium``, tests.browser.harness), a fresh context per test."""

from __future__ import annotations

from collections.abc import Iterator
from typing import Any

import pytest

from tests.browser import harness as h


@pytest.fixture(scope="module")
def browser() -> Iterator[Any]:
    with h.browser() as b:
        yield b


@pytest.fixture
def context(browser: Any) -> Iterator[Any]:
    ctx = browser.new_context(viewport={"width": 1400, "height": 1000})
    ctx.set_default_timeout(h.DEADLINE_S * 1000)
    try:
        yield ctx
    finally:
        ctx.close()
