"""The service's events: one frozen dataclass per event, each knowing its wire name.

The shape follows pynetdicom's ``events.py``: one definition per event with its name and what it
means, and handlers bound to the event's type (:meth:`service.event_bus.EventBus.listen`), not to a
string.  A producer builds the event it means (``bus.publish(RegistrationDone(...))``); a listener
receives that typed object.  Payload fields are typed (record ids, states, reasons); none is a
free-form ``dict``.

Wire format (``GET /events``, :mod:`service.http.api.events`): ``event: <name>`` and, as ``data``, the
JSON object of :meth:`Event.payload`: the fields in declaration order, tuples as lists; a field
named in ``omitted_when_none`` is left out while it is None; a :class:`Reopening` is written as its
three fields in place.  Navigation clients parse these bytes, so a field's name, order and presence
are part of the API (``tests/integration/test_sse_wire_format.py`` pins the bytes,
``tests/unit/service/test_events.py`` every event's keys).  A new event is a new class here, defined
after the others of its group.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, fields
from typing import ClassVar, Literal

_BY_NAME: dict[str, type[Event]] = {}


@dataclass(frozen=True, kw_only=True)
class Event:
    """Base of every service event; a concrete event sets ``name`` (its SSE ``event:`` line)."""

    name: ClassVar[str]
    omitted_when_none: ClassVar[frozenset[str]] = frozenset()
    """Fields left out of the payload while None (they were only sent when known)."""

    def __init_subclass__(cls, **kwargs: object) -> None:
        super().__init_subclass__(**kwargs)
        name = cls.__dict__.get("name")
        if name is None:  # an abstract group (fields shared by several events)
            return
        if name in _BY_NAME:
            raise TypeError(f"event name {name!r} is taken by {_BY_NAME[name].__name__}")
        _BY_NAME[name] = cls

    def payload(self) -> dict[str, object]:
        """The JSON object sent as the event's ``data`` (see the module docstring)."""
        out: dict[str, object] = {}
        for f in fields(self):
            value = getattr(self, f.name)
            if value is None and f.name in self.omitted_when_none:
                continue
            if isinstance(value, Reopening):
                out.update(value.payload())
            elif isinstance(value, tuple):
                out[f.name] = list(value)
            else:
                out[f.name] = value
        return out


Publish = Callable[[Event], None]
"""``publish(event)``, thread-safe: :meth:`service.event_bus.EventBus.publish`."""


# ---- scans (service.intake.recording, service.intake.scan_lifecycle, service.intake.retention) ---


@dataclass(frozen=True)
class Reopening:
    """A series recorded before came again (late slices, or content replaced): what it was."""

    previous_status: str
    previous_slices: int

    def payload(self) -> dict[str, object]:
        return {
            "reopened": True,
            "previous_status": self.previous_status,
            "previous_slices": self.previous_slices,
        }


@dataclass(frozen=True, kw_only=True)
class _ScanRecorded(Event):
    """A series was recorded (:class:`service.intake.recording.Intake`): its scan and the joints' verdict."""

    scan_id: int
    series_uid: str
    folder: str
    still: bool
    link_state: str
    source: str
    """``folder`` (the watcher) or ``dicom`` (C-STORE)."""
    reopening: Reopening | None = None
    omitted_when_none: ClassVar[frozenset[str]] = frozenset({"reopening"})


@dataclass(frozen=True, kw_only=True)
class ScanArrived(_ScanRecorded):
    """A series was recorded ``complete``; auto-register starts from this event."""

    name: ClassVar[str] = "scan_arrived"
    n_slices: int


@dataclass(frozen=True, kw_only=True)
class ScanInvalid(_ScanRecorded):
    """A series was recorded ``invalid``: ``reason`` says which rule it failed."""

    name: ClassVar[str] = "scan_invalid"
    reason: str


@dataclass(frozen=True, kw_only=True)
class _ScanContentChanged(Event):
    """A judged series' content changed (:meth:`service.intake.scan_lifecycle.ScanLifecycle.changing`)."""

    scan_id: int
    series_uid: str
    folder: str
    source: str
    previous_status: str
    previous_slices: int
    added: tuple[str, ...]
    replaced: tuple[str, ...]
    removed: tuple[str, ...]
    reason: str
    n_slices: int | None = None
    """The new slice count, when the deliverer knows it."""
    omitted_when_none: ClassVar[frozenset[str]] = frozenset({"n_slices"})


@dataclass(frozen=True, kw_only=True)
class ScanReopened(_ScanContentChanged):
    """Late slices of a recorded series: it was incomplete when recorded."""

    name: ClassVar[str] = "scan_reopened"


@dataclass(frozen=True, kw_only=True)
class ScanReplaced(_ScanContentChanged):
    """An instance of a judged series was replaced with different bytes, or removed."""

    name: ClassVar[str] = "scan_replaced"


@dataclass(frozen=True, kw_only=True)
class ScanFilesDeleted(Event):
    """The retention policy deleted a scan folder (the records stay)."""

    name: ClassVar[str] = "scan_files_deleted"
    scan_ids: tuple[int, ...]
    folder: str
    bytes: int
    reason: str


# ---- registrations and verifications (service.registrations.orchestrator) ---


@dataclass(frozen=True, kw_only=True)
class RegistrationDone(Event):
    """A registration was accepted and is now current (IGTL push, PACS export)."""

    name: ClassVar[str] = "registration_done"
    registration_id: int
    scan_id: int
    series_uid: str
    fre_mm: float | None
    n_matched: int


@dataclass(frozen=True, kw_only=True)
class RegistrationRefused(Event):
    """A registration was refused and stored with the reason; the current one, if any, stays."""

    name: ClassVar[str] = "registration_refused"
    registration_id: int
    scan_id: int | None
    series_uid: str
    title: str
    reason: str


@dataclass(frozen=True, kw_only=True)
class RegistrationWithdrawn(Event):
    """Registrations withdrawn: made from a scan that was reopened (incomplete when registered) or
    changed, or (``verification_scan_id`` set) the current one, whose verification failed its gate
    or could not be computed (docs/safety.md).  With ``was_current`` nothing is current any more:
    every push channel says INVALID (:attr:`service.registrations.orchestrator.Orchestrator.current` is
    None)."""

    name: ClassVar[str] = "registration_withdrawn"
    registration_ids: tuple[int, ...]
    scan_id: int
    """The scan the registrations were made from."""
    was_current: bool
    reason: str
    verification_scan_id: int | None = None
    """The verification scan that withdrew it (absent: a scan withdrawal)."""
    verification_id: int | None = None
    """The stored failed verification (absent: a scan withdrawal, or a verification that could not be
    computed)."""
    omitted_when_none: ClassVar[frozenset[str]] = frozenset({"verification_scan_id", "verification_id"})


@dataclass(frozen=True, kw_only=True)
class DerivedWithdrawn(Event):
    """Verifications / calibrations made from a scan whose content changed."""

    name: ClassVar[str] = "derived_withdrawn"
    scan_id: int
    verification_ids: tuple[int, ...]
    calibration_ids: tuple[int, ...]
    reason: str


@dataclass(frozen=True, kw_only=True)
class VerificationDone(Event):
    """A verification scan was measured against the current registration."""

    name: ClassVar[str] = "verification_done"
    verification_id: int
    registration_id: int
    scan_id: int
    mean_mm: float
    max_mm: float
    passed: bool


# ---- the robot link (service.intake.capture) ---


@dataclass(frozen=True, kw_only=True)
class LinkState(Event):
    """The robot link's state changed (``connected`` / ``stale`` / ``down``)."""

    name: ClassVar[str] = "link_state"
    url: str
    state: str
    reason: str


# ---- operating-room interfaces (service.intake.cstore_intake, service.navigation.igtl.publisher) ---

ReleaseOutcome = Literal["unchanged", "refused", "invalid", "complete", "reopened", "reopened_invalid"]


@dataclass(frozen=True, kw_only=True)
class DicomAssociationReleased(Event):
    """A C-STORE association released: the verdict on one series it sent."""

    name: ClassVar[str] = "dicom_association_released"
    series_uid: str
    calling_ae: str
    n_instances: int
    outcome: ReleaseOutcome
    scan_id: int | None
    reason: str


@dataclass(frozen=True, kw_only=True)
class DicomAssociationAborted(Event):
    """A C-STORE association was aborted: its partial series recorded ``invalid``."""

    name: ClassVar[str] = "dicom_association_aborted"
    series_uid: str
    n_instances: int
    reason: str


@dataclass(frozen=True, kw_only=True)
class DicomRefused(Event):
    """The SCP refused a peer, a calling AE, a presentation context or a dataset."""

    name: ClassVar[str] = "dicom_refused"
    kind: str
    """``peer``, ``calling_ae``, ``context``, ``dataset``, ``disk``
    (service.intake.storage_scp.ScpRefusal)."""
    reason: str
    calling_ae: str
    peer: str
    sop_instance_uid: str
    status: int | None


@dataclass(frozen=True, kw_only=True)
class _IgtlClientEvent(Event):
    peer: str
    clients: int
    header_version: int


@dataclass(frozen=True, kw_only=True)
class IgtlClientConnected(_IgtlClientEvent):
    """A navigation client connected to the OpenIGTLink server."""

    name: ClassVar[str] = "igtl_client_connected"


@dataclass(frozen=True, kw_only=True)
class IgtlClientDisconnected(_IgtlClientEvent):
    """A navigation client disconnected."""

    name: ClassVar[str] = "igtl_client_disconnected"


@dataclass(frozen=True, kw_only=True)
class IgtlClientHeaderVersion(_IgtlClientEvent):
    """The client sent header version 2: it is answered in version 2 from now on."""

    name: ClassVar[str] = "igtl_client_header_version"


# ---- calibration sessions (service.registrations.calibration_jobs, service.registrations.orchestrator) ---


@dataclass(frozen=True, kw_only=True)
class CalibrationStarted(Event):
    name: ClassVar[str] = "calibration_started"
    calibration_id: int
    scan_ids: tuple[int, ...]


@dataclass(frozen=True, kw_only=True)
class CalibrationProgress(Event):
    """Stage ``detect`` (pose ``pose`` of ``n_poses``, with its scan and matched spheres), then ``fit``."""

    name: ClassVar[str] = "calibration_progress"
    calibration_id: int
    stage: str
    pose: int
    n_poses: int
    scan_id: int | None = None
    n_matched: int | None = None
    omitted_when_none: ClassVar[frozenset[str]] = frozenset({"scan_id", "n_matched"})


@dataclass(frozen=True, kw_only=True)
class CalibrationDone(Event):
    name: ClassVar[str] = "calibration_done"
    calibration_id: int
    calibration_hash: str
    n_poses_used: int
    leave_one_pose_out_mean_mm: float | None
    predicted_held_out_rms_mm: float | None


@dataclass(frozen=True, kw_only=True)
class CalibrationRefused(Event):
    """A calibration was refused (``status``: the HTTP status of a refusal at request time)."""

    name: ClassVar[str] = "calibration_refused"
    calibration_id: int
    title: str
    reason: str
    status: int | None = None
    omitted_when_none: ClassVar[frozenset[str]] = frozenset({"status"})


@dataclass(frozen=True, kw_only=True)
class CalibrationActivated(Event):
    name: ClassVar[str] = "calibration_activated"
    calibration_id: int
    calibration_hash: str
    previous_calibration_id: int | None


@dataclass(frozen=True, kw_only=True)
class CalibrationDeactivated(Event):
    """The active calibration was withdrawn: the nominal robot model is used again."""

    name: ClassVar[str] = "calibration_deactivated"
    calibration_id: int
    reason: str


@dataclass(frozen=True, kw_only=True)
class RegistrationRetired(Event):
    """No registration is current any more (push channels INVALID until the next ``/register``)."""

    name: ClassVar[str] = "registration_retired"
    registration_ids: tuple[int, ...]
    previous_current_registration_id: int | None
    calibration_id: int
    current: None = None
    """Always null: nothing is current after a retirement (clients read the field)."""
    reason: str


# ---- archiving a registration's SRO to the PACS (service.navigation.pacs) --------------------------------


@dataclass(frozen=True, kw_only=True)
class _PacsExportFinished(Event):
    registration_id: int
    destination: str
    dimse_status: int | None
    reason: str
    sop_instance_uid: str
    attempts: int


@dataclass(frozen=True, kw_only=True)
class PacsExportSent(_PacsExportFinished):
    name: ClassVar[str] = "pacs_export_sent"


@dataclass(frozen=True, kw_only=True)
class PacsExportFailed(_PacsExportFinished):
    name: ClassVar[str] = "pacs_export_failed"


EVENT_TYPES: tuple[type[Event], ...] = tuple(_BY_NAME.values())
"""Every event class, in the order above."""
EVENT_NAMES: tuple[str, ...] = tuple(_BY_NAME)
"""Every wire name (``GET /events``), in the order above."""
