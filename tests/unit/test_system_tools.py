"""The dcmtk peers the tests drive are dcmtk's even with this venv activated (pynetdicom installs
apps of the same names into its ``bin``; they took dcmtk's flags as positional arguments and four
DICOM tests failed under an activated venv)."""

from __future__ import annotations

import os
import sys
from pathlib import Path

import pytest

from tests.helpers.system_tools import system_tool


def test_a_tool_of_the_same_name_in_this_venv_is_passed_over(monkeypatch: pytest.MonkeyPatch) -> None:
    venv_bin = Path(sys.prefix) / "bin"
    if not (venv_bin / "storescu").exists():
        pytest.fail(f"pynetdicom's storescu is not in {venv_bin}: the shadowing this test guards is gone?")
    monkeypatch.setenv("PATH", f"{venv_bin}{os.pathsep}{os.environ.get('PATH', '')}")
    found = system_tool("storescu")
    assert found is not None, "dcmtk's storescu is not on PATH (.ci/run installs dcmtk)"
    assert not Path(found).resolve().is_relative_to(Path(sys.prefix).resolve()), found
