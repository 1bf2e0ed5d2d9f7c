"""Every error the service defines, each stating once how it is answered.

A class here derives from the family its *meaning* belongs to (:mod:`registration.errors`: a
refusal, a configuration problem, an accuracy gate, or just :class:`OarmRegError`) and states in
its own body its ``title``, its ``http_status`` and its CLI ``exit_code``, as Starlette's
``HTTPException`` carries its ``status_code``: nothing arrives from a parent chosen for another
reason.  The families of ``registration`` and ``drivers`` know nothing of HTTP: their status and
exit code are the table :data:`service.error_map.ERROR_MAP`, their title their class's.
:func:`service.error_map.classify` reads whichever of the two the nearest class states.

Errors that never reach a client (an OpenIGTLink peer breaking the framing, an instance the DICOM
SCP must not store) derive from :class:`ListenerError`: the listener that raised them handles them.

No class under ``service/`` outside this module derives from an exception
(tests/unit/service/test_error_map.py).
"""

from __future__ import annotations

from typing import ClassVar

from registration.errors import AccuracyGateError, ConfigError, OarmRegError, RegistrationError
from service.error_map import (
    EXIT_ACCURACY,
    EXIT_CONFIG,
    EXIT_INPUT,
    EXIT_REFUSED,
    EXIT_USAGE,
)

# --------------------------------------------------------------------------- records and requests


class NotFoundError(OarmRegError):
    """No scan, registration or verification with that id."""

    title = "Not found"
    http_status = 404
    exit_code = EXIT_INPUT


class NoScanError(OarmRegError):
    """Nothing to register: no complete scan has arrived."""

    title = "No complete scan"
    http_status = 409
    exit_code = EXIT_INPUT


class InternalError(OarmRegError):
    """A bug: the pipeline failed in a way no refusal describes."""

    title = "Internal error"
    http_status = 500
    exit_code = EXIT_INPUT


class QaProtocolError(OarmRegError):
    """A QA protocol request names no such protocol or pose."""

    title = "QA protocol problem"
    http_status = 422
    exit_code = EXIT_INPUT


class QaProtocolNameTakenError(QaProtocolError):
    """A QA protocol request names a protocol that already exists."""

    title = "QA protocol name taken"
    http_status = 409
    exit_code = EXIT_INPUT


# --------------------------------------------------------------------------- registrations


class NoCurrentRegistrationError(RegistrationError):
    """A request that needs the current registration while none is current."""

    title = "No current registration"
    http_status = 409
    exit_code = EXIT_REFUSED


class VerificationRefusedError(RegistrationError):
    """``POST /verify`` of a scan not newer than the current registration's own."""

    title = "Verification refused"
    http_status = 409
    exit_code = EXIT_REFUSED


class SupersededScanError(RegistrationError):
    """``POST /register`` of a scan the service already has newer evidence against: a newer scan at the
    same placement has an accepted registration or a failed verification, or a verification withdrew
    this scan's own registration (docs/safety.md, "Which registration may be current")."""

    title = "Superseded by a newer scan"
    http_status = 409
    exit_code = EXIT_REFUSED

    def __init__(self, message: str, *, newer_scan_id: int, rule: str) -> None:
        super().__init__(message)
        self.newer_scan_id = newer_scan_id
        self.rule = rule


class VerificationUncomputableError(AccuracyGateError):
    """The verification scan's spheres lie further from the registration's predictions than matching
    can bridge: the error is beyond the gate by more than can be measured; the registration is
    withdrawn (docs/safety.md)."""

    title = "Verification failed: error beyond matching"
    http_status = 409
    exit_code = EXIT_ACCURACY


class VerificationFailedError(AccuracyGateError):
    """``oarmreg verify``: the verification's largest error is over the pass/fail limit."""

    title = "Verification failed"
    http_status = 409
    exit_code = EXIT_ACCURACY


# --------------------------------------------------------------------------- calibrations


class CalibrationBusyError(OarmRegError):
    """``POST /calibrations`` while another calibration runs (nothing stored)."""

    title = "A calibration is already running"
    http_status = 409
    exit_code = EXIT_REFUSED


class CalibrationRefusedError(OarmRegError):
    """A calibration request refused at once (duplicate or incomplete scans); stored as ``refused``."""

    title = "Calibration refused"
    http_status = 409
    exit_code = EXIT_REFUSED


class CalibrationStoppedError(OarmRegError):
    """The service stopped while a calibration ran; the calibration is abandoned."""

    title = "Calibration interrupted"
    http_status = 409
    exit_code = EXIT_REFUSED


class CalibrationNotUsableError(OarmRegError):
    """Activation of a calibration that did not succeed or whose model cannot be loaded."""

    title = "Calibration cannot be activated"
    http_status = 409
    exit_code = EXIT_REFUSED


class ActivationRetiresCurrentError(OarmRegError):
    """Activation of a calibration while a registration is current, without ``force``."""

    title = "Activation would retire the current registration"
    http_status = 409
    exit_code = EXIT_REFUSED


# --------------------------------------------------------------------------- navigation output


class SroUnavailableError(OarmRegError):
    """No Spatial Registration object: the registration was refused, or its scan's headers were not
    stored."""

    title = "Spatial Registration object unavailable"
    http_status = 409
    exit_code = EXIT_REFUSED


class PacsExportError(OarmRegError):
    """The PACS archive of a registration cannot be (re)queued: no PACS configured, a refused
    registration, or already archived."""

    title = "PACS export not possible"
    http_status = 409
    exit_code = EXIT_CONFIG


# --------------------------------------------------------------------------- configuration and storage


class ServeLockError(ConfigError):
    """Another ``serve`` holds the data folder."""

    title = "Data folder in use"
    http_status = 422
    exit_code = EXIT_CONFIG


class TlsConfigError(ConfigError):
    """The TLS certificate / key cannot be used."""

    title = "Invalid TLS configuration"
    http_status = 422
    exit_code = EXIT_CONFIG


class DicomScpConfigError(ConfigError):
    """The DICOM Storage SCP configuration is unsafe or invalid."""

    title = "Invalid DICOM SCP configuration"
    http_status = 422
    exit_code = EXIT_CONFIG


class IgtlConfigError(ConfigError):
    """The OpenIGTLink server configuration is unsafe or invalid."""

    title = "Invalid OpenIGTLink server configuration"
    http_status = 422
    exit_code = EXIT_CONFIG


class RobotFrameUidError(ConfigError):
    """The stored robot Frame of Reference UID is unreadable or malformed."""

    title = "Invalid robot frame of reference UID file"
    http_status = 422
    exit_code = EXIT_CONFIG


class DatabaseUnavailableError(OarmRegError):
    """The database file was deleted or replaced while the service ran."""

    title = "Database unavailable"
    http_status = 503
    exit_code = EXIT_CONFIG


class DatabaseBusyError(OarmRegError):
    """The database could not be written: locked by another process past ``database.busy_timeout_s``
    (``SQLITE_BUSY``) or read-only (``SQLITE_READONLY``: the file, its WAL or its folder not writable).
    Nothing was written; the request may be retried after ``Retry-After``."""

    title = "Database busy"
    http_status = 503
    exit_code = EXIT_CONFIG
    RETRY_AFTER_S = 5

    def __init__(self, message: str) -> None:
        super().__init__(message)
        self.headers = {"Retry-After": str(self.RETRY_AFTER_S)}


class StorageFullError(OarmRegError):
    """The data folder is full (SQLite ``SQLITE_FULL`` / ``ENOSPC``): the write was rolled back, nothing
    stored before it is lost."""

    title = "Data folder full"
    http_status = 507
    exit_code = EXIT_CONFIG


# --------------------------------------------------------------------------- the HTTP gate
# (service.http.security.SecurityGate: refused from the request line and headers, before the body)


class HostNotAllowedError(OarmRegError):
    """The ``Host`` header is not one the service answers to (DNS rebinding)."""

    title = "Host not allowed"
    http_status = 400
    exit_code = EXIT_CONFIG


class OriginNotAllowedError(OarmRegError):
    """A browser request from an origin neither the service's own nor in ``api.allowed_origins``."""

    title = "Origin not allowed"
    http_status = 403
    exit_code = EXIT_CONFIG


class UnauthorizedError(OarmRegError):
    """Missing or wrong Bearer token, or an unknown event ticket."""

    title = "Unauthorized"
    http_status = 401
    exit_code = EXIT_USAGE
    headers: ClassVar[dict[str, str]] = {"WWW-Authenticate": 'Bearer realm="oarmreg"'}


class AuthThrottledError(OarmRegError):
    """Too many wrong tokens from one address: locked out for ``retry_after_s``."""

    title = "Too many failed authentications"
    http_status = 429
    exit_code = EXIT_USAGE

    def __init__(self, message: str, *, retry_after_s: int) -> None:
        super().__init__(message)
        self.headers = {"Retry-After": str(retry_after_s)}


class ReadOnlyTokenError(OarmRegError):
    """A mutating request made with the read-only token."""

    title = "Read-only token"
    http_status = 403
    exit_code = EXIT_USAGE


class UnsupportedMediaTypeError(OarmRegError):
    """A mutating request without ``Content-Type: application/json`` (closes CSRF)."""

    title = "Unsupported media type"
    http_status = 415
    exit_code = EXIT_USAGE


class BadRequestError(OarmRegError):
    """A header the gate cannot read (a ``Content-Length`` that is no byte count)."""

    title = "Bad request"
    http_status = 400
    exit_code = EXIT_USAGE


class BodyTooLargeError(OarmRegError):
    """A request body over ``api.max_body_bytes``."""

    title = "Request body too large"
    http_status = 413
    exit_code = EXIT_INPUT


# --------------------------------------------------------------------------- the command line


class UsageError(OarmRegError):
    """A combination of flags the command cannot run with, found in ``run`` (one line)."""

    title = "Usage error"
    http_status = 422
    exit_code = EXIT_USAGE


# --------------------------------------------------------------------------- inside a listener


class ListenerError(OarmRegError):
    """Raised and handled inside a listener or its probe (the OpenIGTLink server, the DICOM SCP),
    which logs it, counts it and ends that peer's connection or refuses that instance.  Never
    answered over HTTP: one that escaped would be a bug (500); the ``demo`` command reports it as
    input it could not use."""

    title = "Listener error"
    http_status = 500
    exit_code = EXIT_INPUT


class IgtlWireError(ListenerError):
    """An OpenIGTLink message could not be encoded or decoded (bad size, CRC, name too long...)."""

    title = "Malformed OpenIGTLink message"


class IgtlCrcError(IgtlWireError):
    """The body's CRC64 differs from the header's (the framing itself is intact)."""

    title = "OpenIGTLink CRC mismatch"


class IgtlProbeError(IgtlWireError):
    """The probe received no matching TRANSFORM in time."""

    title = "No OpenIGTLink TRANSFORM received"


class IgtlPeerError(ListenerError):
    """An OpenIGTLink peer broke a listener limit or the framing: its connection is closed (message =
    why; ``counter`` = the server counter it increments)."""

    title = "OpenIGTLink peer broke a limit"

    def __init__(self, counter: str, why: str) -> None:
        super().__init__(why)
        self.counter = counter


class InstanceNotStoredError(ListenerError):
    """A DICOM instance was received but must not be stored: the service could not record the
    change of its series."""

    title = "DICOM instance not stored"
