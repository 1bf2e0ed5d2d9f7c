"""The reference OpenIGTLink C++ library's client (``tests/peers/igtl_ref_client.cxx``), built once per
session with g++ against Debian's ``libopenigtlink-dev`` 1.11 (``.ci/run`` installs both when
missing): :func:`build_ref_client` (the session fixture ``ref_client`` in tests/conftest.py) and the
marker for tests that need it."""

from __future__ import annotations

import shutil
import subprocess
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[2]
SOURCE = REPO / "tests" / "peers" / "igtl_ref_client.cxx"
INCLUDE = Path("/usr/include/openigtlink")
GXX = shutil.which("g++")

needs_ref_client = pytest.mark.skipif(
    GXX is None or not (INCLUDE / "igtlTransformMessage.h").is_file(),
    reason="g++ or libopenigtlink-dev not installed (.ci/run installs them)",
)


def build_ref_client(folder: Path) -> Path:
    """The C++ client, built into ``folder``."""
    assert GXX is not None
    exe = folder / "igtl_ref_client"
    subprocess.run(
        [GXX, "-O1", "-std=c++11", f"-I{INCLUDE}", str(SOURCE), "-lOpenIGTLink", "-o", str(exe)],
        check=True, capture_output=True, timeout=120,
    )  # fmt: skip
    return exe
