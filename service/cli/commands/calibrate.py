"""``oarmreg calibrate``: multi-pose calibration of robot, rod and O-arm placement.

``oarmreg calibrate run POSES.json --out CALDIR [--phantom FILE] [--robot tx60|tx2_60|URDF]``
    POSES.json = ``{"robot_model": "tx60", "poses": [{"scan_dir": "pose-01/dicom",
    "joints_rad": [6 floats]}, ...]}`` (``scan_dir`` relative to the file).  Every scan is
    loaded, detected and matched with the nominal model; the calibration writes
    ``CALDIR/robot.urdf`` (corrected joint origins) and ``CALDIR/calibration.json``.

``oarmreg calibrate plan --registration REG.json [--n K] --json OUT``
    Proposes K poses for a session from one registration (its joints are read from the
    registration's provenance, written by ``oarmreg register --joints``, or from ``--joints``).
"""

from __future__ import annotations

import argparse
import hashlib
import json
import math
import sys
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

from registration.io.resources import default_phantom
from service.cli.commands.argtypes import output_dir, output_file
from service.cli.commands.scan_inputs import (
    CALIBRATION_FILE,
    N_JOINTS,
    URDF_FILE,
    add_method_argument,
    detection_params_for_phantom,
    load_calibration,
    poses_file_error,
    read_joints_file,
)

HELP = "calibrate robot geometry, rod and O-arm placement from several scans, or plan the poses"

DEFAULT_PHANTOM = default_phantom()


def add_arguments(parser: argparse.ArgumentParser) -> None:
    sub = parser.add_subparsers(dest="calibrate_command", metavar="ACTION", required=True)
    _add_run_arguments(sub.add_parser("run", help="calibrate from the scans listed in POSES.json"))
    _add_plan_arguments(sub.add_parser("plan", help="propose calibration poses from one registration"))


def _add_run_arguments(run_p: argparse.ArgumentParser) -> None:
    run_p.add_argument("poses", type=Path, metavar="POSES.json")
    run_p.add_argument(
        "--out",
        type=output_dir,
        required=True,
        metavar="CALDIR",
        help="folder for robot.urdf, calibration.json",
    )
    run_p.add_argument(
        "--phantom", type=Path, default=DEFAULT_PHANTOM, help="phantom TOML (default: %(default)s)"
    )
    run_p.add_argument(
        "--robot", help="tx60, tx2_60 or a URDF path (default: POSES.json robot_model, else tx60)"
    )
    run_p.add_argument(
        "--parameter-set",
        choices=("full", "offsets", "hand-eye"),
        default="full",
        help="what to estimate besides rod and O-arm placement (default: %(default)s)",
    )
    run_p.add_argument(
        "--max-condition",
        type=float,
        default=None,
        help="optional extra refusal above this identification condition number (off by default; "
        "Schroer et al. ask < 100); the refusal is on the predicted error over the working volume",
    )
    run_p.add_argument(
        "--drop-weak",
        action="store_true",
        help="fix the robot parameters the poses excite least at nominal until the condition number is "
        "≤ --max-condition (100 if not given), reported as dropped",
    )
    run_p.add_argument(
        "--estimator",
        choices=("ls", "map"),
        default=None,
        help="ls: robust least squares (default); map: priors with a cross-validated weight",
    )
    run_p.add_argument(
        "--max-predicted-error-mm",
        type=float,
        default=None,
        help="refuse when the predicted RMS error at the worst pose of the working volume exceeds this "
        "(default 0.5 mm)",
    )
    run_p.add_argument(
        "--config", type=Path, default=None, help="service TOML ([calibration] target_rms_mm to compare with)"
    )
    add_method_argument(run_p)


def _add_plan_arguments(plan_p: argparse.ArgumentParser) -> None:
    plan_p.add_argument("--registration", type=Path, required=True, metavar="REG.json")
    plan_p.add_argument(
        "--n",
        type=int,
        default=None,
        help="force this number of poses (at least 6); default: the fewest (10 or more) whose predicted RMS "
        "error over the working volume meets calibration.target_rms_mm, at most calibration.max_poses",
    )
    plan_p.add_argument("--json", type=output_file, required=True, metavar="OUT.json")
    plan_p.add_argument(
        "--predict",
        type=Path,
        metavar="POSES.json",
        help="predict for this pose set (a plan's JSON or calibrate run's POSES.json) instead of planning",
    )
    plan_p.add_argument("--config", type=Path, default=None, help="service TOML ([calibration] settings)")
    plan_p.add_argument(
        "--joints",
        type=Path,
        metavar="JOINTS.json",
        help='joints of the registration scan, {"joints_rad": [...]} (default: from REG.json)',
    )
    plan_p.add_argument("--robot", help="tx60, tx2_60 or a URDF path (default: REG.json's, else tx60)")
    plan_p.add_argument("--phantom", type=Path, default=DEFAULT_PHANTOM)
    plan_p.add_argument(
        "--calibration", type=Path, metavar="CALDIR", help="plan with this calibration's model and rod"
    )
    plan_p.add_argument(
        "--fov-radius-mm",
        type=float,
        default=None,
        help="scan FOV radius (default: REG.json's series_geometry, else the O-arm's 106.24 mm)",
    )
    plan_p.add_argument(
        "--half-length-mm",
        type=float,
        default=None,
        help="half the axial coverage (default: REG.json's series_geometry, else the O-arm's 79.97 mm)",
    )
    plan_p.add_argument(
        "--volume-centre-mm",
        metavar="X,Y,Z",
        help="volume centre in the image frame (default: REG.json's series_geometry; without one, the "
        "phantom centre at the registration, with a warning)",
    )
    plan_p.add_argument(
        "--keep-out",
        action="append",
        default=[],
        metavar="NAME:X0,Y0,Z0,X1,Y1,Z1",
        help="a box in the image frame (LPS mm) the arm must stay out of (gantry housing, table); "
        "repeatable; the plan names the poses whose joints, tool0 or phantom come within 50 mm",
    )


def run(args: argparse.Namespace) -> int:
    if args.calibrate_command == "run":
        return run_calibration(args)
    return run_plan(args)


def read_poses_file(path: Path) -> tuple[str | None, list[tuple[str, Path, list[float]]]]:
    """(robot_model, [(name, scan_dir, joints_rad)]) from POSES.json; paths resolved against its folder."""
    from registration.calibration.records import (
        MIN_POSES,
    )
    from registration.io.points import read_json

    obj = read_json(path)
    poses = obj.get("poses") if isinstance(obj, dict) else None
    if not isinstance(poses, list) or not poses:
        raise poses_file_error(
            f'{path}: expected {{"robot_model": ..., '
            '"poses": [{"scan_dir": ..., "joints_rad": [...]}, ...]}'
        )
    out = []
    for i, p in enumerate(poses):
        if not isinstance(p, dict) or "scan_dir" not in p or "joints_rad" not in p:
            raise poses_file_error(f'{path}: poses[{i}] needs "scan_dir" and "joints_rad"')
        joints = p["joints_rad"]
        if (
            not isinstance(joints, list)
            or len(joints) != N_JOINTS
            or not all(isinstance(v, int | float) and not isinstance(v, bool) for v in joints)
            or not all(math.isfinite(v) for v in joints)
        ):
            raise poses_file_error(
                f"{path}: poses[{i}].joints_rad must be {N_JOINTS} finite numbers (radians, J1…J6), "
                f"got {joints!r}"
            )
        out.append(
            (str(p["scan_dir"]), (path.parent / str(p["scan_dir"])).resolve(), [float(v) for v in joints])
        )
    if len(out) < MIN_POSES:
        raise poses_file_error(
            f"{path}: {len(out)} pose(s); a calibration needs at least {MIN_POSES} scans at poses spread "
            "over orientation and the wrist joints (plan them with `oarmreg calibrate plan`)"
        )
    model = obj.get("robot_model")
    return (str(model) if model is not None else None), out


def _detect_pose(scan_dir: Path, joints: list[float], name: str, ctx: dict[str, Any]) -> Any:
    from registration.calibration.solver import match_pose
    from registration.detection import detect_spheres
    from registration.dicom import load_series
    from registration.imaging.scan_geometry import series_geometry
    from registration.model.kinematics import sphere_centres_robot_mm

    volume = load_series(scan_dir)
    ctx.setdefault("geometry", series_geometry(volume))
    det = detect_spheres(volume, ctx["detection"])
    q = ctx["model"].check_joints(joints)
    robot_mm = sphere_centres_robot_mm(ctx["model"], q, ctx["rod"], ctx["phantom"].centres_phantom_mm)
    return match_pose(
        name,
        q,
        det.centres_image_mm,
        robot_mm,
        phantom=ctx["phantom"],
        series_uid=volume.series_uid,
        frame_of_reference_uid=volume.frame_of_reference_uid,
    )


def config_hash(*parts: bytes) -> str:
    h = hashlib.sha256()
    for p in parts:
        h.update(hashlib.sha256(p).digest())
    return h.hexdigest()


def run_calibration(args: argparse.Namespace) -> int:
    import dataclasses

    from registration import __version__
    from registration.calibration.solver import calibrate
    from registration.calibration.urdf import read_chain, write_calibrated_urdf
    from registration.io.points import write_json
    from registration.model.kinematics import RobotModel, default_tool0_from_phantom
    from registration.model.phantom import load_phantom
    from service.settings import load_settings

    robot_name, poses = read_poses_file(args.poses)
    model = RobotModel.load(args.robot or robot_name or "tx60")
    phantom = load_phantom(args.phantom)
    rod = default_tool0_from_phantom()
    from service.registrations.calibration_jobs import calibration_params

    detection = detection_params_for_phantom(phantom, method=args.method)
    ctx: dict[str, Any] = {"model": model, "rod": rod, "phantom": phantom, "detection": detection}
    matched = [_detect_pose(d, q, name, ctx) for name, d, q in poses]
    params = calibration_params(
        parameter_set=args.parameter_set,
        drop_weak=args.drop_weak,
        max_condition=args.max_condition,
        estimator=args.estimator,
        max_predicted_error_mm=args.max_predicted_error_mm,
        target_rms_mm=load_settings(args.config).calibration.target_rms_mm,
    )
    result = calibrate(
        matched,
        read_chain(model.urdf_path),
        rod,
        phantom.centres_phantom_mm,
        params,
        scan_volume=ctx["geometry"].scan_volume(),
    )
    created = datetime.now(UTC).isoformat(timespec="seconds")
    chash = config_hash(
        model.urdf_path.read_bytes(),
        Path(args.phantom).read_bytes(),
        json.dumps(dataclasses.asdict(params), sort_keys=True).encode(),
    )
    cal_id = f"cal-{created.replace(':', '').replace('-', '')[:15]}-{chash[:8]}"
    out: Path = args.out
    out.mkdir(parents=True, exist_ok=True)
    write_calibrated_urdf(
        result.chain,
        out / URDF_FILE,
        comment=f"oarmreg calibration {cal_id} ({created}): {int(result.used.sum())} poses, "
        f"FrameOfReferenceUID {matched[0].frame_of_reference_uid}, leave-one-pose-out mean "
        f"{result.lopo_mean_mm:.3f} mm; corrected joint origins of {model.urdf_path.name} "
        "(zero offsets folded into the origins' rpy)",
    )
    doc = result.to_dict()
    doc["provenance"] = {
        "calibration_id": cal_id,
        "created_utc": created,
        "software": f"oarmreg {__version__}",
        "config_sha256": chash,
        "robot_model": model.name,
        "nominal_urdf": str(model.urdf_path),
        "phantom": phantom.name,
        "params": dataclasses.asdict(params),
        "frame_of_reference_uid": matched[0].frame_of_reference_uid,
        "scans": [
            {"name": m.name, "series_uid": m.series_uid, "scan_dir": str(d), "joints_rad": q}
            for m, (_, d, q) in zip(matched, poses, strict=True)
        ],
    }
    doc["robot_urdf"] = URDF_FILE
    write_json(out / CALIBRATION_FILE, doc)
    sys.stdout.write(summary(doc))
    sys.stdout.write(f"written: {out / URDF_FILE}, {out / CALIBRATION_FILE}\n")
    return 0


def summary(d: dict[str, Any]) -> str:
    ident = d["identification"]
    n_used = sum(p["used"] for p in d["poses"])
    lines = [
        f"calibration {d['provenance']['calibration_id']}: {n_used} of {len(d['poses'])} poses used",
        f"identification: rank {ident['rank']} of {ident['n_parameters']}, "
        f"condition number {_fmt(ident['condition_number'])}",
        f"fit RMS {d['fit_rms_mm']:.3f} mm; "
        f"leave-one-pose-out mean {_fmt(d['leave_one_pose_out_mean_mm'])} mm, "
        f"max {_fmt(d['leave_one_pose_out_max_mm'])} mm "
        f"(TRE estimate {_fmt(d['leave_one_pose_out_tre_rms_mm'])} mm RMS)",
        f"predicted error over the working volume after a one-scan registration (posterior): "
        f"{_fmt(d['predicted_held_out_rms_mm'])} mm RMS"
        + (f", worst pose {_fmt(d['predicted_working']['max_mm'])} mm" if d.get("predicted_working") else "")
        + f"; from leave-one-pose-out: {_fmt(d.get('lopo_predicted_rms_mm'))} mm RMS",
    ]
    if d.get("target_rms_mm") is not None:
        lines.append(
            f"planner's target {d['target_rms_mm']:g} mm RMS over the working volume: "
            + (
                "met"
                if d.get("target_met")
                else "NOT met — add poses (`oarmreg calibrate plan` without --n) and calibrate again"
            )
        )
    if d["outlier_poses"]:
        lines.append(f"outlier poses excluded: {', '.join(d['outlier_poses'])}")
    if d["dropped_parameters"]:
        lines.append(f"parameters not excited by the poses, dropped: {', '.join(d['dropped_parameters'])}")
    return "\n".join(lines) + "\n"


def _fmt(v: float | None) -> str:
    return "n/a" if v is None else f"{v:.3f}"


def _pose_set_joints(path: Path, model: Any) -> Any:
    """(K, 6) joints of a plan's JSON (``poses[].joints_rad``, as ``calibrate plan`` writes) or of a
    ``calibrate run`` POSES.json (the same key beside ``scan_dir``)."""
    import numpy as np

    from registration.io.points import read_json

    obj = read_json(path)
    poses = obj.get("poses") if isinstance(obj, dict) else None
    if not isinstance(poses, list) or not poses:
        raise poses_file_error(
            f'{path}: expected {{"poses": [{{"joints_rad": [6 numbers]}}, ...]}} (a plan or POSES.json)'
        )
    rows = []
    for i, p in enumerate(poses):
        q = p.get("joints_rad") if isinstance(p, dict) else None
        if (
            not isinstance(q, list)
            or len(q) != N_JOINTS
            or not all(isinstance(v, int | float) and not isinstance(v, bool) and math.isfinite(v) for v in q)
        ):
            raise poses_file_error(
                f"{path}: poses[{i}].joints_rad must be {N_JOINTS} finite numbers (rad), got {q!r}"
            )
        rows.append(model.check_joints(q))
    if len(rows) < 6:
        raise poses_file_error(f"{path}: {len(rows)} pose(s); a calibration needs at least 6")
    return np.asarray(rows, dtype=np.float64)


def run_plan(args: argparse.Namespace) -> int:

    from registration.calibration.planner import PlannerParams, plan_poses, predict_plan
    from registration.calibration.urdf import read_chain
    from registration.io.points import read_json, read_registration, write_json
    from registration.model.kinematics import RobotModel, default_tool0_from_phantom
    from registration.model.phantom import load_phantom
    from service.settings import load_settings

    if args.n is not None and args.n < 6:
        raise poses_file_error(f"--n {args.n}: a calibration needs at least 6 poses")
    cal_settings = load_settings(args.config).calibration
    y = read_registration(args.registration)
    reg_doc = read_json(args.registration)
    prov = reg_doc.get("provenance", {}) or {}
    joints = read_joints_file(args.joints)[0] if args.joints else prov.get("joints_rad")
    if not isinstance(joints, list):
        raise poses_file_error(
            f"{args.registration}: no joints_rad in its provenance; register with "
            "`oarmreg register --joints JOINTS.json` or pass --joints JOINTS.json"
        )
    if args.calibration:
        model, rod, _ = load_calibration(args.calibration)
    else:
        model, rod = (
            RobotModel.load(args.robot or prov.get("robot_model") or "tx60"),
            default_tool0_from_phantom(),
        )
    chain = read_chain(model.urdf_path)
    q0 = model.check_joints(joints)
    pts = load_phantom(args.phantom).centres_phantom_mm
    volume, source = _plan_volume(args, reg_doc, y @ chain.robot_from_tool0(q0) @ rod)
    params = PlannerParams(
        n_poses=args.n, target_rms_mm=cal_settings.target_rms_mm, max_poses=cal_settings.max_poses
    )
    volume_doc = {
        "centre_image_mm": list(volume.centre_image_mm),
        "fov_radius_mm": volume.fov_radius_mm,
        "half_length_mm": volume.half_length_mm,
        "axis_image": list(volume.axis_image),
        "from": source,
    }
    if args.predict is not None:
        given = _pose_set_joints(args.predict, model)
        rms, worst = predict_plan(
            y, chain, rod, pts, given, volume=volume, params=params, registration_joints_rad=q0
        )
        met = rms <= params.target_rms_mm
        write_json(
            args.json,
            {
                "robot_model": model.name,
                "registration": str(args.registration),
                "poses_file": str(args.predict),
                "n_poses": len(given),
                "volume": volume_doc,
                "predicted_rms_mm": rms,
                "predicted_error_mm": worst,
                "target_rms_mm": params.target_rms_mm,
                "target_met": met,
            },
        )
        sys.stdout.write(
            f"{len(given)} poses of {args.predict}: predicted error over the working volume {rms:.3f} mm RMS "
            f"(worst pose {worst:.3f} mm) against the target {params.target_rms_mm:g} mm: "
            f"{'met' if met else 'NOT met — plan without --predict to let the planner add poses'}\n"
            f"written: {args.json}\n"
        )
        return 0
    plan = plan_poses(y, chain, rod, pts, q0, volume=volume, params=params)
    doc = {
        "robot_model": model.name,
        "registration": str(args.registration),
        "volume": volume_doc,
        **plan.to_dict(),
    }
    for pose in doc["poses"]:
        pose["joints_deg"] = [round(math.degrees(v), 3) for v in pose["joints_rad"]]
    notes = keep_out_and_travel(args, doc, y, chain, rod, q0, plan.joints_rad)
    write_json(args.json, doc)
    sys.stdout.write(pendant_table(doc["poses"]) + shorter_plans_text(plan) + notes)
    why = {
        "target": f"the fewest meeting the target {params.target_rms_mm:g} mm RMS",
        "max_poses": f"calibration.max_poses; the target {params.target_rms_mm:g} mm is NOT met",
        "candidates": f"every feasible pose; the target {params.target_rms_mm:g} mm is NOT met",
        "forced": "--n",
    }[plan.count_reason]
    sys.stdout.write(
        f"{len(plan.joints_rad)} poses planned ({why}) from {plan.n_candidates} feasible candidates in the "
        f"volume of {source}; predicted identification condition number "
        f"{plan.predicted_condition_number:.1f}, predicted error over the working volume "
        f"{plan.predicted_rms_mm:.3f} mm RMS (worst pose {plan.predicted_error_mm:.3f} mm)\n"
        + (f"{plan.advice}\n" if plan.advice else "")
        + f"written: {args.json}\n"
    )
    return 0


SCAN_MINUTES = (1, 2)
"""Minutes one O-arm scan takes with positioning (the issue-42 walkthrough measured 1–2 min)."""


def pendant_table(poses: list[dict[str, Any]]) -> str:
    """The planned poses in degrees, J1…J6 as the Stäubli pendant shows them (``herej()``: the
    driver converts only deg → rad, docs/calibration.md), one row per pose in scan order."""
    head = (
        "pose " + "".join(f"{f'J{j + 1}':>9}" for j in range(N_JOINTS)) + "   (degrees, as on the pendant)\n"
    )
    rows = [
        f"{k:>4} " + "".join(f"{v:9.2f}" for v in pose["joints_deg"]) + "\n" for k, pose in enumerate(poses)
    ]
    return head + "".join(rows)


def shorter_plans_text(plan: Any) -> str:
    """The scans the plan asks for, their time, and what a shorter plan would be predicted to give."""
    k = len(plan.joints_rad)
    lo, hi = (k + 2) * SCAN_MINUTES[0], (k + 2) * SCAN_MINUTES[1]
    lines = [
        f"scans: {k} calibration poses + 1 registration + 1 verification = {k + 2} "
        f"(about {lo}–{hi} min at {SCAN_MINUTES[0]}–{SCAN_MINUTES[1]} min a scan)\n"
    ]
    lines += [
        f"  with {kk:>2} poses: predicted {rms:.3f} mm RMS over the working volume "
        f"(worst pose {worst:.3f} mm)\n"
        for kk, rms, worst in plan.shorter
    ]
    lines.append(
        f"  with {k:>2} poses (this plan): predicted {plan.predicted_rms_mm:.3f} mm RMS "
        f"(worst pose {plan.predicted_error_mm:.3f} mm)\n"
    )
    return "".join(lines)


def _plan_volume(
    args: argparse.Namespace, reg_doc: dict[str, Any], image_from_phantom: Any
) -> tuple[Any, str]:
    """The scan volume the plan must keep every sphere in, and where it came from: REG.json's
    series_geometry, else the phantom centre at the registration; the flags override each part."""
    import numpy as np

    from registration.calibration.planner import ScanVolume
    from registration.model import frames

    geometry = reg_doc.get("series_geometry")
    if geometry is not None:
        from registration.imaging.scan_geometry import SeriesGeometry

        base = SeriesGeometry.from_dict(geometry).scan_volume()
        source = f"series_geometry of {args.registration}"
    else:
        base = ScanVolume(centre_image_mm=tuple(frames.apply(image_from_phantom, np.zeros(3)).tolist()))
        source = "the phantom centre at the registration (REG.json has no series_geometry)"
        if not args.volume_centre_mm:
            sys.stderr.write(
                f"warning: {args.registration} has no series_geometry (written by `oarmreg register` from a "
                "DICOM series): the volume is assumed centred on the phantom; give --volume-centre-mm or "
                "re-register the scan\n"
            )
    if args.volume_centre_mm:
        c = [float(v) for v in args.volume_centre_mm.split(",")]
        if len(c) != 3:
            raise poses_file_error(f"--volume-centre-mm {args.volume_centre_mm!r}: expected X,Y,Z in mm")
        base = ScanVolume((c[0], c[1], c[2]), base.fov_radius_mm, base.half_length_mm, base.axis_image)
        source = "--volume-centre-mm"
    volume = ScanVolume(
        base.centre_image_mm,
        args.fov_radius_mm if args.fov_radius_mm is not None else base.fov_radius_mm,
        args.half_length_mm if args.half_length_mm is not None else base.half_length_mm,
        base.axis_image,
    )
    return volume, source


def _keep_out_boxes(specs: list[str]) -> list[Any]:
    from registration.calibration.keepout import KeepOutBox

    boxes: list[Any] = []
    for spec in specs:
        name, _, numbers = spec.rpartition(":")
        try:
            v = [float(x) for x in numbers.split(",")]
            if len(v) != 6:
                raise ValueError("expected 6 numbers")
            boxes.append(KeepOutBox(name or f"box{len(boxes) + 1}", (v[0], v[1], v[2]), (v[3], v[4], v[5])))
        except ValueError as e:
            raise poses_file_error(
                f"--keep-out {spec!r}: {e}; give NAME:X0,Y0,Z0,X1,Y1,Z1 (image LPS mm)"
            ) from None
    return boxes


def keep_out_and_travel(
    args: argparse.Namespace, doc: dict[str, Any], y: Any, chain: Any, rod: Any, q0: Any, joints: Any
) -> str:
    """Add the keep-out report (``--keep-out`` boxes) and a short-travel scan order to the plan's
    ``doc``; the lines to print (registration/calibration/keepout.py)."""
    from registration.calibration.keepout import keep_out_report, order_for_short_travel, travel_rad

    lines = []
    boxes = _keep_out_boxes(list(getattr(args, "keep_out", []) or []))
    report = keep_out_report(y, chain, rod, joints, boxes)
    doc["keep_out"] = {
        "boxes": [{"name": b.name, "min_mm": list(b.min_mm), "max_mm": list(b.max_mm)} for b in boxes],
        "poses": [
            {"index": r.index, "clearance_mm": r.clearance_mm, "box": r.box, "point": r.point, "near": r.near}
            for r in report
        ],
    }
    near = [r for r in report if r.near]
    if not boxes:
        lines.append("keep-out: none given (--keep-out NAME:X0,Y0,Z0,X1,Y1,Z1 for the gantry and table)\n")
    elif near:
        lines += [
            f"keep-out: pose {r.index} {r.point} is {r.clearance_mm:.0f} mm from '{r.box}' "
            f"({'INSIDE' if r.clearance_mm < 0 else 'near'}): check it on the pendant before moving\n"
            for r in near
        ]
    else:
        lines.append(f"keep-out: every pose stays > 50 mm from {len(boxes)} box(es)\n")
    order = order_for_short_travel(q0, joints)
    planned, short = travel_rad(q0, joints, list(range(len(joints)))), travel_rad(q0, joints, order)
    doc["short_travel_order"] = {"order": order, "travel_rad": short, "planned_order_travel_rad": planned}
    lines.append(
        f"scan order for short joint travel: {','.join(map(str, order))} "
        f"(sum of the largest joint step per move {short:.2f} rad, planned order {planned:.2f} rad)\n"
    )
    return "".join(lines)
