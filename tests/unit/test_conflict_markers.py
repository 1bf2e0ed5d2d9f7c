"""No tracked file holds an unresolved merge conflict (issue 42, item 1).

A conflict has the shape ``<<<<<<< ours`` … ``=======`` … ``>>>>>>> theirs``, each marker at the
start of a line. A lone ``=======`` is a Markdown setext underline, so it counts only between an
opening and a closing marker; a lone opening or closing marker (with its space and label, as git
writes it) is flagged on its own, because half a conflict is still one.
"""

from __future__ import annotations

import re
import subprocess

from tests.helpers.paths import REPO

_OPEN = re.compile(r"^<{7}(?: |$)")
_MIDDLE = re.compile(r"^={7}$")
_CLOSE = re.compile(r"^>{7}(?: |$)")
_BASE = re.compile(r"^\|{7}(?: |$)")  # diff3 style: ||||||| base


def conflict_lines(text: str) -> list[int]:
    """Return the 1-based numbers of the lines that are conflict markers."""
    found: list[int] = []
    inside = False
    for number, line in enumerate(text.splitlines(), start=1):
        if _OPEN.match(line):
            inside = True
            found.append(number)
        elif _CLOSE.match(line):
            inside = False
            found.append(number)
        elif inside and (_MIDDLE.match(line) or _BASE.match(line)):
            found.append(number)
    return found


def test_the_detector_knows_a_conflict_from_a_setext_underline() -> None:
    opening, middle, closing = "<" * 7 + " HEAD", "=" * 7, ">" * 7 + " i34"
    assert conflict_lines(f"Title\n{middle}\n\ntext\n") == []
    assert conflict_lines(f"a\n{opening}\nx\n{middle}\ny\n{closing}\nb\n") == [2, 4, 6]
    assert conflict_lines(f"{closing}\n") == [1]
    assert conflict_lines("<<<<<<<<< not a marker\n") == []


def test_no_tracked_file_holds_conflict_markers() -> None:
    listing = subprocess.run(
        ["git", "ls-files", "-z"], cwd=REPO, capture_output=True, check=True
    ).stdout.decode()
    offenders = []
    for name in filter(None, listing.split("\0")):
        path = REPO / name
        if not path.is_file() or path.is_symlink():
            continue
        data = path.read_bytes()
        if b"\0" in data[:8192]:
            continue  # binary (DICOM, PNG)
        lines = conflict_lines(data.decode("utf-8", errors="replace"))
        if lines:
            offenders.append(f"{name}: lines {lines}")
    assert not offenders, "unresolved merge conflicts:\n" + "\n".join(offenders)
