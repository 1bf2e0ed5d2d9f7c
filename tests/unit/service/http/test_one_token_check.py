"""Issue #35, "one token check": the API token is compared in one function,
:func:`service.http.security.token_matches`, called only by the gate; the routes' dependencies and
the ``GET /registration/current`` fast path read the principal the gate recorded (the old
``api/deps.py`` ``token_ok`` compared it a second time for the fast path)."""

from __future__ import annotations

import ast
from pathlib import Path

ROOT = Path(__file__).resolve().parents[4]
SECURITY = Path("service/http/security.py")


def calls_to(names: set[str]) -> list[str]:
    """``path:line name`` of every call under ``service/`` of a function whose last name is in ``names``."""
    out = []
    for path in sorted((ROOT / "service").rglob("*.py")):
        for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
            if isinstance(node, ast.Call):
                name = ast.unparse(node.func).rsplit(".", 1)[-1]
                if name in names:
                    out.append(f"{path.relative_to(ROOT)}:{node.lineno} {name}")
    return out


def test_the_token_is_compared_only_by_the_gate() -> None:
    calls = calls_to({"compare_digest", "token_matches", "token_ok"})
    assert calls, "the gate's comparison was not found: the scan is vacuous"
    assert [c for c in calls if not c.startswith(str(SECURITY) + ":")] == []
