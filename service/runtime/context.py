"""The service's inputs and its running parts.

:class:`ServiceInputs` is what :func:`service.runtime.inputs.prepare_inputs` validates and loads
before start-up; :func:`service.runtime.assembly.start_service` starts the parts in order and only
then builds the :class:`ServiceContext` (the routes read it as ``request.app.state.ctx``),
complete: every part that always runs is a plain field, and only the parts the settings can switch
off (the folder watcher, the C-STORE intake, the OpenIGTLink publisher, the PACS export,
auto-register) are ``Optional``.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field
from datetime import UTC, datetime
from typing import Any

from drivers.base import RobotLink
from registration.model.kinematics import RobotModel
from registration.model.phantom import Phantom
from service.event_bus import EventBus
from service.intake.capture import Capture
from service.intake.cstore_intake import CStoreIntake
from service.intake.volume_cache import VolumeCache
from service.intake.watcher import SeriesWatcher
from service.navigation.igtl.publisher import IgtlPublisher
from service.navigation.pacs.exporter import PacsExporter
from service.registrations.auto_register import AutoRegister
from service.registrations.calibration_jobs import CalibrationJobs
from service.registrations.orchestrator import Orchestrator
from service.settings import Settings
from service.store import Database


@dataclass(frozen=True)
class ServiceInputs:
    """What exists before start-up: validated settings, the loaded phantom and robot model, the
    robot link (not connected yet), the bus, and the state kept across restarts of the app."""

    settings: Settings
    bus: EventBus
    phantom: Phantom
    robot_model: RobotModel
    robot_link: RobotLink
    volumes: VolumeCache = field(default_factory=VolumeCache)
    started_at: datetime = field(default_factory=lambda: datetime.now(UTC))


@dataclass
class ServiceContext:
    """The running service's parts, built once by the lifespan after each has started."""

    settings: Settings
    bus: EventBus
    phantom: Phantom
    robot_model: RobotModel
    robot_link: RobotLink
    volumes: VolumeCache
    started_at: datetime
    db: Database
    capture: Capture
    orchestrator: Orchestrator
    calibrations: CalibrationJobs
    watcher: SeriesWatcher | None
    """None when started without the folder watcher."""
    cstore: CStoreIntake | None
    """The DICOM C-STORE intake (``[dicom] enabled``)."""
    igtl: IgtlPublisher | None
    """The OpenIGTLink publisher (``[igtl] enabled``)."""
    pacs: PacsExporter | None
    """The PACS archive of each accepted registration (``[pacs] enabled``)."""
    auto_register: AutoRegister | None
    """``service.registrations.auto_register``."""
    retention_problem: str | None = None
    """Set by the retention loop: why the scan folders exceed ``retention.max_disk_mb`` (``/status``)."""

    def listeners(self) -> dict[str, Any]:
        """For ``GET /status`` (``listeners``): each operating-room interface's state."""
        s = self.settings
        d, g, p = s.dicom, s.igtl, s.pacs
        dicom = (
            self.cstore.status()
            if self.cstore is not None
            else {"enabled": d.enabled, "host": d.host, "ae_title": d.ae_title, "port": None}
        )
        igtl = (
            self.igtl.status()
            if self.igtl is not None
            else {"enabled": g.enabled, "host": g.host, "port": None}
        )
        pacs: dict[str, Any] = {"enabled": p.enabled}
        if self.pacs is not None:
            pacs.update(destination=self.pacs.destination, calling_ae_title=p.calling_ae_title)
        return {
            "dicom": dicom,
            "igtl": igtl,
            "pacs": pacs,
            "tls": s.tls.enabled,
            "auto_register": s.service.auto_register,
            "event_bus_failures": [asdict(f) for f in self.bus.listener_failures()],
        }
