"""Every accuracy test runs the O-arm simulator (seconds to tens of seconds each): marked ``slow``,
so ``make test-fast`` (``-m "not slow"``) leaves them out of the edit loop; ``make test`` runs them."""

from __future__ import annotations

from pathlib import Path

import pytest

HERE = Path(__file__).resolve().parent


def pytest_collection_modifyitems(items: list[pytest.Item]) -> None:
    for item in items:
        if HERE in Path(str(item.fspath)).resolve().parents:
            item.add_marker(pytest.mark.slow)
