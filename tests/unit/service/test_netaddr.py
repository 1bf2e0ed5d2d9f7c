"""Peer allow-lists shared by the DICOM SCP and the OpenIGTLink server (service/netaddr.py)."""

from __future__ import annotations

import pytest

from service.netaddr import in_networks, parse_networks


def test_parse_networks_names_the_setting_and_the_bad_entry() -> None:
    with pytest.raises(ValueError, match=r"igtl\.allowed_peer_addresses: .*10\.0\.0\.300"):
        parse_networks(("10.0.0.1", "10.0.0.300"), "igtl.allowed_peer_addresses")


@pytest.mark.parametrize(
    ("host", "inside"),
    [
        ("10.0.0.12", True),  # the listed address
        ("10.1.2.3", True),  # inside the listed network
        ("10.0.0.13", False),
        ("192.168.1.7", False),
        ("fe80::1%eth0", True),  # zone id ignored
        ("fe80::2", False),
        ("not-an-address", False),
        ("", False),
    ],
)
def test_in_networks(host: str, inside: bool) -> None:
    nets = parse_networks(("10.0.0.12", "10.1.0.0/16", "fe80::1"), "dicom.allowed_peer_addresses")
    assert in_networks(host, nets) is inside
