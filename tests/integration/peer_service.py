"""A running service for the third-party-peer suites (issue #23: the reference OpenIGTLink library,
Orthanc): real uvicorn on loopback, a mock simple_message controller holding still, the DICOM
Storage SCP and the OpenIGTLink server on port 0, auto-register on.  Every wait polls with a deadline.
"""

from __future__ import annotations

import contextlib
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any, TypeVar

import httpx
import numpy as np
import pydicom
from pydicom.uid import CTImageStorage
from pynetdicom import AE

from dicomnet.scu import associate
from registration.model.frames import transform_from_xyz_rpy
from service.events import Event
from tests.helpers.scan_cache import simulated_scan
from tests.helpers.tokens import make_token
from tests.integration.polling import wait_for

E = TypeVar("E", bound=Event)

TOKEN = make_token()
WINDOW_S = 0.6
DEADLINE_S = 60.0
AE_TITLE = "OARMREG"
Q1 = (0.0, 0.0, np.pi / 2, 0.0, np.pi / 4, 0.0)
IMAGE_FROM_PHANTOM_1 = transform_from_xyz_rpy([2.0, -3.0, 1.0], [10.0, -6.0, 20.0])


@dataclass
class PeerService:
    client: httpx.Client
    ctx: Any
    robot: Any
    root: Path
    dicom_port: int
    igtl_port: int

    def events(self, kind: type[E]) -> list[E]:
        """The recent events of one class (:meth:`service.event_bus.EventBus.recent`)."""
        return [p.event for p in self.ctx.bus.recent() if isinstance(p.event, kind)]

    def scan(self, uid: str) -> dict[str, Any] | None:
        r = self.client.get("/scans", params={"limit": 1000})
        r.raise_for_status()
        return next((s for s in r.json() if s["series_uid"] == uid), None)

    def wait_scan(self, uid: str, status: str = "complete") -> dict[str, Any]:
        def ok() -> dict[str, Any] | None:
            s = self.scan(uid)
            return s if s is not None and s["status"] == status else None

        return wait_for(ok, f"series {uid} recorded {status}")  # type: ignore[no-any-return]

    def wait_registration(self, scan_id: int) -> dict[str, Any]:
        def accepted() -> dict[str, Any] | None:
            regs = self.client.get("/registrations").json()
            return next((r for r in regs if r["scan_id"] == scan_id and r["status"] == "accepted"), None)

        return wait_for(accepted, f"the auto-registration of scan {scan_id}")  # type: ignore[no-any-return]


@contextlib.contextmanager
def running_service(root: Path, phantom: Any, **overrides: Any) -> Iterator[PeerService]:
    """The service on ``root`` (``overrides``: more ``load_settings`` keys, e.g. ``pacs.port``)."""
    from mocks.robot.robot import ScriptedRobot
    from mocks.robot.runner import run_mock_controller
    from registration.model.kinematics import RobotModel
    from service.cli.commands.serve import serve_in_thread
    from service.http.app import create_app
    from service.settings import load_settings

    model = RobotModel.load("tx60")
    robot = ScriptedRobot(Q1)
    with run_mock_controller("simple-message", robot) as mock:
        settings = load_settings(None, {
            "watch_dir": root / "watch", "data_dir": root / "data", "api_token": TOKEN,
            "robot.link_url": mock.url, "robot.connect_timeout_s": 2.0,
            "stillness.window_s": WINDOW_S, "stillness.max_gap_s": 0.5,
            "watcher.quiet_period_s": 0.3, "watcher.poll_interval_s": 0.2,
            "dicom.enabled": True, "dicom.port": 0, "dicom.ae_title": AE_TITLE,
            "igtl.enabled": True, "igtl.port": 0, "igtl.period_s": 0.2, "service.auto_register": True,
            **overrides,
        })  # fmt: skip
        app = create_app(settings, phantom=phantom, robot_model=model)
        with (
            serve_in_thread(app) as server,
            httpx.Client(
                base_url=server.base_url, headers={"Authorization": f"Bearer {TOKEN}"}, timeout=60.0
            ) as client,
        ):
            lst = client.get("/status").json()["listeners"]
            svc = PeerService(client, app.state.ctx, robot, root, lst["dicom"]["port"], lst["igtl"]["port"])
            wait_for(lambda: client.get("/status").json()["link"]["history_s"] > WINDOW_S, "joint history")
            yield svc


def simulated_series(phantom: Any, folder: Path, **export: Any) -> tuple[str, list[Path]]:
    """Scan 1 of the phantom (``small`` preset) written as a DICOM series into ``folder``."""
    from mocks.oarm.dicom_export import write_dicom_series
    from mocks.oarm.simulator import AcquisitionSettings

    scan = simulated_scan(phantom, IMAGE_FROM_PHANTOM_1, AcquisitionSettings.preset("small"))
    res = write_dicom_series(scan, folder, write_truth=False, **export)
    return str(res.series_uid), sorted(Path(p) for p in res.paths)


def send_files(port: int, files: list[Path], *, calling_ae: str = "OARM_TEST") -> list[int]:
    """C-STORE ``files`` with pynetdicom's SCU; return the statuses."""
    ae = AE(ae_title=calling_ae)
    ae.add_requested_context(CTImageStorage)
    assoc = associate(ae, "127.0.0.1", port, ae_title=AE_TITLE)
    assert assoc.is_established, f"association from {calling_ae} not established"
    try:
        return [int(assoc.send_c_store(pydicom.dcmread(f)).Status) for f in files]
    finally:
        assoc.release()


def wait_export(
    svc: PeerService, registration_id: int, done: Callable[[dict[str, Any]], bool], what: str
) -> dict[str, Any]:
    """The registration's ``pacs_export`` once ``done`` holds for it (deadline)."""

    def ok() -> dict[str, Any] | None:
        exp = svc.client.get(f"/registrations/{registration_id}").json().get("pacs_export")
        return exp if exp is not None and done(exp) else None

    return wait_for(ok, f"the PACS export of registration {registration_id} to be {what}")  # type: ignore[no-any-return]
