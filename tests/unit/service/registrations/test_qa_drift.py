"""The QA drift rule (service.registrations.qa_drift), on its own."""

from __future__ import annotations

import sqlite3
from pathlib import Path

from hypothesis import given
from hypothesis import strategies as st

from service.registrations.qa_drift import drift

RULE = {"window": 3, "limit_mm": 0.5, "rise_mm": 0.2}


def test_the_mean_of_the_last_window_over_the_limit_fires() -> None:
    v = drift([0.1, 0.6, 0.5, 0.55], **RULE)
    assert v is not None and v.reason == "mean" and v.means_mm == (0.6, 0.5, 0.55)
    assert abs(v.mean_mm - 0.55) < 1e-12 and "exceeds qa.drift_mean_mm 0.5 mm" in v.describe()
    assert drift([0.9, 0.4, 0.5, 0.5], **RULE) is None  # an old bad check has left the window


def test_a_monotonic_rise_over_the_limit_fires_and_anything_less_does_not() -> None:
    v = drift([0.1, 0.2, 0.31], **RULE)
    assert v is not None and v.reason == "rise" and abs(v.rise_mm - 0.21) < 1e-12
    assert drift([0.1, 0.2, 0.29], **RULE) is None  # rises by 0.19 mm
    assert drift([0.1, 0.1, 0.31], **RULE) is None  # not at every check
    assert drift([0.1, 0.31], **RULE) is None  # fewer than the window


@given(st.lists(st.floats(0.0, 0.49), min_size=3, max_size=10))
def test_a_series_under_the_limit_fires_only_on_a_monotonic_rise(means: list[float]) -> None:
    last = means[-3:]
    rising = last[0] < last[1] < last[2] and last[2] - last[0] > 0.2
    v = drift(means, **RULE)
    assert (v is not None) == rising
    if v is not None:
        assert v.reason == "rise"


def test_the_rule_reads_only_the_named_calibrations_checks_and_skips_withdrawn_ones(tmp_path: Path) -> None:
    from service.store import Database
    from tests.integration.qa_seed import seed_calibration, seed_qa_series

    seed_qa_series(tmp_path, [0.1, 0.2, 0.3])
    cal = seed_calibration(tmp_path)
    _, mid = seed_qa_series(tmp_path, [0.7, 0.8])
    seed_qa_series(tmp_path, [0.4])
    _, under_cal = seed_qa_series(tmp_path, [0.9, 0.95], calibration_id=cal)
    db = Database.open(tmp_path / "oarmreg.sqlite3")
    try:
        t = db.qa_trend
        assert t.last_means(cal, 3) == [0.9, 0.95]
        assert t.last_means(None, 3) == [0.7, 0.8, 0.4]
        assert [p.verification_id for p in t.checks(cal)] == under_cal
        assert len(t.checks()) == 8 and len(t.checks(nominal=True)) == 6
        assert [f.calibration_id for f in t.fre()] == [None, None, None, cal]
    finally:
        db.close()
    raw = sqlite3.connect(tmp_path / "oarmreg.sqlite3")  # a changed scan withdraws its verification
    with raw:
        raw.execute("UPDATE verifications SET withdrawn_at = 'x' WHERE id = ?", (mid[1],))
    raw.close()
    db = Database.open(tmp_path / "oarmreg.sqlite3")
    try:
        assert db.qa_trend.last_means(None, 3) == [0.3, 0.7, 0.4]
        assert [p.withdrawn for p in db.qa_trend.checks() if p.verification_id == mid[1]] == [True]
    finally:
        db.close()
