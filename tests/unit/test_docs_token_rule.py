"""Every doc that states the API token's minimum length states the code's (issue 42, item 4)."""

from __future__ import annotations

import re

from service.token_strength import MIN_TOKEN_CHARS
from tests.helpers.paths import REPO

_CLAIM = re.compile(r"(?:≥|at least)\s*\**\s*(\d+)\s*characters", re.IGNORECASE)


def test_every_stated_token_length_is_the_codes() -> None:
    files = [REPO / "README.md", REPO / "configs" / "oarmreg.toml", *sorted((REPO / "docs").glob("*.md"))]
    claims = []
    for path in files:
        text = re.sub(r"\s+", " ", path.read_text(encoding="utf-8").replace("#", " "))
        for m in _CLAIM.finditer(text):
            if "token" in text[max(0, m.start() - 200) : m.end() + 40].lower():
                claims.append((path.name, int(m.group(1))))
    assert claims, "no doc states the token's minimum length"
    wrong = [c for c in claims if c[1] != MIN_TOKEN_CHARS]
    assert not wrong, f"docs state a token length other than MIN_TOKEN_CHARS={MIN_TOKEN_CHARS}: {wrong}"
