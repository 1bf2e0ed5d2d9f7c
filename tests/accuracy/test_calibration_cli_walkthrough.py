"""docs/calibration.md "Calibrating from the CLI", run as written and checked against the truth of
the simulated cell (issue 34, item 2; the targets are issue 10's).

The bash block is extracted from the doc and run in a temporary folder with the ``oarmreg`` of this
checkout; the only changes are a smaller scan (the ``small`` preset at the demo's calibration size)
and a forced pose count (``--n 6``, the least the planner takes; the doc keeps the planner's own
count, 23–29 poses on the test bed's cells) so it fits the test budget.  It ends in a registration through
the calibrated model after the O-arm was moved.

The scans come from ``simulate --joints --placement``: a seeded true cell
(:func:`mocks.oarm.placement.make_placement`: joint-origin errors, rod error, J2/J3 sag,
repeatability, encoder noise) behind one hidden ``image_from_robot`` per placement name.  This
module rebuilds that cell to measure the calibrated chain at held-out poses of the moved O-arm's
volume against the truth; it replaced ``test_calibration_dicom.py``, which built the same session
in Python (issue 10) and simulated every scan a second time.
"""

from __future__ import annotations

import json
import math
import os
import re
import subprocess
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import pydicom
import pytest
from numpy.typing import NDArray

from tests.helpers.paths import REPO

F64 = NDArray[np.float64]
DOC = REPO / "docs" / "calibration.md"
SMALL_SCAN = "--preset small --rows 200 --columns 200 --slices 120 --views 120"
"""The scan ``oarmreg demo --calibrate`` uses (service/cli/commands/demo_calibrate.py CAL_PRESET)."""
FORCED_POSES = 6
"""``calibrate plan --n``: the least it takes."""
N_HELD_OUT = 10
MAX_MEAN_MM = 0.10
MAX_MAX_MM = 0.25
"""Issue 10's targets at held-out poses after calibration (mean / max per sphere centre)."""
MIN_IMPROVEMENT = 5.0
"""The nominal model is ≈ 1 mm off on this cell; calibration must cut the mean error ≥ 5 ×."""
pytestmark = pytest.mark.timeout(900)  # the module's session: ~50 s idle, minutes on a loaded machine


def walkthrough() -> str:
    text = DOC.read_text(encoding="utf-8")
    marker = text.index("<!-- cli-walkthrough")
    m = re.search(r"```bash\n(.*?)```", text[marker:], re.S)
    assert m, "no bash block after the cli-walkthrough marker"
    return m.group(1)


@dataclass
class Session:
    work: Path
    calibration: dict[str, Any]
    plan: list[dict[str, Any]]
    poses: list[dict[str, Any]]
    stdout: str


@pytest.fixture(scope="module")
def session(tmp_path_factory: pytest.TempPathFactory) -> Session:
    tmp_path = tmp_path_factory.mktemp("cli-walkthrough")
    script = walkthrough()
    assert script.count("oarmreg simulate") == 4
    script = script.replace("oarmreg simulate", f"oarmreg simulate {SMALL_SCAN}")
    assert script.count("oarmreg calibrate plan") == 1
    script = script.replace("oarmreg calibrate plan", f"oarmreg calibrate plan --n {FORCED_POSES}")
    bin_dir = Path(sys.executable).parent
    env = {
        **{k: v for k, v in os.environ.items() if not k.startswith("OARMREG_")},
        "PATH": f"{bin_dir}{os.pathsep}{os.environ.get('PATH', '')}",
        "PYTHONPATH": str(REPO),
    }
    done = subprocess.run(
        ["bash", "-euo", "pipefail", "-c", script],
        cwd=tmp_path,
        env=env,
        capture_output=True,
        text=True,
        timeout=880,
        check=False,
    )
    assert done.returncode == 0, done.stderr[-3000:]
    work = tmp_path / "oarmreg-cal"
    return Session(
        work=work,
        calibration=json.loads((work / "cal" / "calibration.json").read_text()),
        plan=json.loads((work / "plan.json").read_text())["poses"],
        poses=json.loads((work / "POSES.json").read_text())["poses"],
        stdout=done.stdout,
    )


def test_the_documented_cli_calibration_runs_end_to_end(session: Session) -> None:
    work = session.work
    assert len(session.poses) == len(session.plan) == FORCED_POSES
    assert (work / "cal" / "calibration.json").is_file() and (work / "cal" / "robot.urdf").is_file()
    reg = json.loads((work / "reg.json").read_text())
    assert reg["provenance"]["calibration"]["dir"] == "cal"
    assert reg["fre_mm"] < 0.5


def test_the_plan_speaks_the_pendants_degrees_and_counts_the_scans(session: Session) -> None:
    """Issue 42, item 2: the poses in degrees J1…J6 (printed and written), the scans it asks for."""
    for pose in session.plan:
        assert pose["joints_deg"] == pytest.approx([math.degrees(v) for v in pose["joints_rad"]], abs=1e-3)
    rows = re.findall(r"^\s+(\d+)((?:\s+-?\d+\.\d\d){6})$", session.stdout, re.M)
    assert [int(k) for k, _ in rows] == list(range(FORCED_POSES)), session.stdout
    assert [float(v) for v in rows[0][1].split()] == pytest.approx(session.plan[0]["joints_deg"], abs=0.006)
    assert f"{FORCED_POSES} calibration poses + 1 registration + 1 verification = {FORCED_POSES + 2}" in (
        session.stdout
    )


def test_the_documented_verification_passes_through_the_calibration(session: Session) -> None:
    """Step 6: ``verify --joints`` computed the robot points through reg.json's calibration."""
    ver = json.loads((session.work / "verify.json").read_text())
    assert ver["passed"] is True and ver["n_matched"] == ver["n_expected"] == 28, ver
    assert ver["provenance"]["calibration"]["dir"] == "cal"
    assert ver["max_mm"] <= MAX_MAX_MM


def test_every_pose_was_detected_and_matched(session: Session) -> None:
    c = session.calibration
    assert len(c["poses"]) == FORCED_POSES
    assert all(len(p["sphere_residuals_mm"]) >= 26 for p in c["poses"])
    assert c["outlier_poses"] == []


def _held_out_errors_mm(work: Path) -> tuple[F64, F64]:
    """Per-sphere errors (mm) at :data:`N_HELD_OUT` poses of the moved O-arm's volume that were not
    scanned: through the calibrated model and ``reg.json``, and through the nominal model and a
    nominal registration of the same scan; against the true cell."""
    from mocks.oarm.placement import make_placement
    from mocks.oarm.simulator import AcquisitionSettings
    from registration.calibration.planner import PlannerParams, ScanVolume, feasible_poses
    from registration.calibration.urdf import read_chain
    from registration.io.resources import default_phantom
    from registration.model import frames
    from registration.model.kinematics import RobotModel, default_tool0_from_phantom
    from registration.model.phantom import load_phantom
    from service.cli.main import main

    reg_nom = work / "reg-nominal.json"
    assert main(["register", str(work / "moved"), "--joints", str(work / "moved" / "joints.json"),
                 "--json", str(reg_nom)]) == 0  # fmt: skip
    pts = load_phantom(default_phantom()).centres_phantom_mm
    s = AcquisitionSettings.preset("small", rows=200, columns=200, n_slices=120, n_views=120)
    volume = ScanVolume(fov_radius_mm=s.fov_radius_mm, half_length_mm=s.n_slices * s.slice_spacing_mm / 2)
    moved = make_placement("after-move")  # the doc's step 5
    nominal, rod = RobotModel.load("tx60"), default_tool0_from_phantom()
    start = np.array(json.loads((work / "moved" / "joints.json").read_text())["joints_rad"])
    params = PlannerParams(tilts_deg=(0.0, 20.0, 40.0), shift_mm=10.0)
    chain = read_chain(nominal.urdf_path)
    cand, _, _ = feasible_poses(moved.image_from_robot, chain, rod, pts, start, volume=volume, params=params)
    assert len(cand) >= N_HELD_OUT
    held = [cand[int(i)] for i in np.linspace(0, len(cand) - 1, N_HELD_OUT).round()]
    cal = json.loads((work / "cal" / "calibration.json").read_text())
    cal_model, cal_rod = RobotModel.load(work / "cal" / "robot.urdf"), np.array(cal["tool0_from_phantom"])
    y_cal = np.array(json.loads((work / "reg.json").read_text())["image_from_robot"])
    y_nom = np.array(json.loads(reg_nom.read_text())["image_from_robot"])
    rng = np.random.default_rng(0)  # the cell's repeatability and encoder noise at the held-out poses
    cal_err, nom_err = [], []
    for q in held:
        truth = frames.apply(moved.image_from_phantom_true(q, rng), pts)
        q_rep = moved.cell.reported_joints(q, rng)
        through_cal = frames.apply(y_cal @ cal_model.robot_from_tool0(q_rep) @ cal_rod, pts)
        through_nom = frames.apply(y_nom @ nominal.robot_from_tool0(q_rep) @ rod, pts)
        cal_err.append(np.linalg.norm(through_cal - truth, axis=1))
        nom_err.append(np.linalg.norm(through_nom - truth, axis=1))
    return np.concatenate(cal_err), np.concatenate(nom_err)


def test_held_out_error_after_calibration_meets_the_issue_targets(session: Session) -> None:
    cal, nom = _held_out_errors_mm(session.work)
    assert cal.shape == nom.shape == (N_HELD_OUT * 28,)
    assert float(cal.mean()) <= MAX_MEAN_MM, (float(cal.mean()), float(nom.mean()))
    assert float(cal.max()) <= MAX_MAX_MM, float(cal.max())
    assert float(nom.mean()) >= MIN_IMPROVEMENT * float(cal.mean()), (float(cal.mean()), float(nom.mean()))
    # never optimistic: the figure every registration through this calibration carries
    held_rms = math.sqrt(float(np.mean(cal**2)))
    assert session.calibration["predicted_chain_error_mm"] >= held_rms / 1.5, (
        session.calibration["predicted_chain_error_mm"],
        held_rms,
    )


def test_calibration_files_carry_figures_and_provenance(session: Session) -> None:
    from mocks.oarm.placement import placement_frame_of_reference_uid

    c = session.calibration
    prov = c["provenance"]
    first_files = [next((session.work / p["scan_dir"]).glob("*.dcm")) for p in session.poses]
    series = [str(pydicom.dcmread(f, stop_before_pixels=True).SeriesInstanceUID) for f in first_files]
    assert [s["series_uid"] for s in prov["scans"]] == series
    assert prov["frame_of_reference_uid"] == placement_frame_of_reference_uid("bench")
    assert len(prov["config_sha256"]) == 64 and prov["software"].startswith("oarmreg ")
    assert all(p["std_error"] > 0 for p in c["parameters"])
    assert prov["calibration_id"] in (session.work / "cal" / "robot.urdf").read_text(encoding="utf-8")
