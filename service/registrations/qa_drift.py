"""The QA drift rule (docs/operations.md "QA drift").

Over the last ``window`` QA checks (verifications taken at a QA protocol's pose) under the active
calibration: their mean error above ``limit_mm`` fires, and so does a series that rises at every
check by more than ``rise_mm`` from first to last.  Fewer than ``window`` checks never fire.
Pure: the figures in, a verdict out.
"""

from __future__ import annotations

import itertools
from collections.abc import Sequence
from dataclasses import dataclass


@dataclass(frozen=True)
class DriftVerdict:
    """Why the rule fired (``reason`` ``"mean"`` or ``"rise"``) and on which figures."""

    reason: str
    means_mm: tuple[float, ...]
    mean_mm: float
    rise_mm: float
    limit_mm: float
    rise_limit_mm: float

    def describe(self) -> str:
        means = ", ".join(f"{m:.2f}" for m in self.means_mm)
        if self.reason == "mean":
            what = f"their mean {self.mean_mm:.2f} mm exceeds qa.drift_mean_mm {self.limit_mm:g} mm"
        else:
            what = (
                f"they rose at every check, by {self.rise_mm:.2f} mm "
                f"(over qa.drift_rise_mm {self.rise_limit_mm:g} mm)"
            )
        return f"the last {len(self.means_mm)} QA checks' mean errors are {means} mm: {what}"


def drift(means_mm: Sequence[float], *, window: int, limit_mm: float, rise_mm: float) -> DriftVerdict | None:
    """The verdict on ``means_mm`` (oldest first; only the last ``window`` count), None: no drift."""
    if window < 2 or len(means_mm) < window:
        return None
    last = tuple(float(m) for m in means_mm[-window:])
    mean = sum(last) / len(last)
    rise = last[-1] - last[0]
    rising = all(b > a for a, b in itertools.pairwise(last))
    if mean > limit_mm:
        return DriftVerdict("mean", last, mean, rise, limit_mm, rise_mm)
    if rising and rise > rise_mm:
        return DriftVerdict("rise", last, mean, rise, limit_mm, rise_mm)
    return None
