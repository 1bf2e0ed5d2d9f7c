"""How an error is answered: HTTP status and CLI exit code, read from the nearest class that states them.

A class states them once, in one of two places: a service error in its own body (``http_status``,
``exit_code``: :mod:`service.errors`); a family of ``registration`` or ``drivers``, which know
nothing of HTTP or exit codes, in :data:`ERROR_MAP`.  :func:`classify` walks the class's MRO and
takes the first that states them; a title is the nearest class's ``title`` (an instance may set
its own).  The problem-details handler (:mod:`service.http.api.problems`), the HTTP gate
(:mod:`service.http.security`) and the CLI (:mod:`service.cli.main`) all answer through here.

Exit codes (documented in docs/cli.md, "Exit codes"):

==  ==========================================================
0   success
2   usage error (argparse)
3   configuration error (bad TOML, bad phantom, bad URDF, bad link URL)
4   input data error (DICOM series, points file, detection)
5   robot link error (no link, timeout, protocol)
6   registration refused (ambiguous, mirrored, too few spheres,
    degenerate, robot moved)
7   accuracy gate failed (FRE / verification over threshold)
8   file system (CLI only: a path cannot be read or written --
    missing, no permission, disk full, read-only)
==  ==========================================================
"""

from __future__ import annotations

from dataclasses import dataclass

from drivers.errors import LinkConfigError, RobotLinkError
from registration.errors import (
    AccuracyGateError,
    ConfigError,
    InputFileUnreadableError,
    OarmRegError,
    RegistrationError,
)

EXIT_OK = 0
EXIT_USAGE = 2
EXIT_CONFIG = 3
EXIT_INPUT = 4
EXIT_ROBOT_LINK = 5
EXIT_REFUSED = 6
EXIT_ACCURACY = 7
EXIT_FILES = 8
"""CLI only: an input file that cannot be read (:class:`~registration.errors.InputFileUnreadableError`)
or an ``OSError`` no command turned into a typed error (:func:`service.cli.main.main`)."""


@dataclass(frozen=True)
class ErrorClass:
    """How one error class is answered (its title is the class's own ``title``)."""

    http_status: int
    exit_code: int


ERROR_MAP: dict[type[Exception], ErrorClass] = {
    OarmRegError: ErrorClass(422, EXIT_INPUT),
    ConfigError: ErrorClass(422, EXIT_CONFIG),
    RegistrationError: ErrorClass(409, EXIT_REFUSED),
    AccuracyGateError: ErrorClass(409, EXIT_ACCURACY),
    RobotLinkError: ErrorClass(409, EXIT_ROBOT_LINK),
    LinkConfigError: ErrorClass(422, EXIT_CONFIG),
    InputFileUnreadableError: ErrorClass(422, EXIT_FILES),
}
"""The families of ``registration`` and ``drivers``; a service error states its own
(:mod:`service.errors`)."""

FAMILIES: tuple[type[Exception], ...] = (OarmRegError, RobotLinkError)
"""The roots: every error a user can cause derives from one of these."""


def stated_by(cls: type) -> ErrorClass | None:
    """What ``cls`` itself states: its own ``http_status`` and ``exit_code``, or its row, or None."""
    own = vars(cls)
    if "http_status" in own:
        return ErrorClass(own["http_status"], own["exit_code"])
    return ERROR_MAP.get(cls)


def classify(exc: BaseException) -> ErrorClass | None:
    """What the nearest class of ``type(exc)``'s MRO states (:func:`stated_by`), or None (not ours)."""
    for cls in type(exc).__mro__:
        entry = stated_by(cls)
        if entry is not None:
            return entry
    return None


def title_of(exc: BaseException) -> str:
    """The exception's own ``title`` if it or its class sets one, else the nearest ancestor's."""
    own = getattr(exc, "title", None)
    if isinstance(own, str) and own:
        return own
    for cls in type(exc).__mro__:
        title = vars(cls).get("title")
        if isinstance(title, str) and title:
            return title
    return "Error"


def http_status_of(exc: BaseException) -> int:
    """The HTTP status of a user-caused error (422 for an error that is not ours)."""
    entry = classify(exc)
    return entry.http_status if entry is not None else 422


def exit_code_of(exc: BaseException) -> int:
    """The CLI exit code of a user-caused error (:data:`EXIT_INPUT` for an error that is not ours)."""
    entry = classify(exc)
    return entry.exit_code if entry is not None else EXIT_INPUT
