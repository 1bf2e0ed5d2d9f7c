"""``oarmreg demo``: the whole loop on mock hardware, end to end, over real sockets.

1. a mock Stäubli controller speaks simple_message on loopback (robot holding still);
2. the service (uvicorn, random free port, temporary API token) watches ``OUT/watch`` and
   listens for DICOM C-STORE and OpenIGTLink on free loopback ports;
3. the mock O-arm simulates a DICOM scan of the phantom, posed by the mock robot's forward
   kinematics and a hidden ``image_from_robot``, and pushes it by C-STORE (pynetdicom's SCU,
   as the O-arm's "send" does; :mod:`mocks.oarm.cstore`);
4. acting as the navigation UI over HTTP, the demo waits for the scan, calls ``/register``
   and prints the matrix, the quality figures and the TRUE error (the simulator knows the
   hidden transform); an OpenIGTLink client (pyigtl when importable, else the project's own
   :mod:`service.navigation.igtl.wire` decoder on a plain socket) receives ``RobotToImage``;
5. it moves the robot, rescans, calls ``/verify``, prints the error table and saves the
   histogram PNG into ``OUT``.

The robot and the O-arm simulator pose the phantom through the TRUE cell (:mod:`mocks.cell`:
joint origins, zero offsets, rod and sag differ from the nominal ones) while the service believes
the nominal robot and rod, so the verification at the second pose shows the real error of an
uncalibrated cell (it may FAIL its gate, which withdraws the registration: the demo prints that,
with the service's likely cause and action, and still exits 0).  ``--calibrate`` adds a
calibration session through the service and a before / after comparison
(:mod:`service.cli.commands.demo_calibrate`).

Progress goes to stderr; results to stdout.
"""

from __future__ import annotations

import argparse
import secrets
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

from service.cli.commands.demo_report import evidence_line, expected_error_lines, report_withdrawal

if TYPE_CHECKING:
    import numpy as np
    from numpy.typing import NDArray

    from registration.model.kinematics import RobotModel
    from registration.model.phantom import Phantom
    from service.runtime.context import ServiceInputs
    from service.settings import Settings

HELP = "run the whole registration loop on a mock robot and a simulated O-arm (≈ 1–2 min)"

Q1_RAD = (0.0, 0.0, 1.5707963267948966, 0.0, 0.7853981633974483, 0.0)
"""First pose: the mock robot's home (TX60, J3 = 90°, J5 = 45°)."""
Q2_DELTA_RAD = (0.0, 0.10, -0.15, 0.0, 0.15, 0.35)
"""Verification pose: shoulder J2 +5.7°, elbow J3 −8.6°, wrist J5 +8.6°, J6 +20°, so the check
exercises the arm's chain, not the wrist alone (a J6 turn spins the phantom about its own axis and
leaves the shoulder and elbow errors unseen).  Every sphere centre stays inside the scanned volume
(the simulator's cylinder): ≥ 15 mm for the ``demo`` preset, ≥ 6.7 mm for ``small``
(tests/integration/test_demo_verification_pose.py checks it)."""
VERIFICATION_CAVEAT = (
    "  what this shows: the error at ONE pose a few degrees from the registration's (shoulder, elbow and "
    "wrist moved); it does not bound the error elsewhere in the working volume: a calibration's "
    "predicted error does (docs/calibration.md)"
)
MOVE_DURATION_S = 2.0
WINDOW_S = 1.5
"""Stillness window of the demo's service, s."""
TARGET_DISTANCE_MM = 150.0
TRUE_CELL_SEED = 2
"""Seed of the demo's true cell (mocks.cell.TrueCell with :class:`mocks.cell.CellErrorSizes`)."""
SIMULATOR_NOTE = (
    "NOTE: every scan here comes from this project's own O-arm simulator and a simulated 'true' robot "
    "cell (seeded errors of the sizes in mocks/cell.py): the figures test the software against a "
    "hypothesis, they are not clinical accuracy figures."
)
WAIT_SCAN_S = 120.0


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--out", type=Path, default=None, help="output folder (default: a temporary folder)")
    parser.add_argument(
        "--preset", default="demo", help="simulator preset: demo (512×512×132, default), small (fast), oarm"
    )
    parser.add_argument(
        "--calibrate",
        action="store_true",
        help="then plan and scan a calibration session, calibrate through the service, activate, and "
        "compare before / after at a moved O-arm (TRUE errors; adds ≈ 2–3 min)",
    )
    parser.add_argument(
        "--pacs",
        metavar="AE@HOST:PORT",
        default=None,
        help="archive each registration's DICOM Spatial Registration object to this PACS by C-STORE "
        "(or set OARMREG_PACS__HOST, OARMREG_PACS__PORT, OARMREG_PACS__AE_TITLE); without one the demo "
        "archives nothing",
    )


def pacs_overrides(spec: str | None) -> dict[str, Any]:
    """``--pacs AE@HOST:PORT`` as ``load_settings`` overrides (none without the flag)."""
    from service.cli.commands.argtypes import parse_ae_address

    if spec is None:
        return {}
    parsed = parse_ae_address(spec)
    if parsed is None:
        from registration.errors import ConfigError

        raise ConfigError(f"--pacs {spec!r}: expected AE@HOST:PORT, e.g. ORTHANC@127.0.0.1:4242")
    return {"pacs.ae_title": parsed[0], "pacs.host": parsed[1], "pacs.port": parsed[2]}


def _err(msg: str) -> None:
    sys.stderr.write(msg + "\n")
    sys.stderr.flush()


def _out(msg: str = "") -> None:
    sys.stdout.write(msg + "\n")
    sys.stdout.flush()


class _Progress:
    def __init__(self, label: str) -> None:
        self.label = label
        self.t0 = time.perf_counter()
        self.last = -1

    def __call__(self, fraction: float) -> None:
        pct = int(fraction * 100)
        if pct // 10 != self.last // 10 or pct == 100:
            self.last = pct
            sys.stderr.write(f"\r  {self.label}: {pct:3d} %  ({time.perf_counter() - self.t0:.0f} s)")
            sys.stderr.flush()
            if pct >= 100:
                sys.stderr.write("\n")


def _fmt_matrix(m: Any) -> str:
    return "\n".join("    [" + ", ".join(f"{v:12.6f}" for v in row) + "]" for row in m)


def _wait_scan(client: Any, uid: str, deadline_s: float) -> dict[str, Any]:
    """The scan record once the service holds it complete, with the joints captured for it."""
    import threading

    ev = threading.Event()
    end = time.monotonic() + deadline_s
    while time.monotonic() < end:
        r = client.get("/scans")
        r.raise_for_status()
        for s in r.json():
            if s["series_uid"] != uid:
                continue
            if s["status"] == "complete" and s["joints"] is not None:
                return s  # type: ignore[no-any-return]
            if s["status"] == "invalid":
                from registration.errors import DicomSeriesError

                raise DicomSeriesError(f"the service refused series {uid}: {s['reason']}")
        ev.wait(0.2)
    from registration.errors import DicomSeriesError

    raise DicomSeriesError(
        f"the service did not record series {uid} complete with its joints within {deadline_s:g} s"
    )


def _wait_still(client: Any, robot: Any, deadline_s: float = 30.0) -> None:
    import threading

    ev = threading.Event()
    end = time.monotonic() + deadline_s
    settle = robot.motion_end_t_s() + WINDOW_S
    while time.monotonic() < end:
        link = client.get("/status").json()["link"]
        if link["state"] == "connected" and link["history_s"] > WINDOW_S and time.monotonic() > settle:
            return
        ev.wait(0.1)
    from drivers.errors import RobotLinkError

    raise RobotLinkError(f"the mock robot did not settle within {deadline_s:g} s (link {link})")


def _check(r: Any) -> dict[str, Any]:
    if r.status_code >= 400:
        body = r.json()
        from registration.errors import RegistrationError

        raise RegistrationError(
            f"{r.request.method} {r.request.url.path} → {r.status_code}: {body.get('detail')}"
        )
    return r.json()  # type: ignore[no-any-return]


@dataclass
class _Demo:
    """What the two demo steps share."""

    client: Any
    robot: Any
    phantom: Phantom
    model: RobotModel
    tool0_from_phantom: NDArray[np.float64]
    image_from_phantom_1: NDArray[np.float64]
    hidden_image_from_robot: NDArray[np.float64]
    watch: Path
    out: Path
    preset: str
    dicom_port: int = 0
    igtl_port: int = 0
    cell: Any = None
    """The TRUE cell (:class:`mocks.cell.TrueCell`) that really poses the phantom."""
    pacs: str = ""
    """``AE@host:port`` of the PACS the registrations are archived to ("" = none)."""


def _output_dir(out_arg: str | None) -> tuple[Path, tempfile.TemporaryDirectory[str] | None]:
    """The demo's folder (a temporary one without ``--out``); refuses a non-empty watch folder."""
    tmp = None
    if out_arg is None:
        tmp = tempfile.TemporaryDirectory(prefix="oarmreg-demo-")
        out = Path(tmp.name)
    else:
        out = Path(out_arg).resolve()
        out.mkdir(parents=True, exist_ok=True)
    watch = out / "watch"
    if watch.exists() and any(watch.iterdir()):
        from registration.errors import ConfigError

        raise ConfigError(f"{watch} is not empty; pass an empty or new --out folder")
    return out, tmp


def _demo_settings(out: Path, token: str, link_url: str, pacs: dict[str, Any] | None = None) -> Settings:
    from service.settings import load_settings

    return load_settings(
        None,
        {
            "host": "127.0.0.1",
            "port": 0,
            "watch_dir": out / "watch",
            "data_dir": out / "data",
            "api_token": token,
            "robot.link_url": link_url,
            "stillness.window_s": WINDOW_S,
            "watcher.quiet_period_s": 1.0,
            "watcher.poll_interval_s": 0.5,
            "dicom.enabled": True,
            "dicom.port": 0,
            "igtl.enabled": True,
            "igtl.port": 0,
            **(pacs or {}),
        },
    )


def run(args: argparse.Namespace) -> int:
    import httpx

    from mocks.cell import TrueCell
    from mocks.oarm.simulator import demo_pose
    from mocks.robot.robot import ScriptedRobot
    from mocks.robot.runner import run_mock_controller
    from registration.model.frames import invert
    from service.cli.commands.serve import serve_in_thread
    from service.http.app import create_app

    t_start = time.perf_counter()
    pacs = pacs_overrides(getattr(args, "pacs", None))
    out, tmp = _output_dir(args.out)
    token = secrets.token_urlsafe(24)
    try:
        _err(f"oarmreg demo: output in {out}")
        robot = ScriptedRobot(Q1_RAD)
        with run_mock_controller("simple-message", robot) as mock:
            _err(f"  mock Stäubli controller (simple_message) on {mock.url}")
            settings = _demo_settings(out, token, mock.url, pacs)
            app = create_app(settings)
            inputs: ServiceInputs = app.state.inputs
            t0p = settings.robot.tool0_from_phantom.matrix()
            image_from_phantom_1 = demo_pose()
            cell = TrueCell.sample(TRUE_CELL_SEED, inputs.robot_model, t0p)
            hidden = image_from_phantom_1 @ invert(
                cell.robot_from_tool0_true(Q1_RAD) @ cell.tool0_from_phantom
            )
            with (
                serve_in_thread(app, "127.0.0.1", 0) as server,
                httpx.Client(
                    base_url=server.base_url, headers={"Authorization": f"Bearer {token}"}, timeout=300.0
                ) as client,
            ):
                listeners = client.get("/status").json()["listeners"]
                _err(
                    f"  service on {server.base_url} (watching {settings.watch_dir}; DICOM "
                    f"{settings.dicom.ae_title}@127.0.0.1:{listeners['dicom']['port']}, OpenIGTLink "
                    f"127.0.0.1:{listeners['igtl']['port']})"
                )
                demo = _Demo(
                    client=client,
                    robot=robot,
                    phantom=inputs.phantom,
                    model=inputs.robot_model,
                    tool0_from_phantom=t0p,
                    image_from_phantom_1=image_from_phantom_1,
                    hidden_image_from_robot=hidden,
                    watch=settings.watch_dir,
                    out=out,
                    preset=args.preset,
                    dicom_port=int(listeners["dicom"]["port"]),
                    igtl_port=int(listeners["igtl"]["port"]),
                    cell=cell,
                    pacs=str(listeners.get("pacs", {}).get("destination", "")),
                )
                _out(SIMULATOR_NOTE)
                _scan_and_register(demo)
                _move_scan_verify(demo)
                if args.calibrate:
                    from service.cli.commands.demo_calibrate import DemoHooks, run_calibration_demo

                    run_calibration_demo(demo, DemoHooks(_check, _wait_scan, _wait_still))
        _out(f"\ndemo finished in {time.perf_counter() - t_start:.0f} s; service data in {settings.data_dir}")
    finally:
        if tmp is not None:
            tmp.cleanup()
    return 0


def _scan_and_register(d: _Demo) -> None:
    """Scan 1 with the robot still at Q1, then ``POST /register``; report against the hidden truth."""
    import numpy as np

    from mocks.oarm.dicom_export import write_dicom_series
    from mocks.oarm.simulator import AcquisitionSettings, simulate_scan
    from registration.model.frames import apply, rotation_angle_deg

    acq = AcquisitionSettings.preset(d.preset)
    scan1 = simulate_scan(d.phantom, d.image_from_phantom_1, acq, progress=_Progress("O-arm scan 1"))
    _wait_still(d.client, d.robot)
    exp1 = write_dicom_series(scan1, d.out / "oarm-outbox" / "scan-1")
    _send(d, exp1.paths, "scan 1")
    s1 = _wait_scan(d.client, exp1.series_uid, WAIT_SCAN_S)
    _err(f"  scan {s1['id']} recorded ({s1['n_slices']} slices, robot still: {s1['joints']['still']})")
    _err("  POST /register ...")
    t = time.perf_counter()
    reg = _check(d.client.post("/register", json={}))
    dt = time.perf_counter() - t
    m = np.asarray(reg["image_from_robot"])
    _report_registration(
        reg, dt, m, d.hidden_image_from_robot, d.model, d.tool0_from_phantom, apply, rotation_angle_deg
    )
    _report_igtl(d, reg)
    _report_pacs(d, reg)


PACS_WAIT_S = 30.0
"""How long the demo waits for the archive's first outcome (the service keeps retrying after)."""


def _report_pacs(d: _Demo, reg: dict[str, Any]) -> None:
    """Where the registration's SRO went (only with a PACS configured)."""
    import threading

    if not d.pacs:
        return
    tick = threading.Event()
    end = time.monotonic() + PACS_WAIT_S
    exp: dict[str, Any] | None = None
    while time.monotonic() < end:
        exp = d.client.get(f"/registrations/{reg['id']}").json().get("pacs_export")
        if exp is not None and exp["state"] != "pending":
            break
        tick.wait(0.2)
    _out(f"\n== PACS archive of registration {reg['id']} to {d.pacs}")
    if exp is None:
        _out("  not queued (see the service log)")
        return
    status = "" if exp["dimse_status"] is None else f", C-STORE status 0x{exp['dimse_status']:04X}"
    _out(f"  {exp['state']} after {exp['attempts']} attempt(s){status}: {exp['reason'] or '-'}")
    if exp["state"] == "pending":
        _out(f"  (still pending after {PACS_WAIT_S:g} s; the service keeps retrying with back-off)")
    _out(f"  SOP Instance UID {exp['sop_instance_uid'] or '-'}")


def _send(d: _Demo, paths: Any, label: str) -> None:
    """Push the exported slices to the service by C-STORE, as the O-arm would."""
    from mocks.oarm.cstore import send_series

    res = send_series(sorted(paths), "127.0.0.1", d.dicom_port, called_ae="OARMREG")
    bad = [s for s in res.statuses if s != 0]
    _err(
        f"  O-arm C-STORE of {label}: {len(res.statuses)} slices, {res.n_bytes / 1e6:.1f} MB in "
        f"{res.seconds:.2f} s ({res.mb_per_s:.0f} MB/s), {len(bad)} refused; association released"
    )


def _report_igtl(d: _Demo, reg: dict[str, Any]) -> None:
    """Receive ``RobotToImage`` as a Slicer-like client would and compare it with the REST matrix."""
    import numpy as np

    from service.navigation.igtl.probe import receive_transform

    rx = receive_transform("127.0.0.1", d.igtl_port, "RobotToImage", registration_id=str(reg["id"]))
    expected = np.diag([-1.0, -1.0, 1.0, 1.0]) @ np.asarray(reg["image_from_robot"])
    _out(f"\n== OpenIGTLink TRANSFORM 'RobotToImage' received via {rx.via}")
    _out("  matrix (RAS_from_LPS @ image_from_robot: robot mm → image RAS mm):")
    _out(_fmt_matrix(rx.matrix))
    _out(f"  metadata: {dict(sorted(rx.metadata.items()))}")
    _out(
        f"  max |IGTL − diag(-1,-1,1,1)·REST| = {np.abs(rx.matrix - expected).max():.2e} "
        "(float32 on the wire)"
    )


def _move_scan_verify(d: _Demo) -> None:
    """Move the robot, scan 2, ``POST /verify``; save the histogram PNG."""
    import numpy as np

    from mocks.oarm.dicom_export import write_dicom_series
    from mocks.oarm.simulator import AcquisitionSettings, simulate_scan

    q2 = tuple(a + b for a, b in zip(Q1_RAD, Q2_DELTA_RAD, strict=True))
    moved = ", ".join(f"J{j + 1} {np.degrees(v):+.1f}°" for j, v in enumerate(Q2_DELTA_RAD) if v)
    _err(f"  moving the robot to {np.round(q2, 3).tolist()} rad ({moved}) ...")
    d.robot.move_to(q2, MOVE_DURATION_S)
    image_from_phantom_2 = d.cell.image_from_phantom_true(d.hidden_image_from_robot, q2)
    scan2 = simulate_scan(
        d.phantom,
        image_from_phantom_2,
        AcquisitionSettings.preset(d.preset, seed=1),
        progress=_Progress("O-arm scan 2"),
    )
    _wait_still(d.client, d.robot)
    exp2 = write_dicom_series(scan2, d.out / "oarm-outbox" / "scan-2")
    _send(d, exp2.paths, "scan 2")
    s2 = _wait_scan(d.client, exp2.series_uid, WAIT_SCAN_S)
    _err(f"  scan {s2['id']} recorded; POST /verify ...")
    ver = _check(d.client.post("/verify", json={"scan_id": s2["id"]}))
    png_path = d.out / "verification-histogram.png"
    png = d.client.get(ver["histogram_url"])
    png.raise_for_status()
    png_path.write_bytes(png.content)
    _report_verification(ver, png_path)
    if not ver["passed"]:  # on an uncalibrated cell that is the truth, not an error of the demo
        report_withdrawal(d.client, ver)
    else:  # a pass at another pose raises the evidence level
        cur = d.client.get("/registration/current")
        if cur.status_code == 200:
            _out("  " + evidence_line(cur.json()))


def _report_registration(
    reg: dict[str, Any], dt: float, m: Any, truth: Any, model: Any, t0p: Any, apply: Any, rot_deg: Any
) -> None:
    import numpy as np

    _out(f"\n== Registration {reg['id']} ({reg['status']}, {dt:.1f} s) of scan {reg['scan_id']}")
    _out(expected_error_lines(reg))
    _out("image_from_robot (mm; p_image[LPS] = M @ p_robot):")
    _out(_fmt_matrix(m))
    _out("quality figures:")
    _out(
        f"  spheres expected / detected / matched : {reg['n_expected']} / {reg['n_detected']} "
        f"/ {reg['n_matched']}"
    )
    _out(f"  FRE (RMS residual)                    : {reg['fre_mm']:.4f} mm")
    _out(f"  FLE implied by FRE                    : {reg['fle_mm']:.4f} mm")
    tre = reg["predicted_tre_mm"]
    _out(
        f"  one-scan TRE, this pose only, {len(tre)} targets {TARGET_DISTANCE_MM:g} mm away : max "
        f"{max(tre):.4f} mm"
    )
    _out(f"  symmetry margin                       : {reg['symmetry_margin']} spheres")
    _out(f"  det(R)                                : {reg['rotation_det']:.9f}")
    _out(f"  joints_rad                            : {np.round(reg['joints_rad'], 5).tolist()}")
    # true error against the simulator's hidden transform
    rot_err = rot_deg(m[:3, :3] @ truth[:3, :3].T)
    centre = (model.robot_from_tool0(reg["joints_rad"]) @ t0p)[:3, 3]
    dirs = np.vstack(
        [np.eye(3), -np.eye(3), np.array(np.meshgrid([-1, 1], [-1, 1], [-1, 1])).reshape(3, -1).T]
    )
    dirs = dirs / np.linalg.norm(dirs, axis=1, keepdims=True)
    pts = centre + TARGET_DISTANCE_MM * dirs
    errs = np.linalg.norm(apply(m, pts) - apply(truth, pts), axis=1)
    centre_err = float(np.linalg.norm(apply(m, centre) - apply(truth, centre)))
    _out(
        "TRUE error of the matrix (vs the hidden image_from_robot; at this pose the fit absorbs the "
        "cell's errors):"
    )
    _out(f"  rotation error                        : {rot_err:.4f} deg")
    _out(f"  translation error at the phantom centre : {centre_err:.4f} mm")
    _out(
        f"  TRE at {len(pts)} points {TARGET_DISTANCE_MM:g} mm from the phantom : mean {errs.mean():.4f} mm, "
        f"max {errs.max():.4f} mm"
    )


def _report_verification(ver: dict[str, Any], png_path: Path) -> None:
    _out(
        f"\n== Verification {ver['id']} of scan {ver['scan_id']} against registration "
        f"{ver['registration_id']}"
    )
    _out("  sphere      error (mm)")
    for e in sorted(ver["errors"], key=lambda e: e["sphere"]):
        _out(f"  {e['sphere']:<10}  {e['error_mm']:.4f}")
    _out(
        f"  matched {ver['n_matched']}/{ver['n_expected']}: mean {ver['mean_mm']:.4f} mm, RMS "
        f"{ver['rms_mm']:.4f} mm, "
        f"max {ver['max_mm']:.4f} mm → {'PASS' if ver['passed'] else 'FAIL'}"
    )
    _out(VERIFICATION_CAVEAT)
    _out(f"  histogram: {png_path}")
