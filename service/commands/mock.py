"""``oarmreg mock robot``: run a mock Stäubli controller until Ctrl-C.

::

    oarmreg mock robot --link simple-message://127.0.0.1:0 [--script robot.toml]
    oarmreg mock robot --link "modbus://127.0.0.1:5020?address=100&type=float32&units=deg"
    oarmreg mock robot --link serial://pty

The scheme picks the protocol; port 0 binds a free port.  The bound URL (for
serial: the pty's slave path) is printed on the first line of stdout, so a
script can hand it to ``oarmreg robot joints --link``.  Modbus register-map
options in the URL query configure the served map the same way they configure
the client.
"""

from __future__ import annotations

import argparse
import sys
import threading
from pathlib import Path

HELP = "run a mock controller (simple_message / Modbus / serial) until Ctrl-C"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    sub = parser.add_subparsers(dest="mock_command", metavar="{robot}", required=True)
    r = sub.add_parser("robot", help="mock Stäubli controller streaming joints")
    r.add_argument("--link", required=True, help="URL to serve, e.g. simple-message://127.0.0.1:0")
    r.add_argument("--script", type=Path, help="robot motion script (JSON or TOML, see mocks/robot/robot.py)")
    r.add_argument(
        "--start-delay-s", type=float, default=0.0,
        help="simple_message: wait after a client connects before streaming (the VAL3 driver waits 1 s)",
    )  # fmt: skip


def run(args: argparse.Namespace, stop: threading.Event | None = None) -> int:
    from urllib.parse import urlsplit

    from drivers.base import parse_query
    from drivers.errors import LinkConfigError
    from mocks.robot.robot import ScriptedRobot
    from mocks.robot.runner import run_mock_controller

    parts = urlsplit(args.link)
    kind = parts.scheme
    robot = ScriptedRobot()
    if args.script:
        try:
            robot.run_script(args.script)
        except (OSError, ValueError, KeyError) as e:
            raise LinkConfigError(f"cannot use robot script {args.script}: {e}") from None
    options: dict[str, object] = {}
    host, port = parts.hostname or "127.0.0.1", 0
    if kind == "simple-message":
        port = parts.port if parts.port is not None else 11002
        options["start_delay_s"] = args.start_delay_s
    elif kind == "modbus":
        from drivers.modbus import RegisterMap

        port = parts.port if parts.port is not None else 502
        options["register_map"] = RegisterMap.from_options(parse_query(args.link))
    elif kind != "serial":
        raise LinkConfigError(f"unknown mock kind {kind!r}: use simple-message://, modbus:// or serial://")
    stop = stop or threading.Event()
    with run_mock_controller(kind, robot, host=host, port=port, **options) as mock:
        sys.stdout.write(mock.url + "\n")
        sys.stdout.flush()
        try:
            while not stop.wait(0.5):
                pass
        except KeyboardInterrupt:
            pass
    return 0
