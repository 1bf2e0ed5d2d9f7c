"""Issue #21 in a real browser: the QA trend panel and the "recalibrate" banner.

Two services, each on a data folder holding a QA series written through the service's own store
before start (tests/integration/qa_seed.py): a drifting one raises the banner, a steady one does
not.  Waits are on selectors and page conditions, never on time.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

import pytest

from tests.browser import harness as h
from tests.integration.qa_seed import seed_qa_series

pytestmark = pytest.mark.skipif(
    h.chromium_missing() is not None and os.environ.get("CI") != "true", reason=str(h.chromium_missing())
)

DRIFTING = [0.20, 0.30, 0.42, 0.55]  # the last 3 rise at every check, by 0.25 mm (> qa.drift_rise_mm)
STEADY = [0.20, 0.22, 0.19, 0.21]


@pytest.fixture(scope="module")
def world(phantom: Any) -> h.World:
    from registration.model.kinematics import RobotModel

    return h.World(phantom, RobotModel.load("tx60"), None, None)  # no scans: the QA series is seeded


def _open(context: Any, svc: h.Service) -> h.PageWatch:
    w = h.watched_page(context, svc.base_url)
    w.page.goto(f"{svc.base_url}/#token={h.TOKEN}")
    w.page.wait_for_selector("#live.ok")
    # the QA panel and the banners are rendered in the same step: once the panel has its verdict,
    # the banners are final for this load
    w.page.wait_for_function("document.getElementById('qa-drift').textContent.length > 0")
    return w


def _clean(w: h.PageWatch) -> None:
    assert not w.foreign_requests(), f"requests left the origin: {w.foreign_requests()}"
    assert not w.console_errors(), f"console errors: {w.console_errors()}"


@pytest.mark.parametrize(
    ("means", "drifting"), [(DRIFTING, True), (STEADY, False)], ids=["drifting", "steady"]
)
def test_the_recalibrate_banner_follows_the_drift_rule(
    tmp_path: Path, world: h.World, context: Any, means: list[float], drifting: bool
) -> None:
    (tmp_path / "data").mkdir()
    beta_mm = -0.0123 if drifting else None  # the face offset β (issue #43), or none fitted
    _, vids = seed_qa_series(tmp_path / "data", means, face_offset_mm=beta_mm)
    with h.running_service(tmp_path, world) as svc:
        w = _open(context, svc)
        trend = svc.client.get("/qa/trend").json()
        assert trend["drift"]["drifting"] is drifting
        banner = w.page.locator("#recalibrate-banner")
        if drifting:
            assert banner.count() == 1
            text = banner.inner_text()
            assert "Recalibrate: QA drifting" in text and "0.25 mm" in text and "calibration session" in text
            assert "Drifting" in w.page.inner_text("#qa-drift")
        else:
            assert banner.count() == 0
            assert "Steady" in w.page.inner_text("#qa-drift")
            assert "Recalibrate" not in w.page.inner_text("#banners")
        # the chart: one bar per QA check, labelled with its verification id and pose
        labels = w.page.locator("#qa-chart svg rect title").evaluate_all(
            "els => els.map((e) => e.textContent)"
        )
        assert [t.split(":")[0] for t in labels] == [
            f"#{v} {p}" for v, p in zip(vids, ["p1", "p2"] * 2, strict=True)
        ]
        assert [float(t.split(": ")[1].split()[0]) for t in labels] == pytest.approx(means, abs=5e-5)
        beta_line = w.page.inner_text("#qa-face-offset")
        assert ("-0.0123" in beta_line) if drifting else ("not fitted" in beta_line), beta_line
        _clean(w)
