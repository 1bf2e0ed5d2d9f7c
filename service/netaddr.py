"""Address rules shared by every listener (REST, DICOM SCP, OpenIGTLink): one loopback test."""

from __future__ import annotations

import ipaddress


def is_loopback(host: str) -> bool:
    """True for 127.0.0.0/8, ::1 (bracketed or not) and ``localhost``."""
    if host.lower() == "localhost":
        return True
    try:
        return ipaddress.ip_address(host.strip("[]")).is_loopback
    except ValueError:
        return False


Network = ipaddress.IPv4Network | ipaddress.IPv6Network


def parse_networks(addresses: tuple[str, ...], setting: str) -> tuple[Network, ...]:
    """``allowed_peer_addresses`` entries (addresses or CIDR networks) as networks; ValueError
    naming ``setting`` and the bad entry otherwise."""
    try:
        return tuple(ipaddress.ip_network(a, strict=False) for a in addresses)
    except ValueError as e:
        raise ValueError(f"{setting}: {e}") from None


def in_networks(host: str, networks: tuple[Network, ...]) -> bool:
    """True when the peer address ``host`` (an IPv6 zone id ignored) lies in one of ``networks``;
    False for anything that is not an IP address."""
    try:
        ip = ipaddress.ip_address(host.split("%")[0])
    except ValueError:
        return False
    return any(ip in n for n in networks)


# Strings a network peer chose (DICOM AE titles, a PACS's ErrorComment, OpenIGTLink device names) are
# made safe for a log line or an API field: a peer must not forge log lines (CR/LF), drive a terminal
# (ESC sequences) or flood a record with a long string.


def printable(text: str, limit: int = 64) -> str:
    """``text`` from a peer (an AE title, an ErrorComment, a device name) safe for a log line or an API
    field: control and non-ASCII characters as ``\\xNN`` / ``\\uNNNN`` escapes, at most ``limit``
    characters kept."""
    return text[:limit].encode("ascii", "backslashreplace").decode("ascii").translate(_CONTROL_ESCAPES)


_CONTROL_ESCAPES = {c: f"\\x{c:02x}" for c in (*range(0x20), 0x7F)}
