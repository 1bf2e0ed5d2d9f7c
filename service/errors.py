"""The service's own errors (their HTTP status and exit code: :mod:`service.error_map`)."""

from __future__ import annotations

from typing import ClassVar

from registration.errors import AccuracyGateError, OarmRegError, RegistrationError


class NotFoundError(OarmRegError):
    """No scan, registration or verification with that id."""

    title = "Not found"


class NoScanError(OarmRegError):
    """Nothing to register: no complete scan has arrived."""

    title = "No complete scan"


class NoCurrentRegistrationError(RegistrationError):
    title = "No current registration"


class VerificationRefusedError(RegistrationError):
    title = "Verification refused"


class SupersededScanError(RegistrationError):
    """``POST /register`` of a scan the service already has newer evidence against: a newer scan at the
    same placement has an accepted registration or a failed verification, or a verification withdrew
    this scan's own registration (docs/safety.md, "Which registration may be current")."""

    title = "Superseded by a newer scan"

    def __init__(self, message: str, *, newer_scan_id: int, rule: str) -> None:
        super().__init__(message)
        self.newer_scan_id = newer_scan_id
        self.rule = rule


class VerificationUncomputableError(AccuracyGateError):
    """The verification scan's spheres lie further from the registration's predictions than matching
    can bridge: the error is beyond the gate by more than can be measured; the registration is
    withdrawn (docs/safety.md)."""

    title = "Verification failed: error beyond matching"


class InternalError(OarmRegError):
    """A bug: the pipeline failed in a way no refusal describes."""

    title = "Internal error"


class AuthError(OarmRegError):
    """Missing or wrong Bearer token (answered 401 with ``WWW-Authenticate: Bearer``)."""

    title = "Unauthorized"
    headers: ClassVar[dict[str, str]] = {"WWW-Authenticate": 'Bearer realm="oarmreg"'}


class DatabaseGoneError(OarmRegError):
    """The database file was deleted or replaced while the service ran (answered 503)."""

    title = "Database unavailable"


class StorageFullError(OarmRegError):
    """The data folder is full (SQLite ``SQLITE_FULL`` / ``ENOSPC``): the write was rolled back, nothing
    stored before it is lost.  Answered 507 Insufficient Storage."""

    title = "Data folder full"


class PacsExportError(OarmRegError):
    """The PACS archive of a registration cannot be (re)queued: no PACS configured, a refused
    registration, or already archived."""

    title = "PACS export not possible"


class QaProtocolError(OarmRegError):
    """A QA protocol request names no such protocol or pose, or a name already taken."""

    title = "QA protocol problem"


class QaProtocolNameTakenError(QaProtocolError):
    title = "QA protocol name taken"
