"""argparse ``type=`` functions that refuse bad numbers and output paths at parse time (exit 2,
naming the flag).

argparse turns the :class:`argparse.ArgumentTypeError` message into
``oarmreg CMD: error: argument --max-fre-mm: must be > 0, got -1``.
"""

from __future__ import annotations

import argparse
import math
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


def nonnegative_float(text: str) -> float:
    value = _number(text, float)
    if value < 0:
        raise argparse.ArgumentTypeError(f"must be ≥ 0, got {text}")
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
    return path


def renamed(new_flag: str, why: str) -> Callable[[str], str]:
    """``type=`` of a flag that was renamed: always refuses (exit 2), naming the new flag."""

    def parse(text: str) -> str:
        raise argparse.ArgumentTypeError(f"this flag was renamed: use {new_flag} ({why})")

    parse.__name__ = f"renamed_to_{new_flag}"
    return parse
