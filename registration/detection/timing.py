"""Seconds per named detection stage (what ``DetectionResult.timings_s`` reports)."""

from __future__ import annotations

import time
from collections.abc import Iterator
from contextlib import contextmanager
from typing import Final


class StageTimer:
    """Seconds per named stage: ``with timer.stage("mar_s"): ...`` adds that block's time.

    ``stages`` are created at 0.0 up front (so a stage that never ran still reports 0 s) and keep
    their order in :attr:`seconds`.
    """

    def __init__(self, stages: tuple[str, ...] = ()) -> None:
        self.seconds: dict[str, float] = dict.fromkeys(stages, 0.0)

    @contextmanager
    def stage(self, name: str) -> Iterator[None]:
        t0 = time.perf_counter()
        try:
            yield
        finally:
            self.seconds[name] = self.seconds.get(name, 0.0) + time.perf_counter() - t0


TIMED_STAGES: Final = ("threshold_s", "group_s", "components_s", "mar_s", "circles_s", "centres_s")
"""The stages :func:`detect_spheres` reports (plus ``total_s``)."""
