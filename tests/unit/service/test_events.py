"""Every event's ``data`` bytes are what the service sent before its events became typed.

For each event class an example is built as its producer builds it, and ``json.dumps`` of its
payload is compared with ``json.dumps`` of the dict the producer published before (transcribed
from the producers as they were: the keys, their order, and the keys sent only when known).
``tests/integration/test_sse_wire_format.py`` pins the whole SSE bytes of four of them.
"""

from __future__ import annotations

import json

import pytest

from service import events as ev

OLD_EVENT_NAMES = (
    "scan_arrived", "scan_invalid", "scan_reopened", "scan_replaced", "scan_files_deleted",
    "registration_done", "registration_refused", "registration_withdrawn", "derived_withdrawn",
    "verification_done", "link_state", "dicom_association_released", "dicom_association_aborted",
    "dicom_refused", "igtl_client_connected", "igtl_client_disconnected", "igtl_client_header_version",
    "calibration_started", "calibration_progress", "calibration_done", "calibration_refused",
    "calibration_activated", "calibration_deactivated", "registration_retired", "pacs_export_sent",
    "pacs_export_failed",
)  # fmt: skip
"""The tuple ``service.event_bus.EVENT_NAMES`` was (docs/api.md and docs/safety.md name them)."""

SCAN = {"scan_id": 4, "series_uid": "1.2.3", "folder": "/w/s", "still": True, "link_state": "connected",
        "source": "dicom"}  # fmt: skip
REOPENED = {"reopened": True, "previous_status": "complete", "previous_slices": 190}
CHANGE = {"scan_id": 4, "series_uid": "1.2.3", "folder": "/w/s", "source": "C-STORE into /d",
          "previous_status": "complete", "previous_slices": 190, "added": ["a.dcm"], "replaced": [],
          "removed": ["b.dcm"], "reason": "changed"}  # fmt: skip
CHANGE_EVENT = dict(scan_id=4, series_uid="1.2.3", folder="/w/s", source="C-STORE into /d",
                    previous_status="complete", previous_slices=190, added=("a.dcm",), replaced=(),
                    removed=("b.dcm",), reason="changed")  # fmt: skip
PACS = {"registration_id": 3, "destination": "PACS@h:104", "dimse_status": None, "reason": "x",
        "sop_instance_uid": "1.9", "attempts": 2}  # fmt: skip
IGTL = {"peer": "127.0.0.1:5000", "clients": 1, "header_version": 2}

CASES: list[tuple[ev.Event, dict[str, object]]] = [
    (ev.ScanArrived(**SCAN, n_slices=192), {**SCAN, "n_slices": 192}),
    (
        ev.ScanArrived(**SCAN, reopening=ev.Reopening("complete", 190), n_slices=192),
        {**SCAN, **REOPENED, "n_slices": 192},
    ),
    (ev.ScanInvalid(**SCAN, reason="bad"), {**SCAN, "reason": "bad"}),
    (
        ev.ScanInvalid(**SCAN, reopening=ev.Reopening("replaced", 3), reason="bad"),
        {**SCAN, "reopened": True, "previous_status": "replaced", "previous_slices": 3, "reason": "bad"},
    ),
    (ev.ScanReopened(**CHANGE_EVENT), CHANGE),
    (ev.ScanReplaced(**CHANGE_EVENT, n_slices=191), {**CHANGE, "n_slices": 191}),
    (
        ev.ScanFilesDeleted(scan_ids=(1, 2), folder="/w/s", bytes=1024, reason="age"),
        {"scan_ids": [1, 2], "folder": "/w/s", "bytes": 1024, "reason": "age"},
    ),
    (
        ev.RegistrationDone(registration_id=3, scan_id=2, series_uid="1.2", fre_mm=0.08, n_matched=8),
        {"registration_id": 3, "scan_id": 2, "series_uid": "1.2", "fre_mm": 0.08, "n_matched": 8},
    ),
    (
        ev.RegistrationRefused(registration_id=4, scan_id=None, series_uid="", title="T", reason="r"),
        {"registration_id": 4, "scan_id": None, "series_uid": "", "title": "T", "reason": "r"},
    ),
    (
        ev.RegistrationWithdrawn(registration_ids=(3, 5), scan_id=2, was_current=False, reason="r"),
        {"registration_ids": [3, 5], "scan_id": 2, "was_current": False, "reason": "r"},
    ),
    (
        ev.DerivedWithdrawn(scan_id=2, verification_ids=(1,), calibration_ids=(), reason="r"),
        {"scan_id": 2, "verification_ids": [1], "calibration_ids": [], "reason": "r"},
    ),
    (
        ev.VerificationDone(
            verification_id=1, registration_id=6, scan_id=7, mean_mm=0.2, max_mm=0.4, passed=True
        ),
        {
            "verification_id": 1,
            "registration_id": 6,
            "scan_id": 7,
            "mean_mm": 0.2,
            "max_mm": 0.4,
            "passed": True,
        },
    ),
    (
        ev.LinkState(url="simple-message://h:11002", state="down", reason="refused"),
        {"url": "simple-message://h:11002", "state": "down", "reason": "refused"},
    ),
    (
        ev.DicomAssociationReleased(
            series_uid="1.2", calling_ae="OARM", n_instances=0, outcome="refused", scan_id=None, reason=""
        ),
        {
            "series_uid": "1.2",
            "calling_ae": "OARM",
            "n_instances": 0,
            "outcome": "refused",
            "scan_id": None,
            "reason": "",
        },
    ),
    (
        ev.DicomAssociationAborted(series_uid="1.2", n_instances=7, reason="aborted"),
        {"series_uid": "1.2", "n_instances": 7, "reason": "aborted"},
    ),
    (
        ev.DicomRefused(
            kind="peer", reason="r", calling_ae="", peer="10.0.0.1", sop_instance_uid="", status=None
        ),
        {
            "kind": "peer",
            "reason": "r",
            "calling_ae": "",
            "peer": "10.0.0.1",
            "sop_instance_uid": "",
            "status": None,
        },
    ),
    (ev.IgtlClientConnected(**IGTL), IGTL),
    (ev.IgtlClientDisconnected(**IGTL), IGTL),
    (ev.IgtlClientHeaderVersion(**IGTL), IGTL),
    (ev.CalibrationStarted(calibration_id=1, scan_ids=(2, 3)), {"calibration_id": 1, "scan_ids": [2, 3]}),
    (
        ev.CalibrationProgress(calibration_id=1, stage="fit", pose=4, n_poses=4),
        {"calibration_id": 1, "stage": "fit", "pose": 4, "n_poses": 4},
    ),
    (
        ev.CalibrationProgress(calibration_id=1, stage="detect", pose=1, n_poses=4, scan_id=9, n_matched=8),
        {"calibration_id": 1, "stage": "detect", "pose": 1, "n_poses": 4, "scan_id": 9, "n_matched": 8},
    ),
    (
        ev.CalibrationDone(
            calibration_id=1,
            calibration_hash="ab",
            n_poses_used=6,
            leave_one_pose_out_mean_mm=0.3,
            predicted_held_out_rms_mm=None,
        ),
        {
            "calibration_id": 1,
            "calibration_hash": "ab",
            "n_poses_used": 6,
            "leave_one_pose_out_mean_mm": 0.3,
            "predicted_held_out_rms_mm": None,
        },
    ),
    (
        ev.CalibrationRefused(calibration_id=1, title="T", reason="r", status=409),
        {"calibration_id": 1, "title": "T", "reason": "r", "status": 409},
    ),
    (
        ev.CalibrationRefused(calibration_id=1, title="T", reason="r"),
        {"calibration_id": 1, "title": "T", "reason": "r"},
    ),
    (
        ev.CalibrationActivated(calibration_id=2, calibration_hash="ab", previous_calibration_id=None),
        {"calibration_id": 2, "calibration_hash": "ab", "previous_calibration_id": None},
    ),
    (
        ev.CalibrationDeactivated(calibration_id=2, reason="r"),
        {"calibration_id": 2, "reason": "r"},
    ),
    (
        ev.RegistrationRetired(
            registration_ids=(1,), previous_current_registration_id=1, calibration_id=2, reason="r"
        ),
        {
            "registration_ids": [1],
            "previous_current_registration_id": 1,
            "calibration_id": 2,
            "current": None,
            "reason": "r",
        },
    ),
    (ev.PacsExportSent(**PACS), PACS),
    (ev.PacsExportFailed(**{**PACS, "dimse_status": 0xA700}), {**PACS, "dimse_status": 0xA700}),
]


def test_the_event_names_are_kept() -> None:
    assert ev.EVENT_NAMES == OLD_EVENT_NAMES


def test_every_event_class_has_a_case() -> None:
    assert {type(e) for e, _ in CASES} == set(ev.EVENT_TYPES)


@pytest.mark.parametrize(("event", "old"), CASES, ids=[f"{e.name}-{i}" for i, (e, _) in enumerate(CASES)])
def test_payload_bytes_are_the_old_ones(event: ev.Event, old: dict[str, object]) -> None:
    assert json.dumps(event.payload()) == json.dumps(old)


def test_a_second_class_with_a_taken_name_is_refused() -> None:
    with pytest.raises(TypeError, match="'scan_arrived' is taken by ScanArrived"):

        class Again(ev.Event):
            name = "scan_arrived"


def test_events_are_frozen() -> None:
    e = ev.LinkState(url="u", state="down", reason="r")
    with pytest.raises(AttributeError):
        e.state = "connected"
