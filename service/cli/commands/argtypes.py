"""argparse ``type=`` functions that refuse bad numbers and output paths at parse time (exit 2,
naming the flag).

argparse turns the :class:`argparse.ArgumentTypeError` message into
``oarmreg CMD: error: argument --max-fre-mm: must be > 0, got -1``.
"""

from __future__ import annotations

import argparse
import math
import os
import tempfile
from collections.abc import Callable
from pathlib import Path


def _number(text: str, kind: type[float] | type[int]) -> float:
    try:
        value = kind(text)
    except ValueError:
        what = "an integer" if kind is int else "a number"
        raise argparse.ArgumentTypeError(f"expected {what}, got {text!r}") from None
    if not math.isfinite(value):
        raise argparse.ArgumentTypeError(f"expected a finite number, got {text!r}")
    return value


def positive_float(text: str) -> float:
    """A finite float > 0 (thresholds in mm, durations in s)."""
    value = _number(text, float)
    if value <= 0:
        raise argparse.ArgumentTypeError(f"must be > 0, got {text}")
    return value


def positive_int(text: str) -> int:
    value = int(_number(text, int))
    if value <= 0:
        raise argparse.ArgumentTypeError(f"must be a positive integer, got {text}")
    return value


def float_below(limit: float) -> Callable[[str], float]:
    """A finite float in (0, limit)."""

    def parse(text: str) -> float:
        value = positive_float(text)
        if value >= limit:
            raise argparse.ArgumentTypeError(f"must be < {limit:g}, got {text}")
        return value

    parse.__name__ = f"float_below_{limit:g}"
    return parse


def output_file(text: str) -> Path:
    """A file path to write (JSON, PNG): refused at parse time when something that is not a regular
    file is already there, so a directory given by mistake is named before any work is done,
    instead of a traceback after it."""
    path = Path(text)
    if path.exists() and not path.is_file():
        raise argparse.ArgumentTypeError(
            f"{text} exists and is not a regular file (a folder?): give a file path"
        )
    _check_parent(text, path)
    if path.exists() and not os.access(path, os.W_OK):
        raise argparse.ArgumentTypeError(f"{text} exists and this user cannot overwrite it")
    return path


def renamed(new_flag: str, why: str) -> Callable[[str], str]:
    """``type=`` of a flag that was renamed: always refuses (exit 2), naming the new flag."""

    def parse(text: str) -> str:
        raise argparse.ArgumentTypeError(f"this flag was renamed: use {new_flag} ({why})")

    parse.__name__ = f"renamed_to_{new_flag}"
    return parse


def output_dir(text: str) -> Path:
    """A folder the command creates or fills: refused when a non-folder is there, or when it is
    missing and its parent is missing or not writable (nothing is created but the folder named)."""
    path = Path(text)
    if path.exists():
        if not path.is_dir():
            raise argparse.ArgumentTypeError(f"{text} exists and is not a folder: give a folder path")
        _probe_writable(text, path)
        return path
    _check_parent(text, path)
    return path


def _check_parent(text: str, path: Path) -> None:
    """The folder ``path`` goes into exists and this user may write there (nothing is created)."""
    parent = path.parent
    if not parent.is_dir():
        raise argparse.ArgumentTypeError(
            f"{text}: folder {parent} does not exist; create it first (nothing is created for you)"
        )
    _probe_writable(text, parent)


def _probe_writable(text: str, folder: Path) -> None:
    """Create and at once delete a hidden file in ``folder``: permissions alone do not tell (root
    passes every access check, and /proc or a read-only mount still refuse)."""
    try:
        with tempfile.NamedTemporaryFile(dir=folder, prefix=".oarmreg-write-check-"):
            pass
    except OSError as e:
        raise argparse.ArgumentTypeError(
            f"{text}: cannot write into folder {folder} ({e.strerror or e}); choose a writable folder"
        ) from None


def parse_ae_address(text: str) -> tuple[str, str, int] | None:
    """``AE@HOST:PORT`` (an IPv6 host in brackets) as (AE title, host, port), or None when malformed
    (an AE title of 1–16 characters, a port 1–65535)."""
    import re

    m = re.fullmatch(r"([^@\s]{1,16})@([^:\s]+|\[[0-9A-Fa-f:]+\]):(\d{1,5})", text.strip())
    if m is None or not 0 < int(m[3]) < 65536:
        return None
    return m[1], m[2].strip("[]"), int(m[3])


def ae_address(text: str) -> tuple[str, str, int]:
    """argparse type of ``--to AE@HOST:PORT``."""
    parsed = parse_ae_address(text)
    if parsed is None:
        raise argparse.ArgumentTypeError(
            f"expected AE@HOST:PORT (port 1–65535), e.g. OARMREG@127.0.0.1:11112; got {text!r}"
        )
    return parsed


def add_data_arguments(parser: argparse.ArgumentParser) -> None:
    """``--config`` / ``--data``: the service's data folder, for the commands that read its database."""
    parser.add_argument("--config", type=Path, default=None, help="TOML settings file (for data_dir)")
    parser.add_argument("--data", type=Path, default=None, help="the service's data folder (data_dir)")


def db_path_from_args(args: argparse.Namespace) -> Path:
    """The database path of :func:`add_data_arguments`' folder (data_dir from the settings otherwise)."""
    from service.settings import load_settings

    path: Path = load_settings(args.config, {"data_dir": args.data}).db_path
    return path
