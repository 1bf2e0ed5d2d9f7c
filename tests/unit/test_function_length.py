"""No function longer than :data:`MAX_FUNCTION_LINES` lines in the production packages (issue #35).

Counted on the source (``ast``) from the ``def`` line to the function's last line, docstring and
comments included, decorators not; a nested function counts on its own and inside its parent.
The issue found six over the limit (``write_dicom_series`` 176 lines, ``calibrate`` 146, …); all were
split since, and this keeps it so.
"""

from __future__ import annotations

import ast
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
PACKAGES = ("registration", "drivers", "dicomnet", "service", "mocks")
MAX_FUNCTION_LINES = 100


def long_functions(path: Path, limit: int = MAX_FUNCTION_LINES) -> list[str]:
    """``path:line name (n lines)`` for each function in ``path`` longer than ``limit`` lines."""
    tree = ast.parse(path.read_text(encoding="utf-8"), str(path))
    return [
        f"{path}:{node.lineno} {node.name} ({n} lines)"
        for node in ast.walk(tree)
        if isinstance(node, ast.FunctionDef | ast.AsyncFunctionDef)
        and (n := (node.end_lineno or node.lineno) - node.lineno + 1) > limit
    ]


def test_the_checker_counts_from_def_to_the_last_line(tmp_path: Path) -> None:
    src = tmp_path / "m.py"
    body = "".join(f"    x{i} = {i}\n" for i in range(99))
    src.write_text(f"@decorator\ndef at_limit():\n{body}\n\nasync def over():\n{body}    return 1\n")
    assert long_functions(src) == [f"{src}:104 over (101 lines)"]


def test_no_function_over_the_limit() -> None:
    bad = [line for pkg in PACKAGES for p in sorted((ROOT / pkg).rglob("*.py")) for line in long_functions(p)]
    assert bad == [], f"split these (at most {MAX_FUNCTION_LINES} lines a function): {bad}"
