"""The ``oarmreg`` command line.

``main(argv=None) -> int`` is callable from tests.  Exit codes: see
:mod:`service.error_map` (0 ok, 2 usage, 3 configuration, 4 input data,
5 robot link, 6 registration refused, 7 accuracy gate, 8 file system) and docs/cli.md.
Every failure is one line on stderr: the project's typed errors by their family; an ``OSError``
(a path that cannot be read or written) exit 8; a ``ValueError`` from parsing a file (JSON and
the like) exit 4.  The traceback of those two is logged at DEBUG (``--log-level DEBUG``).
"""

from __future__ import annotations

import argparse
import importlib
import logging
import os
import re
import sys
from collections.abc import Sequence
from typing import NoReturn

from registration import __version__
from service.error_map import EXIT_FILES, EXIT_INPUT, EXIT_USAGE, FAMILIES, exit_code_of, title_of

log = logging.getLogger(__name__)

COMMANDS: dict[str, str] = {
    "simulate": "service.cli.commands.simulate",
    "detect": "service.cli.commands.detect",
    "register": "service.cli.commands.register",
    "verify": "service.cli.commands.verify",
    "robot": "service.cli.commands.robot",
    "mock": "service.cli.commands.mock",
    "serve": "service.cli.commands.serve",
    "demo": "service.cli.commands.demo",
    "calibrate": "service.cli.commands.calibrate",
    "backup": "service.cli.commands.backup",
    "restore": "service.cli.commands.restore",
    "config": "service.cli.commands.config",
    "qa": "service.cli.commands.qa",  # QA protocols
    "token": "service.cli.commands.token",
    "send": "service.cli.commands.send",
}


class OneLineParser(argparse.ArgumentParser):
    """An argparse parser whose usage error is one line (what was wrong, where the help is), exit 2,
    as every other failure of the CLI; subcommand parsers inherit the class."""

    def error(self, message: str) -> NoReturn:
        self.exit(EXIT_USAGE, f"{self.prog}: error: {message} (see `{self.prog} --help`)\n")


def build_parser(only: str | None = None) -> argparse.ArgumentParser:
    """The full parser, or with ``only`` one subcommand (its module alone is imported: start-up time)."""
    parser = OneLineParser(
        prog="oarmreg",
        description="O-arm ↔ Stäubli spatial registration (Bai et al. 2018, "
        "doi:10.1088/1742-6596/1016/1/012006)",
    )
    parser.add_argument("--version", action="version", version=f"oarmreg {__version__}")
    _add_logging_options(parser, "")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for name, module_name in COMMANDS.items():
        if only is not None and name != only:
            continue
        try:
            module = importlib.import_module(module_name)
        except ModuleNotFoundError as e:
            if e.name == module_name:
                continue  # command not built yet
            raise
        p = sub.add_parser(name, help=module.HELP, description=module.HELP)
        _add_logging_options(p, "_sub")  # `oarmreg serve -v` as well as `oarmreg -v serve`
        module.add_arguments(p)
        p.set_defaults(_run=module.run)
    return parser


def _add_logging_options(parser: argparse.ArgumentParser, suffix: str) -> None:
    """``-v``, ``--log-level``, ``--log-format`` on the top parser and on every subcommand.

    Separate destinations (``verbose`` / ``verbose_sub``…): argparse copies a subparser's defaults
    over the top parser's values, so one shared destination would lose ``oarmreg -v serve``.
    """
    from service.logsetup import LEVELS, LOG_FORMATS

    parser.add_argument("-v", "--verbose", dest="verbose" + suffix, action="count", default=0,
                        help="more logging, one level per -v: warning by default, -v info, -vv debug; "
                        "serve starts at info, so serve -v is debug")  # fmt: skip
    parser.add_argument("--log-level", dest="log_level" + suffix, type=str.upper, choices=LEVELS,
                        default=None, help="log level (overrides -v and serve's [log] level)")  # fmt: skip
    parser.add_argument("--log-format", dest="log_format" + suffix, choices=LOG_FORMATS, default=None,
                        help="text (default) or json: one JSON object per line")  # fmt: skip


def log_level_of(args: argparse.Namespace, default: int) -> tuple[int, bool]:
    """The level the flags ask for (``--log-level``, else ``-v`` counted from ``default``), and whether
    any flag asked (then a command's own level setting must not override it)."""
    named = getattr(args, "log_level_sub", None) or getattr(args, "log_level", None)
    if named:
        return int(getattr(logging, named)), True
    verbose = int(getattr(args, "verbose", 0)) + int(getattr(args, "verbose_sub", 0))
    if verbose:
        return max(logging.DEBUG, min(default, logging.WARNING) - 10 * verbose), True
    return default, False


def _requested_command(argv: Sequence[str]) -> str | None:
    """The subcommand ``argv`` names (its first non-option word), if it is one of :data:`COMMANDS`."""
    word = next((a for a in argv if not a.startswith("-")), None)
    return word if word in COMMANDS else None


_NEGATIVE_LIST_RE = re.compile(r"^-[0-9.][0-9.eE+-]*(,[0-9.eE+-]*)+$")
"""A comma-separated list of numbers starting with a negative one (``-12.3,4,5``)."""


def join_negative_lists(argv: Sequence[str]) -> list[str]:
    """``--pose -12.3,4,...`` → ``--pose=-12.3,4,...``.

    argparse takes a word starting with ``-`` for an option unless it looks like one negative
    number, so a comma-separated list starting with a negative value ("expected one argument")
    needs joining to its long option.  Such a word can never be an option itself.
    """
    out: list[str] = []
    for word in argv:
        prev = out[-1] if out else ""
        if _NEGATIVE_LIST_RE.match(word) and prev.startswith("--") and "=" not in prev and prev != "--":
            out[-1] = f"{prev}={word}"
        else:
            out.append(word)
    return out


def _one_line(command: str, title: str, e: BaseException | str, code: int) -> int:
    print(f"oarmreg {command}: {title}: {e}", file=sys.stderr)  # noqa: T201
    return code


def main(argv: Sequence[str] | None = None) -> int:
    argv = join_negative_lists(sys.argv[1:] if argv is None else argv)
    parser = build_parser(only=_requested_command(argv))
    args = parser.parse_args(argv)
    if not getattr(args, "_run", None):
        parser.print_help(sys.stderr)
        return 2
    from service.logsetup import configure

    module = importlib.import_module(COMMANDS[args.command])
    level, _ = log_level_of(args, getattr(module, "DEFAULT_LOG_LEVEL", logging.WARNING))
    configure(level, getattr(args, "log_format_sub", None) or getattr(args, "log_format", None) or "text")
    try:
        return int(args._run(args))
    except FAMILIES as e:
        return _one_line(args.command, title_of(e), e, exit_code_of(e))
    except KeyboardInterrupt:
        return 130
    except BrokenPipeError:  # output piped into `head` & co.: stop quietly, as Unix tools do
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        return 141
    except OSError as e:  # a path no command checked: one line, not a traceback
        log.debug("file system error", exc_info=True)
        where = f" ({e.filename})" if e.filename and str(e.filename) not in str(e) else ""
        return _one_line(
            args.command,
            "File system error",
            f"{e}{where}; check the path exists, is writable by this user and the disk has room",
            EXIT_FILES,
        )
    except ValueError as e:  # a value in a file the command parsed (JSON, numbers): input data
        log.debug("invalid value", exc_info=True)
        return _one_line(
            args.command, "Invalid input", f"{e}; fix the value in the input and run again", EXIT_INPUT
        )


if __name__ == "__main__":
    raise SystemExit(main())
