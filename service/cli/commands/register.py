"""``oarmreg register``: DICOM series (or image points) + robot points → ``image_from_robot``."""

from __future__ import annotations

import argparse
import sys
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

from service.cli.commands.argtypes import (
    float_below,
    output_file,
    positive_float,
    positive_int,
    renamed,
)
from service.cli.commands.scan_inputs import (
    add_common_image_arguments,
    add_joints_arguments,
    load_image_points,
    robot_points,
    write_refusal,
)
from service.errors import UsageError

HELP = "register a scan to the robot: detect spheres, match them to the robot points, fit image_from_robot"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    add_common_image_arguments(parser)
    add_joints_arguments(parser)
    parser.add_argument(
        "--targets-robot",
        type=Path,
        metavar="FILE.json",
        help='targets in the ROBOT frame for the predicted TRE, {"targets_robot_mm": [[x, y, z], ...]} '
        "(default: 6 points quality.default_target_distance_mm from the phantom centre, as the service)",
    )
    parser.add_argument(
        "--targets",
        type=renamed("--targets-robot", 'robot-frame targets, file key "targets_robot_mm"'),
        help=argparse.SUPPRESS,
    )
    parser.add_argument(
        "--prior-rotation",
        type=prior_rotation_arg,
        metavar="RX,RY,RZ|FILE.json",
        help="expected rotation of image_from_robot: roll,pitch,yaw in degrees (URDF xyz convention) or a "
        'JSON file with "image_from_robot" (4 × 4) or "rotation" (3 × 3)',
    )
    parser.add_argument(
        "--prior-tolerance-deg",
        type=float_below(45.0),
        default=30.0,
        help="discard poses further than this from the prior (must be < 45; default 30)",
    )
    parser.add_argument(
        "--phantom-confirmed",
        action="store_true",
        help="the phantom file is the phantom scanned: register even when far more spheres are "
        "detected than it has, or the best pose explains a small share of them",
    )
    parser.add_argument(
        "--prereg",
        metavar="R:I,R:I,R:I,R:I",
        help="paper pre-registration: 4 pairs robot sphere index : image point index (non-coplanar)",
    )
    parser.add_argument(
        "--config",
        type=Path,
        default=None,
        help="service TOML settings file: its [quality] gates and default_target_distance_mm and its "
        "[detection] method and use_mar, as the service uses them; flags override it (default: the "
        "built-in defaults and OARMREG_* environment)",
    )
    parser.add_argument("--max-fre-mm", type=positive_float, help="override the FRE gate (mm, > 0)")
    parser.add_argument(
        "--min-margin", type=positive_int, help="override the symmetry margin (matched spheres, ≥ 1)"
    )
    parser.add_argument(
        "--sro",
        type=output_file,
        metavar="OUT.dcm",
        help="also write the DICOM Spatial Registration object (needs DICOM_DIR; not written on refusal)",
    )
    parser.add_argument(
        "--robot-frame-uid",
        help="Frame of Reference UID of the robot base frame for --sro (default: the one stored in --data, "
        "minted on first use)",
    )
    parser.add_argument(
        "--data",
        type=Path,
        default=None,
        help="service data folder holding the robot frame UID (with --sro, give it or --robot-frame-uid)",
    )


def prior_rotation_arg(text: str) -> str:
    """argparse type of ``--prior-rotation``: parse it now so a bad value names the flag (exit 2)."""
    from registration.errors import OarmRegError

    try:
        parse_prior(text)
    except OarmRegError as e:
        raise argparse.ArgumentTypeError(str(e).removeprefix(f"--prior-rotation {text!r}: ")) from None
    return text


def parse_prior(text: str | None) -> Any:
    """Rotation (3 × 3) from 'rx,ry,rz' degrees or a JSON file; None if not given."""
    if text is None:
        return None
    import numpy as np

    from registration.errors import PointsFileError
    from registration.io.points import read_json
    from registration.model.frames import transform_from_xyz_rpy

    path = Path(text)
    if path.suffix.lower() == ".json" or path.is_file():
        obj = read_json(path)
        key = "image_from_robot" if isinstance(obj, dict) and "image_from_robot" in obj else "rotation"
        if not isinstance(obj, dict) or key not in obj:
            raise PointsFileError(f'{path}: expected "image_from_robot" (4 × 4) or "rotation" (3 × 3)')
        m = np.asarray(obj[key], dtype=np.float64)
        return m[:3, :3] if m.shape == (4, 4) else m
    try:
        rpy = [float(v) for v in text.split(",")]
    except ValueError:
        rpy = []
    if len(rpy) != 3:
        raise PointsFileError(f"--prior-rotation {text!r}: expected RX,RY,RZ in degrees or a JSON file")
    return transform_from_xyz_rpy([0.0, 0.0, 0.0], rpy)[:3, :3]


def parse_prereg(text: str | None) -> list[tuple[int, int]] | None:
    if text is None:
        return None
    from registration.errors import PointsFileError

    try:
        pairs = [tuple(int(v) for v in item.split(":")) for item in text.split(",")]
    except ValueError:
        pairs = []
    if len(pairs) != 4 or any(len(pr) != 2 for pr in pairs):
        raise PointsFileError(
            f"--prereg {text!r}: expected 4 pairs ROBOT_INDEX:IMAGE_INDEX separated by commas"
        )
    return [(a, b) for a, b in pairs]


def run(args: argparse.Namespace) -> int:
    import dataclasses

    import numpy as np

    from registration import __version__
    from registration.errors import OarmRegError
    from registration.io.points import read_targets, write_json
    from registration.matching.records import params_dict
    from registration.matching.register import register_points
    from registration.model.phantom import load_phantom
    from service.settings import load_settings

    check_sro_arguments(args)
    try:
        timings: dict[str, float] = {}
        provenance: dict[str, Any] = {
            "software": f"oarmreg {__version__}",
            "created_utc": datetime.now(UTC).isoformat(timespec="seconds"),
        }
        robot = robot_points(args, provenance)
        image = load_image_points(args, provenance, timings)
        quality = load_settings(args.config).quality
        params = registration_params(args, quality)
        phantom = None
        if args.phantom and args.phantom.lower() != "none":
            phantom = load_phantom(args.phantom)
            provenance["phantom"] = phantom.name
        if args.targets_robot:
            targets = read_targets(args.targets_robot)
            provenance["targets_source"] = f"given: {args.targets_robot}"
        else:
            targets, provenance["targets_source"] = default_targets(
                robot, phantom, quality.default_target_distance_mm
            )
        provenance["params"] = params_dict(params)
        result = register_points(
            robot,
            np.asarray(image, dtype=np.float64).reshape(-1, 3),
            params=params,
            targets_robot_mm=targets,
            orientation_prior=parse_prior(args.prior_rotation),
            prior_tolerance_deg=args.prior_tolerance_deg,
            prereg_pairs=parse_prereg(args.prereg),
            phantom=phantom,
        )
    except OarmRegError as e:
        write_refusal(args.json, e)
        raise
    result = dataclasses.replace(
        result,
        timings_s={**timings, **result.timings_s},
        provenance={**provenance, **dict(result.provenance)},
    )
    doc = result.to_dict()
    geometry = (doc.get("provenance") or {}).pop("series_geometry", None)
    if geometry is not None:
        doc["series_geometry"] = geometry
    # the chain's figure (calibration posterior or nominal prior), as the service attaches it to every
    # registration: the error to expect at the robot's other working poses
    from registration.calibration.records import chain_error_figure

    cal = (doc.get("provenance") or {}).get("calibration")
    doc["predicted_chain_error_mm"], doc["chain_error_source"] = chain_error_figure(cal)
    if args.json:  # files first: the result must not depend on stdout staying open
        write_json(args.json, doc)
    if getattr(args, "sro", None) is not None:
        write_sro(args, doc)
    sys.stdout.write(summary(doc))
    if args.json:
        sys.stdout.write(f"written: {args.json}\n")
    if getattr(args, "sro", None) is not None:
        sys.stdout.write(f"written: {args.sro} (DICOM Spatial Registration)\n")
    return 0


def registration_params(args: argparse.Namespace, quality: Any) -> Any:
    """The gates of ``[quality]`` (as :func:`service.registrations.orchestrator.pipeline_params`), the flags
    overriding them."""
    from registration.matching.records import RegistrationParams

    overrides: dict[str, Any] = {
        "min_matched": quality.min_matched_spheres,
        "min_runner_up_margin": quality.min_symmetry_margin,
        "max_fre_mm": quality.max_fre_mm,
    }
    if args.max_fre_mm is not None:
        overrides["max_fre_mm"] = args.max_fre_mm
    if args.min_margin is not None:
        overrides["min_runner_up_margin"] = args.min_margin
    if getattr(args, "phantom_confirmed", False):
        overrides["phantom_confirmed"] = True
    return RegistrationParams(**overrides)


def default_targets(robot_mm: Any, phantom: Any, distance_mm: float) -> tuple[Any, str]:
    """The service's default targets (:func:`registration.pipeline.default_targets_robot_mm`): 6 points
    ``distance_mm`` from the phantom centre along the robot axes, and a label saying so.  The
    phantom centre in the robot frame is fitted from the robot points (phantom sphere order); without
    a phantom whose sphere count matches, their centroid."""
    import numpy as np

    from registration.matching.rigid import fit_rigid_unchecked
    from registration.pipeline import default_targets_robot_mm

    robot = np.asarray(robot_mm, dtype=np.float64).reshape(-1, 3)
    if phantom is not None and len(phantom.centres_phantom_mm) == len(robot):
        centre = fit_rigid_unchecked(np.asarray(phantom.centres_phantom_mm, dtype=np.float64), robot)[:3, 3]
        where = "the phantom centre"
    else:
        centre, where = robot.mean(axis=0), "the robot points' centroid"
    label = f"default: 6 points {distance_mm:g} mm from {where} along the robot axes"
    return default_targets_robot_mm(centre, distance_mm), label


def check_sro_arguments(args: argparse.Namespace) -> None:
    """``--sro`` needs the robot frame's UID from somewhere the user named (never a folder made in
    the working directory behind their back)."""
    if getattr(args, "sro", None) is not None and args.robot_frame_uid is None and args.data is None:
        raise UsageError(
            "--sro needs the robot base frame's Frame of Reference UID: give --data DIR (the service's "
            "data folder, which holds it) or --robot-frame-uid UID"
        )


def write_sro(args: argparse.Namespace, doc: dict[str, Any]) -> None:
    """Write the Spatial Registration object of this registration to ``args.sro``.

    Raises
    ------
    PointsFileError
        ``--sro`` without DICOM_DIR (the SRO references the scan's instances).
    RobotFrameUidError
        ``--robot-frame-uid`` is not a DICOM UID, or the stored one is malformed.
    """
    from registration.dicom import list_series
    from registration.dicom.uids import is_dicom_uid
    from registration.errors import PointsFileError
    from registration.io.sro import build_spatial_registration
    from service.errors import RobotFrameUidError
    from service.intake.recording import scan_instances_from_files
    from service.navigation.sro_export import ct_headers
    from service.registrations.robot_frame import robot_frame_uid

    if args.dicom_dir is None:
        raise PointsFileError("--sro needs DICOM_DIR: the Spatial Registration object references the scan")
    uid = args.robot_frame_uid
    if uid is None:
        uid = robot_frame_uid(args.data)  # check_sro_arguments made sure --data is given
    elif not is_dicom_uid(uid):
        raise RobotFrameUidError(f"--robot-frame-uid {uid!r} is not a DICOM UID (digits, dots, ≤ 64 chars)")
    series_uid = str(doc.get("provenance", {}).get("series_uid", ""))
    summary = next(s for s in list_series(args.dicom_dir) if s.series_uid == series_uid)  # headers only
    inst = scan_instances_from_files(series_uid, list(summary.files))
    tre = doc.get("predicted_tre_mm") or []
    ds = build_spatial_registration(
        doc["image_from_robot"],
        ct_headers(inst),
        robot_frame_of_reference_uid=uid,
        fre_mm=float(doc["fre_mm"]),
        status="accepted",
        registration_id="oarmreg register",
        content_datetime=datetime.now(UTC),
        tre_pred_mm=max(tre) if tre else None,
        chain_error_mm=doc.get("predicted_chain_error_mm"),
        software_version=str(doc.get("provenance", {}).get("software", "")),
    )
    ds.save_as(args.sro, enforce_file_format=True)


def summary(d: dict[str, Any]) -> str:
    """Human-readable summary of a registration dict: the honest figure first (the chain's expected
    error at the robot's working poses, and whether a calibration backs it), then the matrix, then the
    one-scan figures labelled as what they are."""
    from service.registrations.evidence import UNVERIFIED_ACTION

    cal = (d.get("provenance") or {}).get("calibration")
    cal_id = cal.get("calibration_id") if isinstance(cal, dict) else None
    lines = [
        f"evidence: CALIBRATED: calibration {cal_id} backs the robot side"
        if cal_id is not None
        else "evidence: UNVERIFIED: one scan cannot see an error in the robot model, rod or mount; "
        f"next: {UNVERIFIED_ACTION}"
    ]
    chain = d.get("predicted_chain_error_mm")
    if chain is not None:
        source = str(d.get("chain_error_source", ""))
        backed = (
            ""
            if source.startswith("calibration") and "posterior" in source
            else "; the cell is NOT calibrated"
        )
        lines.append(
            f"expected error at the robot's working poses: {chain:.3f} mm (predicted_chain_error_mm, {source}"
            f"{backed})"
        )
    lines.append("image_from_robot (p_image = M · p_robot, mm, LPS):")
    for row in d["image_from_robot"]:
        lines.append("  [" + "  ".join(f"{v:12.6f}" for v in row) + "]")
    lines.append(
        f"spheres: {d['n_expected']} expected, {d['n_detected']} detected, {d['n_matched']} matched "
        f"({d['method']})"
    )
    lines.append(
        f"FRE {d['fre_mm']:.3f} mm (RMS residual, not accuracy); implied FLE {d['fle_mm']:.3f} mm; "
        f"max residual {d['max_residual_mm']:.3f} mm"
    )
    tres = d["predicted_tre_mm"]
    if tres:
        where = (d.get("provenance") or {}).get("targets_source", "")
        lines.append(
            f"one-scan TRE, this pose only (Fitzpatrick: this scan's sphere localisation, not the chain's "
            f"error at other poses): max {max(tres):.3f} mm at {len(tres)} targets ({where})"
        )
    for t, tre in zip(d["targets_robot_mm"], tres, strict=True):
        lines.append(f"  one-scan TRE at robot ({t[0]:.1f}, {t[1]:.1f}, {t[2]:.1f}) mm: {tre:.3f} mm")
    ru = d.get("runner_up_rotation_deg")
    ru_txt = (
        f", runner-up {d['runner_up_matched']} matched, {ru:.1f}° away ({d['runner_up_source']})"
        if ru
        else ""
    )
    lines.append(f"symmetry margin {d['symmetry_margin']} spheres{ru_txt}; det(R) = {d['rotation_det']:.9f}")
    if "prereg" in d:
        lines.append(
            f"pre-registration non-rigidity {d['prereg']['nonrigidity']:.2%}, "
            f"rms {d['prereg']['rms_mm']:.3f} mm"
        )
    return "\n".join(lines) + "\n"
