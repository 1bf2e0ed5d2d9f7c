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
