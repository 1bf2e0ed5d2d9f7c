"""What ``register``, ``verify``, ``calibrate`` and ``detect`` share: where the image-space sphere
centres come from (a scan and its detection settings, or a points file), where the robot-space ones
come from (a points file, or joint angles through a robot model and perhaps a calibration), and the
refusal file.  The commands import these from here, never from each other."""

from __future__ import annotations

import argparse
import hashlib
import math
import time
from pathlib import Path
from typing import TYPE_CHECKING, Any

from registration.detection.estimators import METHODS
from registration.io.resources import default_phantom
from service.cli.commands.argtypes import output_file

if TYPE_CHECKING:  # light at import: `oarmreg detect` must not load the service stack
    from registration.detection import DetectionParams
    from registration.model.phantom import Phantom

DEFAULT_PHANTOM = default_phantom()


N_JOINTS = 6
"""Joints of the Stäubli TX60 / TX2-60 (both URDFs): one angle each per pose."""

JOINTS_KEY = "joints_rad"
"""The one key of a joints file: ``{"joints_rad": [J1, …, J6]}`` in radians."""

CALIBRATION_FILE = "calibration.json"

URDF_FILE = "robot.urdf"


def add_method_argument(parser: argparse.ArgumentParser) -> None:
    """``--method``, the same for every command that detects: an override of the estimator only."""
    parser.add_argument(
        "--method",
        choices=METHODS,
        default=None,
        help="centre estimator instead of the phantom material's (registration.detection."
        "METHOD_FOR_MATERIAL), keeping the material's other detection settings: subvoxel (3-D "
        "intensity-weighted centroid), paper (per-slice Pythagorean depth, Bai 2018), model (a blurred, "
        "saturated ball fitted to the raw voxels), core (saturated core of an opaque sphere: tungsten "
        "carbide) or rays (outline of a streaked sphere: steel, titanium)",
    )


def detection_params_for_phantom(
    phantom: Phantom | str | Path | None, *, method: str | None = None, **overrides: object
) -> DetectionParams:
    """The detection settings every command uses: the phantom's sphere material and diameter
    through :func:`registration.detection.params_for_spheres`, as the service chooses them.

    ``phantom`` is a loaded phantom or its TOML path; None or ``"none"`` means the built-in
    phantom.  ``method`` (a ``--method`` flag) replaces only the centre estimator and keeps the
    material's other settings; ``overrides`` are other
    :class:`~registration.detection.DetectionParams` fields.
    """
    from registration.detection import params_for_spheres
    from registration.model.phantom import Phantom, load_phantom

    if not isinstance(phantom, Phantom):
        phantom = load_phantom(
            DEFAULT_PHANTOM if phantom is None or str(phantom).lower() == "none" else phantom
        )
    if method is not None:
        overrides["method"] = method
    return params_for_spheres(phantom.sphere_material, phantom.sphere_diameter_mm, **overrides)


def add_common_image_arguments(parser: argparse.ArgumentParser) -> None:
    """Arguments shared by ``register`` and ``verify``: where the image-space sphere centres come from."""
    parser.add_argument("dicom_dir", nargs="?", type=Path, help="folder holding the O-arm DICOM series")
    parser.add_argument(
        "--image-points",
        type=Path,
        metavar="FILE.json",
        help='detected centres in the image frame, {"spheres_mm": [[x, y, z], ...]}, instead of DICOM_DIR',
    )
    parser.add_argument("--series-uid", help="SeriesInstanceUID to use when the folder holds several series")
    add_method_argument(parser)
    parser.add_argument(
        "--phantom",
        default=str(DEFAULT_PHANTOM),
        help="phantom TOML: its sphere material and diameter choose the detection settings as the "
        "service does; register also checks its symmetry twins explicitly ('none' skips that check "
        "and detects with the built-in phantom's settings; default: %(default)s)",
    )
    parser.add_argument(
        "--robot-points",
        type=Path,
        required=True,
        metavar="FILE.json",
        help='sphere centres in the robot frame in phantom sphere order, {"spheres_mm": [[x, y, z], ...]}',
    )
    parser.add_argument(
        "--json", type=output_file, metavar="OUT.json", help="write the result (or the refusal) here"
    )


def add_joints_arguments(parser: argparse.ArgumentParser, calibration_default: str = "nominal") -> None:
    """``--joints``/``--calibration``/``--robot`` (``register`` and ``verify``): the robot side from the
    joint angles by forward kinematics instead of ``--robot-points``."""
    for action in parser._actions:
        if action.dest == "robot_points":
            action.required = False
    parser.add_argument(
        "--joints",
        type=Path,
        metavar="JOINTS.json",
        help='joint angles of the scan, {"joints_rad": [...]}: robot points by forward kinematics '
        "(instead of --robot-points)",
    )
    parser.add_argument(
        "--calibration",
        type=Path,
        metavar="CALDIR",
        help="with --joints: use this calibration's robot.urdf and tool0_from_phantom "
        f"(default: {calibration_default})",
    )
    parser.add_argument(
        "--robot", help="with --joints and no --calibration: tx60, tx2_60 or a URDF (default tx60)"
    )


def robot_points(args: argparse.Namespace, provenance: dict[str, Any]) -> Any:
    """The robot-frame sphere centres from ``--robot-points`` or ``--joints`` (exactly one)."""
    from registration.errors import PointsFileError
    from registration.io.points import read_points

    if (args.robot_points is None) == (args.joints is None):
        raise PointsFileError("give either --robot-points FILE.json or --joints JOINTS.json (exactly one)")
    if args.joints is not None:
        return robot_points_from_joints(args, provenance)
    provenance["robot_points_file"] = str(args.robot_points)
    provenance["robot_points_sha256"] = sha256_of(args.robot_points)
    return read_points(args.robot_points)


def sha256_of(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def load_image_points(args: argparse.Namespace, provenance: dict[str, Any], timings: dict[str, float]) -> Any:
    """(M, 3) image-frame centres from ``--image-points`` or by loading + detecting ``dicom_dir``."""
    from registration.errors import PointsFileError
    from registration.io.points import read_points

    if (args.dicom_dir is None) == (args.image_points is None):
        raise PointsFileError("give either DICOM_DIR or --image-points FILE.json (exactly one of them)")
    if args.image_points is not None:
        provenance["image_points_file"] = str(args.image_points)
        provenance["image_points_sha256"] = (
            sha256_of(args.image_points) if args.image_points.is_file() else None
        )
        return read_points(args.image_points, min_points=0)
    from registration.detection import detect_spheres
    from registration.dicom import load_series
    from service.settings import load_settings

    # [detection] from the TOML the service reads (defaults < file < OARMREG_* < --method)
    ds = load_settings(args.config).detection
    method = args.method if args.method is not None else (None if ds.method == "default" else ds.method)
    dparams = detection_params_for_phantom(args.phantom, method=method, use_mar=ds.use_mar)
    t0 = time.perf_counter()
    volume = load_series(args.dicom_dir, series_uid=args.series_uid, unique=True)
    timings["load_s"] = time.perf_counter() - t0
    from registration.imaging.scan_geometry import series_geometry

    # the scan's real volume, for `oarmreg calibrate plan` (moved to the top level by run)
    provenance["series_geometry"] = series_geometry(volume).to_dict()
    t0 = time.perf_counter()
    det = detect_spheres(volume, dparams)
    timings["detect_s"] = time.perf_counter() - t0
    provenance.update(
        {
            "dicom_dir": str(args.dicom_dir),
            "series_uid": volume.series_uid,
            "frame_of_reference_uid": volume.frame_of_reference_uid,
            "detection_method": det.method,
            "n_rejected_detections": len(det.rejections),
        }
    )
    return det.centres_image_mm


def write_refusal(path: Path | None, error: Exception) -> None:
    if path is None:
        return
    from registration.io.points import write_json

    write_json(path, {"refused": True, "reason": str(error), "error": type(error).__name__})


def poses_file_error(msg: str) -> Exception:
    from registration.errors import PosesFileError

    return PosesFileError(msg)


def is_json_number(value: object) -> bool:
    """A JSON number (``true``/``false`` and strings are not angles)."""
    return isinstance(value, int | float) and not isinstance(value, bool)


def read_joints_file(path: Path) -> tuple[list[float], dict[str, Any]]:
    """(J1…J6 in radians, the whole JSON object) of a joints file ``{"joints_rad": [6 numbers]}``.

    Raises
    ------
    PosesFileError
        Not an object, no ``joints_rad`` (a ``joints_deg`` key is named as such: the file needs
        radians), or not 6 finite numbers.
    InputFileUnreadableError
        The file is missing or unreadable (exit 8).
    """
    from registration.io.points import read_json

    obj = read_json(path)
    expected = f'expected {{"{JOINTS_KEY}": [6 numbers]}} (radians, J1…J6)'
    if not isinstance(obj, dict):
        raise poses_file_error(f"{path}: {expected}, found a JSON {type(obj).__name__}")
    if JOINTS_KEY not in obj:
        found = f"found keys {sorted(obj)[:8]}" if obj else "found an empty object"
        fix = (
            f'; the accepted key is "{JOINTS_KEY}" (radians): convert degrees × π/180, '
            "or copy the radians row of `oarmreg calibrate plan`'s output"
            if any("deg" in str(k) for k in obj)
            else f'; the accepted key is "{JOINTS_KEY}"'
        )
        raise poses_file_error(f"{path}: {expected}, {found}{fix}")
    joints = obj[JOINTS_KEY]
    if (
        not isinstance(joints, list)
        or len(joints) != N_JOINTS
        or not all(is_json_number(v) and math.isfinite(v) for v in joints)
    ):
        raise poses_file_error(
            f'{path}: "{JOINTS_KEY}" must be {N_JOINTS} finite JSON numbers (radians, J1…J6), '
            f"got {joints!r}; fix the file"
        )
    return [float(v) for v in joints], obj


def load_calibration(caldir: Path) -> tuple[Any, Any, dict[str, Any]]:
    """(calibrated RobotModel, tool0_from_phantom (4 × 4 mm), calibration.json dict) from CALDIR."""
    import numpy as np

    from registration.errors import ConfigError, NotRigidError
    from registration.io.points import read_json
    from registration.model.frames import as_transform
    from registration.model.kinematics import RobotModel

    path = Path(caldir) / CALIBRATION_FILE
    if not path.is_file():
        raise ConfigError(f"{caldir}: no {CALIBRATION_FILE}; run `oarmreg calibrate run` to create it")
    doc = read_json(path)
    try:
        rod = as_transform(
            np.asarray(doc["tool0_from_phantom"], dtype=np.float64), f"{path}: tool0_from_phantom"
        )
    except (KeyError, TypeError, ValueError, NotRigidError) as e:
        raise ConfigError(f'{path}: needs "tool0_from_phantom" as a rigid 4 × 4 nested list ({e})') from None
    model = RobotModel.load(Path(caldir) / str(doc.get("robot_urdf", URDF_FILE)))
    return model, rod, doc


def robot_points_from_joints(args: argparse.Namespace, provenance: dict[str, Any]) -> Any:
    """Sphere centres (robot frame) for ``oarmreg register --joints [--calibration]``."""
    from registration.model.kinematics import RobotModel, default_tool0_from_phantom, sphere_centres_robot_mm
    from registration.model.phantom import load_phantom

    joints, obj = read_joints_file(args.joints)
    if args.calibration is not None:
        model, rod, doc = load_calibration(args.calibration)
        provenance["calibration"] = {
            "dir": str(args.calibration),
            **{
                k: doc.get("provenance", {}).get(k)
                for k in ("calibration_id", "config_sha256", "created_utc")
            },
            "predicted_chain_error_mm": doc.get("predicted_chain_error_mm"),
        }
    else:
        model = RobotModel.load(args.robot or obj.get("robot_model") or "tx60")
        rod = default_tool0_from_phantom()
        provenance["calibration"] = None
    phantom_path = args.phantom if args.phantom and args.phantom.lower() != "none" else str(DEFAULT_PHANTOM)
    q = model.check_joints(joints)
    provenance.update(
        {
            "joints_rad": [float(v) for v in q],
            "robot_model": model.name,
            "robot_urdf": str(model.urdf_path),
            "tool0_from_phantom": rod.tolist(),
        }
    )
    return sphere_centres_robot_mm(model, q, rod, load_phantom(phantom_path).centres_phantom_mm)
