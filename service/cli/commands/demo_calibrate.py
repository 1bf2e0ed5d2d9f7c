"""``oarmreg demo --calibrate``: a calibration session through the service, then before / after.

Called by :mod:`service.cli.commands.demo` once its own registration and verification ran (the robot
and the simulated O-arm pose the phantom through the TRUE cell, :class:`mocks.cell.TrueCell`,
while the service believes the nominal robot and rod).

1. plan the poses (:func:`registration.calibration.planner.plan_poses`, its own count) from the current
   registration;
2. move the mock robot to each, scan (one FrameOfReferenceUID), export into the watch folder;
3. ``POST /calibrations`` with those scans, wait for it;
4. move the O-arm (a new hidden ``image_from_robot``, a new FrameOfReferenceUID), scan once at a
   registration pose and once at a verification pose; ``/register`` + ``/verify`` with the
   nominal model (before), ``POST /calibrations/{id}/activate`` (retires it), ``/register`` +
   ``/verify`` again (after);
5. print both side by side with the TRUE errors at held-out poses (the simulator knows the cell).
"""

from __future__ import annotations

import sys
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from registration.model import frames

N_HELD_OUT = 10
CAL_PRESET = {"rows": 200, "columns": 200, "n_slices": 120, "n_views": 120}
"""The ``small`` preset at 200 × 200 × 120 (0.7 × 0.7 × 1 mm), 120 views: detection stays accurate
(FLE ≈ 0.05 mm) at ~5 s per simulated scan; the calibration part uses it for every scan."""
MOVED_OARM_XYZ_RPY = ((8.0, -6.0, 4.0), (2.0, -3.0, 4.0))
"""How far the O-arm is moved after the session (mm, deg), applied to the hidden image_from_robot."""
SESSION_FOR_UID = "1.2.826.0.1.3680043.8.498.1010"
MOVED_FOR_UID = "1.2.826.0.1.3680043.8.498.1011"
WAIT_S = 600.0


@dataclass(frozen=True)
class DemoHooks:
    """demo.py's HTTP helpers (passed in: this module must not import demo.py, which imports it)."""

    check: Callable[[Any], dict[str, Any]]
    wait_scan: Callable[[Any, str, float], dict[str, Any]]
    wait_still: Callable[[Any, Any], None]


def _err(msg: str) -> None:
    sys.stderr.write(msg + "\n")
    sys.stderr.flush()


def _out(msg: str = "") -> None:
    sys.stdout.write(msg + "\n")
    sys.stdout.flush()


def _acq() -> Any:
    from mocks.oarm.simulator import AcquisitionSettings

    return AcquisitionSettings.preset("small", **CAL_PRESET)


def _scan_at(d: Any, h: DemoHooks, q: Any, y_true: Any, name: str, for_uid: str, rng: Any) -> dict[str, Any]:
    """Move, scan through the true cell, export with ``for_uid``, wait until the service records it."""
    from mocks.oarm.dicom_export import write_dicom_series
    from mocks.oarm.simulator import simulate_scan

    d.robot.move_to(tuple(float(v) for v in q), 1.0)
    scan = simulate_scan(d.phantom, d.cell.image_from_phantom_true(y_true, q, rng), _acq())
    h.wait_still(d.client, d.robot)
    staging = d.out / "oarm-outbox" / name
    exp = write_dicom_series(scan, staging, write_truth=False, frame_of_reference_uid=for_uid)
    staging.rename(d.watch / name)
    return h.wait_scan(d.client, exp.series_uid, 120.0)


def _wait_calibration(d: Any, cal_id: int) -> dict[str, Any]:
    ev = threading.Event()
    end = time.monotonic() + WAIT_S
    while time.monotonic() < end:
        cal = d.client.get(f"/calibrations/{cal_id}").json()
        if cal["status"] != "running":
            return cal  # type: ignore[no-any-return]
        ev.wait(0.5)
    from registration.errors import RegistrationError

    raise RegistrationError(f"calibration {cal_id} did not finish within {WAIT_S:g} s")


def _true_errors_mm(d: Any, reg: dict[str, Any], model: Any, rod: Any, y_true: Any, held: Any) -> Any:
    """Per held-out pose: mean sphere-centre distance, registration's chain vs the true cell (mm)."""
    pts = d.phantom.centres_phantom_mm
    y = np.asarray(reg["image_from_robot"])
    return np.array(
        [
            np.linalg.norm(
                frames.apply(y @ model.robot_from_tool0(q) @ rod, pts)
                - frames.apply(d.cell.image_from_phantom_true(y_true, q), pts),
                axis=1,
            ).mean()
            for q in held
        ]
    )


def _plan(d: Any) -> tuple[Any, Any]:
    """K calibration poses from the current registration; held-out candidates at the moved O-arm."""
    from registration.calibration.planner import PlannerParams, ScanVolume, feasible_poses, plan_poses
    from registration.calibration.urdf import read_chain

    acq = _acq()
    volume = ScanVolume(
        fov_radius_mm=acq.fov_radius_mm, half_length_mm=acq.n_slices * acq.slice_spacing_mm / 2
    )
    cur = d.client.get("/registration/current").json()
    if "registration_id" in cur and "image_from_robot" not in cur:  # withdrawn: still the best estimate
        cur = d.client.get(f"/registrations/{cur['registration_id']}").json()
    chain, pts, q0 = read_chain(d.model.urdf_path), d.phantom.centres_phantom_mm, cur["joints_rad"]
    plan = plan_poses(
        np.asarray(cur["image_from_robot"]), chain, d.tool0_from_phantom, pts, q0, volume=volume,
        params=PlannerParams(shift_mm=18.0),
    )  # fmt: skip
    _err(
        f"  planned {len(plan.joints_rad)} calibration poses (the planner's count: predicted "
        f"{plan.predicted_rms_mm:.3f} mm RMS over the working volume, target {plan.target_rms_mm:g} mm "
        f"{'met' if plan.target_met else 'NOT met'}) from {plan.n_candidates} candidates (predicted "
        f"condition number {plan.predicted_condition_number:.0f})"
    )
    y2 = _moved_y(d)
    cand, _, _ = feasible_poses(
        y2, chain, d.tool0_from_phantom, pts, q0, volume=volume,
        params=PlannerParams(tilts_deg=(0.0, 20.0, 40.0), shift_mm=10.0),
    )  # fmt: skip
    return plan.joints_rad, cand


def _moved_y(d: Any) -> Any:
    xyz, rpy = MOVED_OARM_XYZ_RPY
    return frames.transform_from_xyz_rpy(list(xyz), list(rpy)) @ d.hidden_image_from_robot


def run_calibration_demo(d: Any, h: DemoHooks) -> None:
    """The ``--calibrate`` part (see the module docstring); ``d`` is demo.py's ``_Demo``."""
    t0 = time.perf_counter()
    rng = np.random.default_rng(10)
    _err("\n== Calibration session: the service calibrates robot, rod and O-arm placement")
    poses, cand = _plan(d)
    ids = []
    for i, q in enumerate(poses, start=1):
        s = _scan_at(d, h, q, d.hidden_image_from_robot, f"cal-{i:02d}", SESSION_FOR_UID, rng)
        ids.append(int(s["id"]))
        _err(
            f"  calibration scan {i}/{len(poses)}: scan {s['id']} recorded ({time.perf_counter() - t0:.0f} s)"
        )
    # the service's defaults (the demo and POST /calibrations use the same ones)
    r = h.check(d.client.post("/calibrations", json={"scan_ids": ids}))
    _err(f"  POST /calibrations → calibration {r['id']} running ...")
    cal = _wait_calibration(d, int(r["id"]))
    if cal["status"] != "done":
        from registration.errors import RegistrationError

        raise RegistrationError(f"calibration {cal['id']} refused: {cal['reason']}")
    _report_calibration(cal)
    urdf = d.out / f"calibration-{cal['id']}.urdf"
    urdf.write_text(d.client.get(cal["urdf_url"]).text, encoding="utf-8")
    _before_after(d, h, cal, urdf, cand, rng, t0)


def _report_calibration(cal: dict[str, Any]) -> None:
    used = sum(p["used"] for p in cal["poses"])
    _out(f"\n== Calibration {cal['id']} ({cal['status']}, {cal['duration_s']:.1f} s): {used} poses used")
    _out(
        f"  fit RMS {cal['fit_rms_mm']:.3f} mm; leave-one-pose-out mean "
        f"{cal['leave_one_pose_out_mean_mm']:.3f} mm"
    )
    target = cal.get("target_rms_mm")
    met = (
        ""
        if target is None
        else f" (planner's target {target:g} mm: {'met' if cal.get('target_met') else 'NOT met'})"
    )
    _out(
        "  predicted error at unseen poses after a one-scan registration: "
        f"{cal['predicted_held_out_rms_mm']:.3f} mm RMS{met}"
    )
    if cal["dropped_parameters"]:
        _out(f"  not excited by the poses, dropped: {', '.join(cal['dropped_parameters'])}")
    _out(f"  calibration hash {cal['calibration_hash'][:16]}…")


def _register_and_verify(
    d: Any, h: DemoHooks, scan_id: int, ver_scan_id: int
) -> tuple[dict[str, Any], dict[str, Any]]:
    from service.cli.commands.demo_report import expected_error_lines, report_withdrawal

    reg = h.check(d.client.post("/register", json={"scan_id": scan_id}))
    _out(f"\n== Registration {reg['id']} of scan {scan_id}: {expected_error_lines(reg)}")
    ver = h.check(d.client.post("/verify", json={"scan_id": ver_scan_id}))
    _out(
        f"  verification {ver['id']} of scan {ver_scan_id}: max {ver['max_mm']:.3f} mm → "
        f"{'PASS' if ver['passed'] else 'FAIL'}"
    )
    if not ver["passed"]:
        report_withdrawal(d.client, ver)
    return reg, ver


def _before_after(
    d: Any, h: DemoHooks, cal: dict[str, Any], urdf: Path, cand: Any, rng: Any, t0: float
) -> None:
    from registration.model.kinematics import RobotModel

    y2 = _moved_y(d)
    idx = np.linspace(0, len(cand) - 1, N_HELD_OUT + 2).round().astype(int)
    q_reg, q_ver, held = cand[idx[0]], cand[idx[-1]], cand[idx[1:-1]]
    _err("  the O-arm is moved (new placement, new FrameOfReferenceUID); registration + verification scans")
    s_reg = _scan_at(d, h, q_reg, y2, "moved-register", MOVED_FOR_UID, rng)
    s_ver = _scan_at(d, h, q_ver, y2, "moved-verify", MOVED_FOR_UID, rng)
    reg_nom, ver_nom = _register_and_verify(d, h, int(s_reg["id"]), int(s_ver["id"]))
    act = h.check(
        d.client.post(f"/calibrations/{cal['id']}/activate", json={"force": True})  # retires reg_nom
    )
    retired = d.client.get(f"/registrations/{reg_nom['id']}").json()["status"]
    _err(f"  calibration {act['id']} activated: registration {reg_nom['id']} is now {retired}")
    reg_cal, ver_cal = _register_and_verify(d, h, int(s_reg["id"]), int(s_ver["id"]))
    assert reg_cal["provenance"]["calibration"]["calibration_id"] == cal["id"]
    nom = _true_errors_mm(d, reg_nom, d.model, d.tool0_from_phantom, y2, held)
    cal_model = RobotModel.load(urdf)
    calib = _true_errors_mm(d, reg_cal, cal_model, np.asarray(cal["tool0_from_phantom"]), y2, held)
    _out(
        f"\n== Before / after calibration, O-arm moved; registration scan {s_reg['id']}, "
        f"verification scan {s_ver['id']}"
    )
    _out(f"  {'':44s} {'nominal model':>16s} {'calibrated':>16s}")
    _out(f"  {'registration':44s} {reg_nom['id']:>16d} {reg_cal['id']:>16d}")
    _out(f"  {'FRE (mm)':44s} {reg_nom['fre_mm']:>16.3f} {reg_cal['fre_mm']:>16.3f}")
    for label, key in (("/verify mean (mm)", "mean_mm"), ("/verify max (mm)", "max_mm")):
        _out(f"  {label:44s} {ver_nom[key]:>16.3f} {ver_cal[key]:>16.3f}")
    gates = ("PASS" if ver_nom["passed"] else "FAIL", "PASS" if ver_cal["passed"] else "FAIL")
    _out(f"  {'/verify gate':44s} {gates[0]:>16s} {gates[1]:>16s}")
    label = f"TRUE error, {len(held)} held-out poses, mean (mm)"
    _out(f"  {label:44s} {nom.mean():>16.3f} {calib.mean():>16.3f}")
    _out(
        f"  {f'TRUE error, {len(held)} held-out poses, max (mm)':44s} {nom.max():>16.3f} {calib.max():>16.3f}"
    )
    _out("  (TRUE = mean sphere-centre distance, registration + model + rod vs the simulator's hidden cell)")
    _out(f"  calibration part: {time.perf_counter() - t0:.0f} s")
