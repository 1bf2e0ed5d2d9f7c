"""System tools the tests drive as real peers, found on ``PATH`` but never in this virtual environment.

pynetdicom installs apps of its own named like dcmtk's (``storescu``, ``echoscu``, ``findscu``...) into
the environment's ``bin``; with the venv activated they come first on ``PATH`` and take dcmtk's flags
(``+sd``, ``-aec``) as positional arguments ("argument port: invalid int value").  The tests that
name dcmtk mean dcmtk (.ci/run installs it).
"""

from __future__ import annotations

import os
import shutil
import sys
from pathlib import Path


def system_tool(name: str) -> str | None:
    """``name`` on ``PATH`` outside this interpreter's environment (``sys.prefix``), or None."""
    env_bin = Path(sys.prefix).resolve()
    dirs = [
        d
        for d in os.environ.get("PATH", "").split(os.pathsep)
        if d and not Path(d).resolve().is_relative_to(env_bin)
    ]
    return shutil.which(name, path=os.pathsep.join(dirs))
