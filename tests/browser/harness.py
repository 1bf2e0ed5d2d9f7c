"""The real service on mock hardware with a history worth showing, and headless Chromium (issue #21).

Shared by the browser tests (one service and one browser per module) and ``make screenshots``.
The service: mock simple_message controller, simulated O-arm scans exported into the watched
folder, uvicorn on loopback.  Chromium: Debian's ``/usr/bin/chromium`` driven by Playwright (its
own browser download cannot work here), headless, no sandbox (root), no background traffic.
No sleeps: every wait polls with a deadline or waits on a selector.
"""

from __future__ import annotations

import contextlib
import os
import shutil
import time
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import httpx
import numpy as np

from tests.helpers.scan_cache import simulated_scan
from tests.helpers.tokens import make_token
from tests.integration.fast_service import fast_overrides
from tests.integration.polling import wait_for, wait_robot_still

REPO = Path(__file__).resolve().parents[2]
TOKEN = make_token()
WINDOW_S = 0.6
DEADLINE_S = 60.0
Q1 = (0.0, 0.0, np.pi / 2, 0.0, np.pi / 4, 0.0)
Q2 = (0.0, 0.0, np.pi / 2, 0.0, np.pi / 4, 0.3)
CHROMIUM = Path(os.environ.get("OARMREG_CHROMIUM", "/usr/bin/chromium"))
CHROMIUM_ARGS = (
    "--no-sandbox",  # CI runs as root; Chromium's sandbox refuses root
    "--headless",
    "--disable-gpu",
    "--disable-background-networking",
    "--disable-component-update",
    "--disable-sync",
    "--no-first-run",
)


def chromium_missing() -> str | None:
    """Why the browser tests cannot run here (None: they can)."""
    if not CHROMIUM.is_file():
        return f"{CHROMIUM} not installed (apt-get install chromium; .ci/run installs it)"
    try:
        import playwright.sync_api  # noqa: F401
    except ImportError:
        return "playwright (the test extra) is not installed"
    return None


@dataclass
class World:
    """Simulated scans (small preset): scan1 at Q1, scan2 at Q2 (a verification pose)."""

    phantom: Any
    model: Any
    scan1: Any
    scan2: Any


def make_world(phantom: Any) -> World:
    from mocks.oarm.simulator import AcquisitionSettings
    from registration.model.frames import invert, transform_from_xyz_rpy
    from registration.model.kinematics import RobotModel

    model = RobotModel.load("tx60")
    t0p = transform_from_xyz_rpy([0, 0, 200], [180, 0, 0])
    image_from_phantom_1 = transform_from_xyz_rpy([2.0, -3.0, 1.0], [10.0, -6.0, 20.0])
    image_from_robot = image_from_phantom_1 @ invert(model.robot_from_tool0(Q1) @ t0p)
    image_from_phantom_2 = image_from_robot @ model.robot_from_tool0(Q2) @ t0p
    small = AcquisitionSettings.preset("small")
    scan1 = simulated_scan(phantom, image_from_phantom_1, small)
    scan2 = simulated_scan(phantom, image_from_phantom_2, AcquisitionSettings.preset("small", seed=1))
    return World(phantom, model, scan1, scan2)


@dataclass
class Service:
    base_url: str
    client: httpx.Client
    robot: Any
    ctx: Any
    watch: Path
    n_exports: int = 0
    scans: dict[str, int] = field(default_factory=dict)

    def hold_at(self, q: tuple[float, ...]) -> None:
        if not np.allclose(self.robot.joints_rad_at(), q, atol=1e-9):
            self.robot.move_to(q, duration_s=0.01)
        wait_robot_still(self.client, self.robot, WINDOW_S, DEADLINE_S)

    def export(self, scan: Any, name: str, *, drop_last: int = 0) -> tuple[str, Path]:
        """Write ``scan`` atomically into ``watch/<name>-<n>``; returns (series UID, held-back files)."""
        from mocks.oarm.dicom_export import write_dicom_series

        name = f"{name}-{self.n_exports}"
        self.n_exports += 1
        staging = self.watch.parent / f"staging-{name}"
        held = self.watch.parent / f"held-{name}"
        res = write_dicom_series(scan, staging, write_truth=False)
        if drop_last:
            held.mkdir()
            for f in sorted(staging.glob("*.dcm"))[-drop_last:]:
                f.rename(held / f.name)
        staging.rename(self.watch / name)
        return str(res.series_uid), held

    def scan(self, uid: str) -> dict[str, Any]:
        def find() -> dict[str, Any] | None:
            return next((s for s in self.client.get("/scans").json() if s["series_uid"] == uid), None)

        return wait_for(find, f"scan {uid} to be recorded")  # type: ignore[no-any-return]

    def register(self, scan_id: int) -> httpx.Response:
        return self.client.post("/register", json={"scan_id": scan_id})


@contextlib.contextmanager
def running_service(root: Path, world: World, **settings_kw: Any) -> Iterator[Service]:
    from mocks.robot.robot import ScriptedRobot
    from mocks.robot.runner import run_mock_controller
    from service.cli.commands.serve import serve_in_thread
    from service.http.app import create_app
    from service.settings import load_settings

    watch, data = root / "watch", root / "data"
    robot = ScriptedRobot(Q1)
    with run_mock_controller("simple-message", robot) as mock:
        settings = load_settings(None, fast_overrides(watch, data, mock.url, TOKEN, WINDOW_S, **settings_kw))
        app = create_app(settings, phantom=world.phantom, robot_model=world.model)
        with (
            serve_in_thread(app) as server,
            httpx.Client(
                base_url=server.base_url, headers={"Authorization": f"Bearer {TOKEN}"}, timeout=120.0
            ) as client,
        ):
            yield Service(server.base_url, client, robot, app.state.ctx, watch)


def build_history(svc: Service, world: World) -> dict[str, Any]:
    """What an OR day leaves: an accepted registration, a refusal (robot moved during the scan),
    a passed verification and a failed one (a tighter gate is not possible per request, so the
    failed one is of a scan whose registration pose differs: see the test), a current registration.

    Returns the API's answers by name.
    """
    out: dict[str, Any] = {}
    svc.hold_at(Q1)
    uid, _ = svc.export(world.scan1, "reg")
    scan1 = svc.scan(uid)
    assert scan1["status"] == "complete" and scan1["joints"]["still"], scan1
    r = svc.register(scan1["id"])
    assert r.status_code == 200, r.text
    out["accepted"] = r.json()

    # a refusal: the robot moves while the scan arrives
    j6_start = svc.robot.joints_rad_at()[5]
    svc.robot.move_to(Q2, duration_s=6.0)  # still moving while the series is exported and settles
    # the minimum-jerk profile starts slowly: export once J6 has clearly left (20 × the stillness gate)
    wait_for(lambda: abs(svc.robot.joints_rad_at()[5] - j6_start) > 0.01, "the robot to start moving")
    uid, _ = svc.export(world.scan1, "moving")
    moving = svc.scan(uid)
    assert not moving["joints"]["still"], moving
    refused = svc.register(moving["id"])
    assert refused.status_code == 409, refused.text
    out["refused"] = refused.json()

    # a verification at Q2 against the current registration
    svc.hold_at(Q2)
    uid, _ = svc.export(world.scan2, "verify")
    scan2 = svc.scan(uid)
    v = svc.client.post("/verify", json={"scan_id": scan2["id"]})
    assert v.status_code == 200, v.text
    out["verification"] = v.json()
    svc.hold_at(Q1)
    return out


@contextlib.contextmanager
def browser() -> Iterator[Any]:
    """One headless Chromium (Playwright's sync API) for a module."""
    from playwright.sync_api import sync_playwright

    with sync_playwright() as pw:
        b = pw.chromium.launch(executable_path=str(CHROMIUM), args=list(CHROMIUM_ARGS), headless=True)
        try:
            yield b
        finally:
            b.close()


@dataclass
class PageWatch:
    """A page with every request and console message recorded (for origin and error checks)."""

    page: Any
    origin: str
    requests: list[str] = field(default_factory=list)
    console: list[tuple[str, str, str]] = field(default_factory=list)
    """(type, text, URL of the source) of every console message; for Chromium's "Failed to load
    resource" errors (a fetch() answered 4xx/5xx) the URL is the resource's."""
    page_errors: list[str] = field(default_factory=list)

    def foreign_requests(self) -> list[str]:
        return [u for u in self.requests if not (u.startswith(self.origin + "/") or u == self.origin)]

    def console_errors(self, provoked: tuple[tuple[str, int], ...] = ()) -> list[str]:
        """Console errors and uncaught page errors, except the failed loads the test itself provoked:
        ``provoked`` holds (path, status) pairs, e.g. ``("/registration/current", 409)`` when the
        scenario withdraws the current registration while the page may be fetching it.  Any other
        error (another status, another path, anything else) is returned."""
        return [
            text
            for kind, text, url in self.console
            if kind == "error" and not self._provoked(text, url, provoked)
        ] + self.page_errors

    def _provoked(self, text: str, url: str, provoked: tuple[tuple[str, int], ...]) -> bool:
        if not (text.startswith(FAILED_LOAD) and url.startswith(self.origin + "/")):
            return False
        path = url[len(self.origin) :].split("?", 1)[0]
        return any(path == p and text.startswith(f"{FAILED_LOAD} {status} ") for p, status in provoked)

    def on_console(self, msg: Any) -> None:
        self.console.append((msg.type, msg.text, str(msg.location.get("url", ""))))


FAILED_LOAD = "Failed to load resource: the server responded with a status of"
"""How Chromium logs a fetch() answered with an HTTP error (the status follows, then its reason)."""


def watched_page(context: Any, origin: str) -> PageWatch:
    page = context.new_page()
    w = PageWatch(page, origin)
    page.on("request", lambda req: w.requests.append(req.url))
    page.on("console", w.on_console)
    page.on("pageerror", lambda exc: w.page_errors.append(str(exc)))
    return w


def copy_late_slices(held: Path, folder: Path) -> None:
    """Deliver held-back slices of a series into its folder (atomically, one by one)."""
    for f in sorted(held.glob("*.dcm")):
        tmp = folder / f".{f.name}.part"
        shutil.copyfile(f, tmp)
        tmp.rename(folder / f.name)


def monotonic_deadline(timeout_s: float) -> float:
    return time.monotonic() + timeout_s
