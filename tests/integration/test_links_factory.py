"""The URL factory (issue #9): a static scheme table, no registration by import, no import cycle."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

from drivers.errors import LinkConfigError
from drivers.factory import SCHEMES, open_link
from drivers.modbus import ModbusLink
from drivers.serial_link import SerialLink
from drivers.simple_message import SimpleMessageLink


@pytest.mark.parametrize(
    ("url", "cls"),
    [
        ("simple-message://10.0.0.1:11002", SimpleMessageLink),
        ("modbus://10.0.0.1:502?fc=4", ModbusLink),
        ("serial:///dev/ttyS0?baudrate=115200", SerialLink),
    ],
)
def test_each_scheme_builds_its_class_without_connecting(url: str, cls: type) -> None:
    link = open_link(url)
    assert type(link) is cls and link.url == url
    assert not link.running and link.health().state == "down"


def test_the_table_is_static_and_complete() -> None:
    assert dict(SCHEMES) == {
        "simple-message": SimpleMessageLink,
        "modbus": ModbusLink,
        "serial": SerialLink,
    }
    with pytest.raises(LinkConfigError, match=r"unknown robot link scheme 'ftp'.*modbus"):
        open_link("ftp://10.0.0.1")


MODULES = [
    "drivers.base",
    "drivers.simple_message",
    "drivers.modbus",
    "drivers.serial_link",
    "drivers.factory",
]


@pytest.mark.parametrize("first", MODULES)
def test_any_module_imports_first_and_base_imports_no_link_module(first: str) -> None:
    code = (
        f"import sys, {first}\n"
        "links = {'drivers.simple_message', 'drivers.modbus', 'drivers.serial_link'}\n"
        f"if {first!r} == 'drivers.base':\n"
        "    assert not links & set(sys.modules), sorted(links & set(sys.modules))\n"
        "import drivers.factory\n"
        "assert drivers.factory.open_link('serial:///dev/ttyS0').scheme == 'serial'\n"
    )
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60,
                       cwd=Path(__file__).resolve().parents[2])  # fmt: skip
    assert r.returncode == 0, r.stderr
