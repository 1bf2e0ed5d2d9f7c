"""The test suite needs nothing outside the checkout (issue 34, item 7)."""

from __future__ import annotations

import re
import subprocess
from pathlib import Path

import pytest

from tests.helpers.paths import REPO

TESTS = REPO / "tests"
OUTSIDE_PATTERNS = [
    re.compile(r"""["']shared["']\s*/"""),  # Path(...) / "shared" / ...
    re.compile(r"""\.parent\s*/\s*["']shared"""),
    re.compile(r"""["']/work/"""),  # an absolute path into the build machine
    re.compile(r"OARMREG_REFERENCE_DIR"),
]


def test_kinematics_reference_lives_in_the_repository() -> None:
    """The four reference tests read tests/data/reference_robots/ and can no longer skip."""
    reference = TESTS / "data" / "reference_robots"
    for name in ("fk_reference.json", "staubli_tx60.urdf", "staubli_tx2_60.urdf", "README.md"):
        assert (reference / name).is_file(), name
    source = (TESTS / "unit" / "registration" / "model" / "test_kinematics.py").read_text(encoding="utf-8")
    assert '"data" / "reference_robots"' in source
    assert "pytest.skip" not in source


def test_no_test_names_a_path_outside_the_checkout() -> None:
    offenders = []
    for path in TESTS.rglob("*.py"):
        if path.resolve() == Path(__file__).resolve():
            continue
        text = path.read_text(encoding="utf-8")
        offenders += [f"{path.relative_to(REPO)}: {p.pattern}" for p in OUTSIDE_PATTERNS if p.search(text)]
    assert not offenders


def test_coverage_data_is_not_tracked() -> None:
    try:
        tracked = subprocess.run(
            ["git", "-C", str(REPO), "ls-files", "--", ".coverage"],
            capture_output=True,
            text=True,
            check=True,
        ).stdout
    except (OSError, subprocess.CalledProcessError):
        pytest.skip("not a git checkout")
    assert tracked.strip() == ""
    assert ".coverage" in (REPO / ".gitignore").read_text().split()
