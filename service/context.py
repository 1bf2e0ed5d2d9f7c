"""What the routes need (``request.app.state.ctx``), built by :func:`service.app.create_app`."""

from __future__ import annotations

import asyncio
from dataclasses import dataclass, field
from datetime import UTC, datetime
from typing import IO

from drivers.base import RobotLink
from registration.model.kinematics import RobotModel
from registration.model.phantom import Phantom
from service.calibration_jobs import CalibrationJobs
from service.capture import Capture
from service.event_bus import EventBus
from service.or_integration import OrIntegration
from service.orchestrator import Orchestrator
from service.records import RegistrationRecord
from service.settings import Settings
from service.store import Database
from service.tickets import TicketBook
from service.volume_cache import VolumeCache
from service.watcher import SeriesWatcher


@dataclass
class ServiceContext:
    """The service's parts; ``db``, ``capture`` and ``orchestrator`` exist once the app has started."""

    settings: Settings
    bus: EventBus
    phantom: Phantom
    robot_model: RobotModel
    robot_link: RobotLink
    volumes: VolumeCache = field(default_factory=VolumeCache)
    db: Database = field(init=False)
    capture: Capture = field(init=False)
    orchestrator: Orchestrator = field(init=False)
    calibrations: CalibrationJobs = field(init=False)
    watcher: SeriesWatcher | None = None
    or_integration: OrIntegration | None = None
    """DICOM SCP, OpenIGTLink server, auto-register (:mod:`service.or_integration`)."""
    db_watch_task: asyncio.Task[None] | None = None
    tickets: TicketBook = field(default_factory=TicketBook)
    """Single-use tickets for GET /events?ticket= (service.security)."""
    retention_task: asyncio.Task[None] | None = None
    retention_problem: str | None = None
    """Set by the retention loop: why the scan folders exceed ``retention.max_disk_mb`` (``/status``)."""
    serve_lock: IO[bytes] | None = None
    """``<data>/serve.lock``, held exclusively while the service runs (service.data_dir)."""
    started_at: datetime = field(default_factory=lambda: datetime.now(UTC))
    current_json: tuple[RegistrationRecord, bytes] | None = None
    """(current registration record, its JSON) for GET /registration/current."""

    def current_registration_json(self) -> bytes | None:
        """The current registration as JSON bytes, encoded once per registration (None if none)."""
        cur = self.orchestrator.current
        if cur is None:
            return None
        cached = self.current_json
        if cached is None or cached[0] is not cur:
            from service.api.models import registration_out

            cached = (cur, registration_out(cur).model_dump_json().encode())
            self.current_json = cached
        return cached[1]
