"""``calibrate plan`` says what fewer poses would cost (issue 42, item 2)."""

from __future__ import annotations

import numpy as np

from registration.calibration.planner import PosePlan, shorter_counts
from service.cli.commands.calibrate import pendant_table, shorter_plans_text


def test_shorter_counts_are_few_below_the_plan_and_start_at_the_least() -> None:
    assert shorter_counts(6) == []
    assert shorter_counts(8) == [6]
    assert shorter_counts(12) == [6, 7, 10]
    assert shorter_counts(20) == [6, 10, 15, 18]
    assert all(
        len(shorter_counts(k)) <= 4 and all(6 <= c < k for c in shorter_counts(k)) for k in range(6, 60)
    )


def test_the_printout_counts_scans_and_minutes_and_lists_shorter_plans() -> None:
    plan = PosePlan(
        joints_rad=np.zeros((20, 6)),
        predicted_condition_number=9.0,
        tilt_deg=np.zeros(20),
        inside_margin_mm=np.zeros(20),
        max_joint_step_rad=np.zeros(20),
        n_candidates=100,
        predicted_error_mm=0.09,
        predicted_rms_mm=0.05,
        shorter=((6, 0.14, 0.26), (13, 0.07, 0.12)),
    )
    text = shorter_plans_text(plan)
    assert "20 calibration poses + 1 registration + 1 verification = 22 (about 22–44 min" in text
    assert "with  6 poses: predicted 0.140 mm RMS" in text and "with 20 poses (this plan)" in text
    assert plan.to_dict()["shorter_plans"][0] == {
        "n_poses": 6,
        "predicted_rms_mm": 0.14,
        "predicted_error_mm": 0.26,
    }


def test_the_pendant_table_is_degrees_in_joint_order() -> None:
    table = pendant_table([{"joints_deg": [10.0, -20.5, 90.0, 0.0, 45.0, 180.0]}])
    assert table.splitlines()[0].split()[:7] == ["pose", "J1", "J2", "J3", "J4", "J5", "J6"]
    assert table.splitlines()[1].split() == ["0", "10.00", "-20.50", "90.00", "0.00", "45.00", "180.00"]
