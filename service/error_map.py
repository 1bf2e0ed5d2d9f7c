"""The one table from error families to HTTP status, CLI exit code and default title.

``registration`` and ``drivers`` raise errors that know nothing of HTTP or exit codes; the
service's problem-details handler (:mod:`service.http.api.problems`) and the CLI
(:mod:`service.cli.main`) both look them up here.  A class is matched by its nearest ancestor in
:data:`ERROR_MAP`; an exception's own ``title`` attribute, where its class sets one, wins over
the family's.

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
    JointHistoryIncompleteError,
    OarmRegError,
    RegistrationError,
    RobotMovedError,
)
from service.errors import (
    AuthError,
    DatabaseGoneError,
    InternalError,
    NoScanError,
    NotFoundError,
    PacsExportError,
    QaProtocolError,
    QaProtocolNameTakenError,
    StorageFullError,
)

EXIT_OK = 0
EXIT_USAGE = 2
EXIT_CONFIG = 3
EXIT_INPUT = 4
EXIT_ROBOT_LINK = 5
EXIT_REFUSED = 6
EXIT_ACCURACY = 7
EXIT_FILES = 8
"""CLI only (:func:`service.cli.main.main`): an ``OSError`` no command turned into a typed error."""


@dataclass(frozen=True)
class ErrorClass:
    """How one error family is answered."""

    http_status: int
    exit_code: int
    title: str


ERROR_MAP: dict[type, ErrorClass] = {
    OarmRegError: ErrorClass(422, EXIT_INPUT, "Invalid input"),
    ConfigError: ErrorClass(422, EXIT_CONFIG, "Configuration error"),
    RegistrationError: ErrorClass(409, EXIT_REFUSED, "Registration refused"),
    AccuracyGateError: ErrorClass(409, EXIT_ACCURACY, "Accuracy gate failed"),
    NotFoundError: ErrorClass(404, EXIT_INPUT, "Not found"),
    NoScanError: ErrorClass(409, EXIT_INPUT, "No complete scan"),
    InternalError: ErrorClass(500, EXIT_INPUT, "Internal error"),
    AuthError: ErrorClass(401, EXIT_USAGE, "Unauthorized"),
    DatabaseGoneError: ErrorClass(503, EXIT_CONFIG, "Database unavailable"),
    RobotLinkError: ErrorClass(409, EXIT_ROBOT_LINK, "Robot link error"),
    LinkConfigError: ErrorClass(422, EXIT_CONFIG, "Invalid robot link configuration"),
    StorageFullError: ErrorClass(507, EXIT_CONFIG, "Data folder full"),
    # stillness (docs/safety.md, "Stillness and health"): two refusals, never one for the other
    RobotMovedError: ErrorClass(409, EXIT_REFUSED, "Robot moved during the scan"),
    JointHistoryIncompleteError: ErrorClass(409, EXIT_REFUSED, "Joint history incomplete"),
    PacsExportError: ErrorClass(409, EXIT_CONFIG, "PACS export not possible"),
    QaProtocolError: ErrorClass(422, EXIT_INPUT, "QA protocol problem"),
    QaProtocolNameTakenError: ErrorClass(409, EXIT_INPUT, "QA protocol name taken"),
}

FAMILIES: tuple[type[Exception], ...] = (OarmRegError, RobotLinkError)
"""The roots: every error a user can cause derives from one of these."""


def classify(exc: BaseException) -> ErrorClass | None:
    """The entry of the nearest ancestor of ``type(exc)`` in :data:`ERROR_MAP`, or None (not ours)."""
    for cls in type(exc).__mro__:
        entry = ERROR_MAP.get(cls)
        if entry is not None:
            return entry
    return None


def title_of(exc: BaseException) -> str:
    """The exception's own ``title`` if its class sets one, else its family's."""
    own = getattr(exc, "title", None)
    if isinstance(own, str) and own:
        return own
    entry = classify(exc)
    return entry.title if entry is not None else "Error"


def http_status_of(exc: BaseException) -> int:
    """The HTTP status of a user-caused error (422 for one not in the table)."""
    entry = classify(exc)
    return entry.http_status if entry is not None else 422


def exit_code_of(exc: BaseException) -> int:
    """The CLI exit code of a user-caused error (:data:`EXIT_INPUT` for one not in the table)."""
    entry = classify(exc)
    return entry.exit_code if entry is not None else EXIT_INPUT
