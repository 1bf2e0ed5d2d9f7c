"""The orchestrator alone, without HTTP: a real store in a temp folder, a recording bus, two simulated
scans of the default phantom on the TX60 (the pipeline runs for real: it is what the orchestrator
orchestrates), and scan records written as the intake writes them.

What becomes current, what is refused and stored, what a failed verification withdraws, which scan
is superseded, and which events reach the bus.  The same rules are tested through the running
service in tests/integration/test_service_loop.py and tests/faults/test_verification_governs.py.
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from mocks.oarm.dicom_export import write_dicom_series
from mocks.oarm.simulator import AcquisitionSettings
from registration.model.frames import invert, transform_from_xyz_rpy
from registration.model.kinematics import RobotModel
from service.errors import SupersededScanError, VerificationUncomputableError
from service.events import (
    RegistrationDone,
    RegistrationRefused,
    RegistrationWithdrawn,
    VerificationDone,
)
from service.records import JointSnapshot, NewScan, RegistrationRecord, RegistrationRefusal
from service.registrations.orchestrator import Orchestrator, SupersededOverride
from service.settings import Settings, load_settings
from service.store import Database
from tests.helpers.scan_cache import simulated_scan

Q1 = (0.0, 0.0, np.pi / 2, 0.0, np.pi / 4, 0.0)
Q2 = (0.0, 0.0, np.pi / 2, 0.0, np.pi / 4, 0.3)  # J6 +0.3 rad: the phantom turns about its own axis
IMAGE_FROM_PHANTOM_1 = transform_from_xyz_rpy([2.0, -3.0, 1.0], [10.0, -6.0, 20.0])
TOOL0_FROM_PHANTOM = transform_from_xyz_rpy([0, 0, 200], [180, 0, 0])
"""The settings' default rod (robot.tool0_from_phantom)."""
WINDOW_S = 2.0


@dataclass(frozen=True)
class Folders:
    """Two scans on disk as DICOM: at Q1 and at Q2 (the robot moved the phantom between them)."""

    scan1: Path
    scan2: Path
    for_uid: str


@pytest.fixture(scope="module")
def folders(tmp_path_factory: pytest.TempPathFactory, phantom: Any) -> Folders:
    model = RobotModel.load("tx60")
    image_from_robot = IMAGE_FROM_PHANTOM_1 @ invert(model.robot_from_tool0(Q1) @ TOOL0_FROM_PHANTOM)
    image_from_phantom_2 = image_from_robot @ model.robot_from_tool0(Q2) @ TOOL0_FROM_PHANTOM
    root = tmp_path_factory.mktemp("orchestrator-scans")
    for_uid = "1.2.826.0.1.3680043.8.498.4401"  # one O-arm placement for both scans
    scans = (
        simulated_scan(phantom, IMAGE_FROM_PHANTOM_1, AcquisitionSettings.preset("small")),
        simulated_scan(phantom, image_from_phantom_2, AcquisitionSettings.preset("small", seed=1)),
    )
    for name, scan in zip(("scan1", "scan2"), scans, strict=True):
        write_dicom_series(scan, root / name, write_truth=False, frame_of_reference_uid=for_uid)
    return Folders(root / "scan1", root / "scan2", for_uid)


@dataclass
class World:
    orchestrator: Orchestrator
    db: Database
    events: list[Any]
    folders: Folders
    settings: Settings

    def record(self, folder: Path, joints: tuple[float, ...], verdict: str = "still", name: str = "") -> int:
        """The scan record the intake writes for ``folder`` (``name`` tells re-recordings apart)."""
        snapshot = JointSnapshot(
            link_url="simple-message://127.0.0.1:11002", link_state="connected", window_s=WINDOW_S,
            verdict=verdict,  # type: ignore[arg-type]
            joints_rad=tuple(joints), joints_received_at="2026-12-05T10:00:00+00:00",
            stillness_reason="" if verdict == "still" else f"the robot {verdict} during the scan",
        )  # fmt: skip
        from registration.dicom import load_series

        volume = load_series(folder, unique=True)
        uid = volume.series_uid + name
        self.orchestrator.volumes.put(uid, volume)  # as the intake caches what it recorded
        scan_id, _ = self.db.scans.upsert(
            NewScan(
                series_uid=uid,
                folder=str(folder),
                status="complete",
                frame_of_reference_uid=self.folders.for_uid,
                n_files=volume.shape[0],
                n_slices=volume.shape[0],
                snapshot=snapshot,
            )
        )
        return scan_id

    def of(self, kind: type) -> list[Any]:
        return [e for e in self.events if isinstance(e, kind)]

    def failing_verification(self) -> int:
        """Verify on the second scan recorded with the first pose's joints: the prediction misses by
        millimetres, so the verification fails its gate (a stored record) or cannot be computed (an
        error); either withdraws.  Returns the verification scan's id."""
        wrong = self.record(self.folders.scan2, Q1, name=".wrong-joints")
        try:
            ver = self.orchestrator.verify(wrong)
        except VerificationUncomputableError:
            return wrong
        assert not ver.passed and ver.max_mm > self.settings.quality.max_verification_error_mm, ver
        return wrong


@pytest.fixture
def world(tmp_path: Path, folders: Folders, phantom: Any) -> Iterator[World]:
    settings = load_settings(None, {"data_dir": tmp_path / "data", "stillness.window_s": WINDOW_S})
    db = Database.open(tmp_path / "oarmreg.sqlite3")
    events: list[Any] = []
    try:
        orch = Orchestrator(settings, db, phantom, RobotModel.load("tx60"), events.append)
        yield World(orch, db, events, folders, settings)
    finally:
        db.close()


def test_an_accepted_registration_becomes_current_and_is_announced(world: World) -> None:
    scan_id = world.record(world.folders.scan1, Q1)
    rec = world.orchestrator.register(scan_id)
    assert isinstance(rec, RegistrationRecord) and rec.status == "accepted", rec
    assert world.orchestrator.current is not None and world.orchestrator.current.id == rec.id
    assert world.db.registrations.current_id() == rec.id
    assert rec.fre_mm is not None and rec.fre_mm < 0.5
    assert [e.registration_id for e in world.of(RegistrationDone)] == [rec.id]
    assert world.of(RegistrationRefused) == []


def test_a_moved_robot_is_refused_stored_and_the_current_one_stays(world: World) -> None:
    good = world.orchestrator.register(world.record(world.folders.scan1, Q1))
    assert isinstance(good, RegistrationRecord)
    moved = world.record(world.folders.scan1, Q1, verdict="moved", name=".moved")
    out = world.orchestrator.register(moved)
    assert isinstance(out, RegistrationRefusal) and out.registration_id is not None, out
    stored = world.db.registrations.get(out.registration_id)
    assert stored is not None and stored.status == "refused" and stored.http_status == 409, stored
    assert "moved" in stored.reason.lower(), stored.reason
    assert world.orchestrator.current is not None and world.orchestrator.current.id == good.id
    refused = world.of(RegistrationRefused)
    assert [(e.registration_id, e.scan_id) for e in refused] == [(out.registration_id, moved)]


def test_a_passing_verification_keeps_it_current_and_a_failing_one_withdraws_it(world: World) -> None:
    reg = world.orchestrator.register(world.record(world.folders.scan1, Q1))
    assert isinstance(reg, RegistrationRecord)
    passed = world.orchestrator.verify(world.record(world.folders.scan2, Q2))
    assert passed.passed and passed.registration_id == reg.id, passed
    assert world.orchestrator.current is not None and world.orchestrator.current.id == reg.id
    wrong = world.failing_verification()
    assert world.orchestrator.current is None
    assert world.db.registrations.current_id() is None
    withdrawal = world.orchestrator.withdrawal
    assert withdrawal is not None and withdrawal.registration_id == reg.id
    assert withdrawal.verification_scan_id == wrong
    withdrawn = world.of(RegistrationWithdrawn)
    assert [(e.registration_ids, e.was_current) for e in withdrawn] == [((reg.id,), True)]
    assert [v.passed for v in world.of(VerificationDone)][:1] == [True]


def test_a_scan_with_newer_evidence_against_it_is_refused_unless_overridden(world: World) -> None:
    first = world.record(world.folders.scan1, Q1)
    reg = world.orchestrator.register(first)
    assert isinstance(reg, RegistrationRecord)
    world.failing_verification()
    again = world.orchestrator.register(first)  # the withdrawn registration's own scan
    assert isinstance(again, RegistrationRefusal) and isinstance(again.error, SupersededScanError), again
    assert world.orchestrator.current is None
    why = "the O-arm was put back; the failed verification's scan was taken while it was bumped"
    overridden = world.orchestrator.register(first, override=SupersededOverride(why))
    assert isinstance(overridden, RegistrationRecord) and overridden.status == "accepted", overridden
    assert world.orchestrator.current is not None and world.orchestrator.current.id == overridden.id
    assert overridden.figures is not None
    assert why in str(overridden.figures.provenance.get("superseded_override")), overridden.figures.provenance


def test_withdrawing_a_changed_scan_withdraws_its_current_registration(world: World) -> None:
    scan_id = world.record(world.folders.scan1, Q1)
    reg = world.orchestrator.register(scan_id)
    assert isinstance(reg, RegistrationRecord)
    withdrawn_ids = world.orchestrator.withdraw_scan(scan_id, "the series changed on disk")
    assert withdrawn_ids == [reg.id]
    assert world.orchestrator.current is None and world.db.registrations.current_id() is None
    stored = world.db.registrations.get(reg.id)
    assert stored is not None and stored.status == "withdrawn"
    withdrawn = world.of(RegistrationWithdrawn)
    assert [(e.registration_ids, e.scan_id, e.was_current) for e in withdrawn] == [((reg.id,), scan_id, True)]
    assert withdrawn[0].reason == "the series changed on disk"
