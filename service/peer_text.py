"""Strings a network peer chose (DICOM AE titles, a PACS's ErrorComment, OpenIGTLink device names),
made safe for a log line or an API field: a peer must not forge log lines (CR/LF), drive a terminal
(ESC sequences) or flood a record with a long string."""

from __future__ import annotations


def printable(text: str, limit: int = 64) -> str:
    """``text`` from a peer (an AE title, an ErrorComment, a device name) safe for a log line or an API
    field: control and non-ASCII characters as ``\\xNN`` / ``\\uNNNN`` escapes, at most ``limit``
    characters kept."""
    return text[:limit].encode("ascii", "backslashreplace").decode("ascii").translate(_CONTROL_ESCAPES)


_CONTROL_ESCAPES = {c: f"\\x{c:02x}" for c in (*range(0x20), 0x7F)}
