"""DICOM UIDs: the one check of PS3.5 §9.1 the service applies to every UID a peer or a file gives it."""

from __future__ import annotations

import re
from typing import Final

MAX_UID_CHARS: Final = 64
"""PS3.5 §9.1: a UID is at most 64 characters."""
_UID: Final = re.compile(r"(0|[1-9][0-9]*)(\.(0|[1-9][0-9]*))*")


def is_dicom_uid(text: str) -> bool:
    """True when ``text`` is a DICOM UID (PS3.5 §9.1): components of digits without leading zeros,
    joined by dots, at most 64 characters.  The whole string must match: a trailing newline, which a
    ``$``-anchored pattern (and ``pydicom.uid.UID.is_valid``) lets through, does not; so a UID that
    passes is also safe as a path component."""
    return len(text) <= MAX_UID_CHARS and _UID.fullmatch(text) is not None
