"""Test doubles for the unit tests of the orchestrator and the calibration jobs.

The pipeline runs for real (kinematics, matching, the FRE and verification gates, the calibration
solver) except sphere detection: :class:`FakeDetector` stands in for
``registration.detection.detect_spheres`` and returns the centres :meth:`Cell.scan` computed for the
scan's series (the phantom's spheres through the nominal robot model and rod, mapped into the image by
a known ``image_from_robot``, with a little noise).  Volumes are tiny placeholders put in the
:class:`~service.intake.volume_cache.VolumeCache`, so nothing is read from disk.
"""

from __future__ import annotations

import threading
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, TypeVar

import numpy as np
import pytest
from numpy.typing import NDArray

from mocks.cell import SPREAD_BASE_JOINTS_RAD, SPREAD_OFFSETS_RAD
from registration.detection import DetectionParams, DetectionResult
from registration.detection.records import DetectedSphere
from registration.imaging.volume import Volume
from registration.model import frames
from registration.model.kinematics import RobotModel, sphere_centres_robot_mm
from registration.model.phantom import Phantom, load_phantom
from service.events import Event
from service.intake.volume_cache import VolumeCache
from service.records import JointSnapshot, NewScan, ScanStatus, StillnessVerdict
from service.settings import Settings, load_settings
from service.store import Database

E = TypeVar("E", bound=Event)
F64 = NDArray[np.float64]

PLACEMENT = "1.2.826.0.1.3680043.8.498.4401"
"""The FrameOfReferenceUID of the O-arm placement the scans are taken at."""
IMAGE_FROM_ROBOT = frames.transform_from_xyz_rpy([300.0, -100.0, 500.0], [10.0, 80.0, -30.0])
"""Where the robot base is in the scans' image frame (mm)."""
NOISE_MM = 0.02
"""Per-axis detection noise (σ, mm): FRE well inside the 0.5 mm gate."""


class Recorder:
    """A publisher: collects every event passed to it, in order (from any thread)."""

    def __init__(self) -> None:
        self.events: list[Event] = []
        self._changed = threading.Condition()

    def __call__(self, event: Event) -> None:
        with self._changed:
            self.events.append(event)
            self._changed.notify_all()

    def wait_for(self, kind: type[E], timeout_s: float = 60.0) -> E:
        """The first event of ``kind``, once published (AssertionError after ``timeout_s``)."""
        found = self._published(kind, timeout_s)
        assert found, f"no {kind.__name__} within {timeout_s} s; events: {self.names}"
        return found[0]

    def published_within(self, kind: type[Event], timeout_s: float) -> bool:
        """Whether an event of ``kind`` is (or gets) published within ``timeout_s`` (no assertion)."""
        return bool(self._published(kind, timeout_s))

    def _published(self, kind: type[E], timeout_s: float) -> list[E]:
        """The events of ``kind`` once there is one, or none after ``timeout_s``."""
        with self._changed:
            return self._changed.wait_for(lambda: self.of(kind), timeout=timeout_s)

    def of(self, kind: type[E]) -> list[E]:
        return [e for e in self.events if isinstance(e, kind)]

    @property
    def names(self) -> list[str]:
        return [e.name for e in self.events]

    def clear(self) -> None:
        self.events.clear()


class FakeDetector:
    """``detect_spheres(volume, params)``: the centres set for the volume's series (KeyError if none).

    ``before`` runs first on each call with the series UID (a test makes the scan change, or raises)."""

    def __init__(self) -> None:
        self.centres: dict[str, F64] = {}
        self.calls: list[str] = []
        self.before: Callable[[str], object] | None = None

    def __call__(self, volume: Volume, params: DetectionParams) -> DetectionResult:
        self.calls.append(volume.series_uid)
        if self.before is not None:
            self.before(volume.series_uid)
        spheres = tuple(
            DetectedSphere(
                center_image_mm=np.asarray(c, dtype=np.float64), radius_mm=1.6, n_slices=5, score=1.0
            )
            for c in self.centres[volume.series_uid]
        )
        return DetectionResult(spheres=spheres, rejections=(), method="fake", timings_s={"fake_s": 0.0})


def reachable_joints() -> list[tuple[float, ...]]:
    """Spread TX60 poses (mocks.cell) inside the joint limits, the base pose first."""
    model = RobotModel.load("tx60")
    out = []
    for offset in SPREAD_OFFSETS_RAD:
        q = SPREAD_BASE_JOINTS_RAD + offset
        try:
            model.check_joints(q)
        except Exception:
            continue
        out.append(tuple(float(v) for v in q))
    return out


POSES = reachable_joints()


@dataclass
class Cell:
    """A database, the settings, the phantom and robot model, and a way to make scans of them."""

    tmp: Path
    settings: Settings
    db: Database
    phantom: Phantom
    model: RobotModel
    detector: FakeDetector
    volumes: VolumeCache = field(default_factory=lambda: VolumeCache(size=64))
    publish: Recorder = field(default_factory=Recorder)
    n_scans: int = 0

    @property
    def rod(self) -> F64:
        return self.settings.robot.tool0_from_phantom.matrix()

    def centres_image_mm(
        self, joints: Sequence[float], image_from_robot: F64 = IMAGE_FROM_ROBOT, *, seed: int = 0
    ) -> F64:
        robot = sphere_centres_robot_mm(self.model, joints, self.rod, self.phantom.centres_phantom_mm)
        noise = np.random.default_rng(seed).normal(0.0, NOISE_MM, robot.shape)
        return np.asarray(frames.apply(image_from_robot, robot) + noise, dtype=np.float64)

    def scan(
        self,
        joints: Sequence[float] = POSES[0],
        *,
        image_from_robot: F64 = IMAGE_FROM_ROBOT,
        n_spheres: int | None = None,
        verdict: StillnessVerdict = "still",
        status: ScanStatus = "complete",
        for_uid: str = PLACEMENT,
        snapshot: bool = True,
    ) -> int:
        """Record a scan of the phantom held at ``joints`` and set what detection finds in it (the
        first ``n_spheres`` spheres only, if given); its id."""
        self.n_scans += 1
        uid = f"{PLACEMENT}.{self.n_scans}"
        centres = self.centres_image_mm(joints, image_from_robot, seed=self.n_scans)
        self.detector.centres[uid] = centres if n_spheres is None else centres[:n_spheres]
        snap = JointSnapshot(
            link_url="simple-message://127.0.0.1:11002", link_state="connected", window_s=60.0,
            verdict=verdict, captured_at="2026-01-01T00:00:00+00:00", joints_rad=tuple(joints),
            joints_received_at="2026-01-01T00:00:00+00:00", n_samples=3000,
            stillness_reason="the robot moved 0.2 rad" if verdict == "moved" else "",
        )  # fmt: skip
        sid, created = self.db.scans.upsert(
            NewScan(
                series_uid=uid, folder=str(self.tmp / "scans" / str(self.n_scans)), status=status,
                reason="" if status == "complete" else "instances missing", frame_of_reference_uid=for_uid,
                n_files=2, n_slices=2, rows=2, columns=2, snapshot=snap if snapshot else None,
            )
        )  # fmt: skip
        assert created
        voxels = np.zeros((2, 2, 2), dtype=np.int16)
        self.volumes.put(uid, Volume(voxels, np.eye(4), series_uid=uid, frame_of_reference_uid=for_uid))
        return sid


def moved(translation_mm: Sequence[float], image_from_robot: F64 = IMAGE_FROM_ROBOT) -> F64:
    """``image_from_robot`` after the phantom (or the O-arm) moved by ``translation_mm`` in the image."""
    shift = np.eye(4)
    shift[:3, 3] = translation_mm
    return np.asarray(shift @ image_from_robot, dtype=np.float64)


def make_settings(tmp: Path, **overrides: Any) -> Settings:
    return load_settings(None, {"data_dir": tmp / "data", "watch_dir": tmp / "watch", **overrides})


def install_detector(monkeypatch: pytest.MonkeyPatch) -> FakeDetector:
    """Replace ``detect_spheres`` where the pipeline and the calibration worker look it up."""
    import registration.detection
    import registration.pipeline

    fake = FakeDetector()
    monkeypatch.setattr(registration.pipeline, "detect_spheres", fake)
    monkeypatch.setattr(registration.detection, "detect_spheres", fake)
    return fake


def open_cell(tmp: Path, monkeypatch: pytest.MonkeyPatch, **overrides: Any) -> Cell:
    """A cell on a new database in ``tmp`` (the caller closes ``cell.db``)."""
    settings = make_settings(tmp, **overrides)
    db = Database.open(tmp / "oarmreg.sqlite3")
    model = RobotModel.load(settings.robot.model)
    return Cell(tmp, settings, db, load_phantom(settings.phantom_file), model, install_detector(monkeypatch))
