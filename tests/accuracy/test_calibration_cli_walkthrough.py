"""docs/calibration.md "Calibrating from the CLI", run as written (issue 34, item 2): the bash block
is extracted from the doc and run in a temporary folder with the ``oarmreg`` of this checkout; the
only changes are a smaller scan (the ``small`` preset at the demo's calibration size) and a forced
pose count (``--n 6``, the least the planner takes; the doc keeps the planner's own count, 15–18
poses in this volume) so it fits the test budget.  Ends in a registration through the calibrated model."""

from __future__ import annotations

import json
import os
import re
import subprocess
import sys
from pathlib import Path

import pytest

from tests.helpers.paths import REPO

DOC = REPO / "docs" / "calibration.md"
SMALL_SCAN = "--preset small --rows 200 --columns 200 --slices 120 --views 120"
"""The scan ``oarmreg demo --calibrate`` uses (service/cli/commands/demo_calibrate.py CAL_PRESET)."""
FORCED_POSES = 6
"""``calibrate plan --n``: the least it takes."""


def walkthrough() -> str:
    text = DOC.read_text(encoding="utf-8")
    marker = text.index("<!-- cli-walkthrough")
    m = re.search(r"```bash\n(.*?)```", text[marker:], re.S)
    assert m, "no bash block after the cli-walkthrough marker"
    return m.group(1)


@pytest.mark.timeout(900)
def test_the_documented_cli_calibration_runs_end_to_end(tmp_path: Path) -> None:
    script = walkthrough()
    assert script.count("oarmreg simulate") == 3
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
    poses = json.loads((work / "POSES.json").read_text())["poses"]
    plan = json.loads((work / "plan.json").read_text())["poses"]
    assert len(poses) == len(plan) >= 6
    assert (work / "cal" / "calibration.json").is_file() and (work / "cal" / "robot.urdf").is_file()
    reg = json.loads((work / "reg.json").read_text())
    assert reg["provenance"]["calibration"]["dir"] == "cal"
    assert reg["fre_mm"] < 0.5
