"""``oarmreg mock robot``: run a mock Stäubli controller until Ctrl-C (SIGINT) or SIGTERM.

::

    oarmreg mock robot --link simple-message://127.0.0.1:0 [--script robot.toml]
    oarmreg mock robot --link "modbus://127.0.0.1:5020?address=100&type=float32&units=deg"
    oarmreg mock robot --link serial://pty

The scheme picks the protocol; port 0 binds a free port.  The bound URL (for
serial: the pty's slave path) is printed on the first line of stdout, so a
script can hand it to ``oarmreg robot joints --link``.  Modbus register-map
options in the URL query configure the served map the same way they configure
the client.

SIGINT and SIGTERM only raise a flag that the main loop polls, so the server stops through its
normal path (no KeyboardInterrupt thrown into whatever the main thread was doing, possibly
holding a lock the shutdown needs); SIGUSR1 dumps every thread's stack to stderr (``faulthandler``)
for a controller that does not stop.
"""

from __future__ import annotations

import argparse
import faulthandler
import signal
import sys
import threading
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

HELP = "run a mock controller (simple_message / Modbus / serial) until Ctrl-C"

POLL_S = 0.2
"""How often the main loop looks at the stop flag (s): the latency of a Ctrl-C."""


@contextmanager
def _stop_on_signals(stop: threading.Event) -> Iterator[Callable[[], bool]]:
    """Yields "should stop?": ``stop`` is set, or SIGINT / SIGTERM arrived (main thread only;
    the handlers only set a flag, and the previous ones come back on exit)."""
    flag = [False]
    previous: dict[signal.Signals, Any] = {}
    if threading.current_thread() is threading.main_thread():

        def handler(signum: int, frame: object) -> None:
            flag[0] = True

        for sig in (signal.SIGINT, signal.SIGTERM):
            previous[sig] = signal.signal(sig, handler)
        if hasattr(signal, "SIGUSR1"):
            faulthandler.register(signal.SIGUSR1, all_threads=True)
    try:
        yield lambda: flag[0] or stop.is_set()
    finally:
        for sig, h in previous.items():
            signal.signal(sig, h)
        if previous and hasattr(signal, "SIGUSR1"):
            faulthandler.unregister(signal.SIGUSR1)


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
    with (
        _stop_on_signals(stop) as should_stop,
        run_mock_controller(kind, robot, host=host, port=port, **options) as mock,
    ):
        sys.stdout.write(mock.url + "\n")
        sys.stdout.flush()
        while not should_stop():
            time.sleep(POLL_S)
    return 0
