"""``oarmreg simulate``: simulate an O-arm scan of the phantom and write a DICOM series + truth.json."""

from __future__ import annotations

import argparse
import math
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

from registration.io.resources import default_phantom
from service.cli.commands.argtypes import output_dir, output_file, positive_float, positive_int
from service.errors import UsageError

HELP = "simulate an O-arm scan of the calibration phantom; write a DICOM CT series and truth.json"

DEFAULT_PHANTOM = default_phantom()
JOINTS = 6
"""Joints of the TX60 / TX2-60 arms the simulated cell models."""


def add_arguments(parser: argparse.ArgumentParser) -> None:
    from mocks.oarm.cbct import CBCT_PRESET_NAMES
    from mocks.oarm.physics import SPHERE_MATERIALS
    from mocks.oarm.simulator import DEMO_POSE_XYZ_RPY, HOLE_MODELS, ORIENTATIONS, PRESET_NAMES

    default_pose = ",".join(f"{v:g}" for v in DEMO_POSE_XYZ_RPY)
    parser.add_argument(
        "--out",
        required=True,
        type=output_dir,
        help="output folder for the series and truth.json (its parent must exist; a non-empty folder is "
        "refused unless --replace)",
    )
    parser.add_argument(
        "--replace",
        action="store_true",
        help="--out holds an earlier simulated series: delete its *.dcm and truth.json first",
    )
    parser.add_argument(
        "--phantom", type=Path, default=DEFAULT_PHANTOM, help="phantom TOML (default: %(default)s)"
    )
    parser.add_argument(
        "--pose",
        default=default_pose,
        help="image_from_phantom as 'tx,ty,tz,rx,ry,rz' (mm, deg; URDF rpy) (default: %(default)s)",
    )
    parser.add_argument(
        "--preset",
        choices=PRESET_NAMES + CBCT_PRESET_NAMES,
        default="demo-realistic",
        help="acquisition preset; *-realistic add kernel scatter (SPR 0.2), light spread and a 0.8 mm "
        "PSF; oarm-cbct (512 x 512 x 192, 391 views), oarm-cbct-roi, cbct-ci are cone-beam (cbct.py); "
        "oarm, demo, small are the gentler legacy presets (default: %(default)s)",
    )
    parser.add_argument(
        "--material",
        choices=SPHERE_MATERIALS,
        default=None,
        help="sphere material, overriding the phantom file's sphere_material",
    )
    parser.add_argument(
        "--hole-model",
        choices=HOLE_MODELS,
        default="tight",
        help="how a sphere sits in the plastic: tight (the plastic fits the sphere) or drilled (a "
        "Ø2.5 x 2.5 mm air cylinder, the sphere seated on its bottom) (default: %(default)s)",
    )
    parser.add_argument(
        "--hole-tolerance-mm",
        type=float,
        default=0.02,
        help="machining tolerance of the hole positions, applied to the true sphere centres "
        "(Bai 2018: ±0.02 mm) (default: %(default)s)",
    )
    parser.add_argument(
        "--scatter-spr", type=float, default=None, help="override the scatter-to-primary ratio (0 = legacy)"
    )
    parser.add_argument("--seed", type=int, default=0, help="noise seed")
    parser.add_argument(
        "--dose", type=positive_float, default=1.0, help="dose factor (multiplies photons per ray)"
    )
    parser.add_argument("--views", type=positive_int, default=None, help="override the number of views")
    parser.add_argument("--slices", type=positive_int, default=None, help="override the number of slices")
    parser.add_argument(
        "--rows", type=positive_int, default=None, help="override the image rows (FOV = rows × pixel)"
    )
    parser.add_argument("--columns", type=positive_int, default=None, help="override the image columns")
    parser.add_argument("--vertebra", action="store_true", help="add a bone block (vertebra) beside the cube")
    parser.add_argument("--rod", action="store_true", help="add the steel connecting rod")
    parser.add_argument(
        "--body", action="store_true", help="surround everything with a water ellipse (patient)"
    )
    parser.add_argument("--metal-free", action="store_true", help="spheres made of plastic (reference scan)")
    parser.add_argument("--reverse-order", action="store_true", help="InstanceNumber runs against z")
    parser.add_argument("--unsigned", action="store_true", help="unsigned pixels, RescaleIntercept -1024")
    parser.add_argument("--bits-stored", type=int, choices=(12, 16), default=16)
    parser.add_argument("--orientation", choices=sorted(ORIENTATIONS), default="axial")
    _add_robot_pose_arguments(parser)
    parser.add_argument(
        "--png",
        type=output_file,
        default=None,
        help="render the slice cutting most spheres: FILE stem + _bone/_soft/_zoom_bone + _window.png",
    )


def _add_robot_pose_arguments(parser: argparse.ArgumentParser) -> None:
    """``--joints``, ``--pose-index``, ``--placement`` and their companions: the phantom posed by joint
    angles through the simulated true cell (calibration from the CLI)."""
    cal = parser.add_argument_group(
        "robot poses (calibration from the CLI, docs/calibration.md)",
        "pose the phantom by joint angles through a simulated TRUE cell (mocks/cell.py: joint origins, "
        "zero offsets, sag and rod off their nominal values, encoder noise) beside a named O-arm "
        "placement; writes joints.json (the joints the controller would report) beside the scan",
    )
    cal.add_argument(
        "--joints",
        metavar="J1,...,J6|FILE.json",
        help='joint angles in radians, as a comma list, a file {"joints_rad": [...]}, or a '
        "`calibrate plan` output / POSES.json with --pose-index (replaces --pose)",
    )
    cal.add_argument(
        "--pose-index",
        type=int,
        default=None,
        metavar="K",
        help='with --joints FILE.json holding "poses": take poses[K] (0-based)',
    )
    cal.add_argument(
        "--placement",
        default=None,
        metavar="NAME",
        help="O-arm placement: scans with the same NAME share the hidden image_from_robot and one "
        "FrameOfReferenceUID (derived from NAME); default 'bench' with --joints, else a new UID per run",
    )
    cal.add_argument("--robot", default="tx60", help="nominal robot model of the cell (default: %(default)s)")
    cal.add_argument(
        "--cell-seed",
        type=int,
        default=None,
        help="seed of the simulated true cell (default: the demo's, mocks/oarm/placement.py)",
    )
    cal.add_argument(
        "--poses",
        type=output_file,
        default=None,
        metavar="POSES.json",
        help="with --joints: add this scan (scan_dir relative to the file, reported joints) to a "
        "`calibrate run` POSES.json, created if missing",
    )


def _overrides(args: argparse.Namespace, base_photons_per_ray: float) -> dict[str, object]:
    """The settings the flags change, for either simulator."""
    overrides: dict[str, object] = {
        "seed": args.seed,
        "photons_per_ray": base_photons_per_ray * args.dose,
        "orientation": args.orientation,
    }
    if args.views:
        overrides["n_views"] = args.views
    if args.slices:
        overrides["n_slices"] = args.slices
    for flag in ("rows", "columns"):
        if getattr(args, flag, None):
            overrides[flag] = getattr(args, flag)
    if args.scatter_spr is not None:
        overrides["scatter_spr"] = args.scatter_spr
    return overrides


SIMULATED_FILES = ("*.dcm", "truth.json", "joints.json")
"""What ``simulate`` writes into ``--out`` (and ``--replace`` deletes)."""


def clear_output_folder(out: Path, *, replace: bool) -> None:
    """Refuse a non-empty ``out`` (its old slices would mix with the new series) unless ``replace``;
    with ``replace``, delete an earlier simulated series, and refuse anything else found there.

    Raises
    ------
    UsageError
        ``out`` holds files and ``replace`` is false, or holds files simulate did not write.
    """
    if not out.is_dir():
        return
    entries = sorted(out.iterdir())
    if not entries:
        return
    if not replace:
        raise UsageError(
            f"--out {out} is not empty ({len(entries)} entries, e.g. {entries[0].name}): new slices would "
            "mix with the old ones; give an empty or new folder, or --replace to delete an earlier "
            "simulated series there"
        )
    ours = {p for pattern in SIMULATED_FILES for p in out.glob(pattern) if p.is_file()}
    others = [p for p in entries if p not in ours]
    if others:
        raise UsageError(
            f"--replace: {out} holds {len(others)} entries simulate did not write (e.g. {others[0].name}); "
            "not deleting them: give another folder"
        )
    for p in ours:
        p.unlink()


def joints_from_argument(text: str, pose_index: int | None) -> list[float]:
    """Six joint angles (rad) from ``--joints``: a comma list, or a JSON file with ``joints_rad``, or
    with ``pose_index`` a file with ``"poses": [{"joints_rad": ...}, ...]``.

    Raises
    ------
    PointsFileError
        Not six finite numbers, a missing file, or ``pose_index`` out of range.
    """
    from registration.errors import PointsFileError
    from registration.io.points import read_json

    path = Path(text)
    if path.suffix.lower() == ".json" or path.is_file():
        obj = read_json(path)
        where = str(path)
        if pose_index is not None:
            poses = obj.get("poses") if isinstance(obj, dict) else None
            if not isinstance(poses, list) or not -len(poses) <= pose_index < len(poses):
                n = len(poses) if isinstance(poses, list) else 0
                raise PointsFileError(f"{path}: --pose-index {pose_index} but the file lists {n} poses")
            obj, where = poses[pose_index], f"{path} poses[{pose_index}]"
        values = obj.get("joints_rad") if isinstance(obj, dict) else None
    else:
        if pose_index is not None:
            raise PointsFileError("--pose-index needs --joints FILE.json")
        where = "--joints"
        try:
            values = [float(v) for v in text.split(",")]
        except ValueError:
            values = None
    if (
        not isinstance(values, list)
        or len(values) != JOINTS
        or not all(isinstance(v, int | float) and not isinstance(v, bool) for v in values)
        or not all(math.isfinite(v) for v in values)
    ):
        raise PointsFileError(
            f"{where}: expected {JOINTS} finite joint angles in radians (J1…J6), "
            f"got {values if values is not None else text!r}"
        )
    return [float(v) for v in values]


def write_joints(out: Path, joints_rad: list[float], robot: str, placement: str, poses: Path | None) -> None:
    """``out/joints.json`` (what `register --joints` reads) and, with ``poses``, its POSES.json entry."""
    import os

    from registration.io.points import read_json, write_json

    write_json(out / "joints.json", {"joints_rad": joints_rad, "robot_model": robot, "placement": placement})
    if poses is None:
        return
    doc = read_json(poses) if poses.is_file() else {"robot_model": robot, "poses": []}
    entries = doc.get("poses") if isinstance(doc, dict) else None
    if not isinstance(entries, list):
        from registration.errors import PointsFileError

        raise PointsFileError(f'{poses}: expected {{"robot_model": ..., "poses": [...]}}; give a new file')
    scan_dir = os.path.relpath(out.resolve(), poses.resolve().parent)
    entries = [e for e in entries if not (isinstance(e, dict) and e.get("scan_dir") == scan_dir)]
    entries.append({"name": out.name, "scan_dir": scan_dir, "joints_rad": joints_rad, "placement": placement})
    write_json(poses, {**doc, "poses": entries})


def run(args: argparse.Namespace) -> int:
    from mocks.oarm.cbct import CBCT_PRESET_NAMES, ConeBeamSettings, simulate_cbct
    from mocks.oarm.dicom_export import write_dicom_series
    from mocks.oarm.simulator import AcquisitionSettings, pose_from_string, simulate_scan, spheres_imaged_at
    from registration.errors import ConfigError
    from registration.model.phantom import load_phantom

    if args.dose <= 0:
        raise ConfigError(f"--dose must be > 0, got {args.dose}")
    clear_output_folder(args.out, replace=args.replace)
    phantom = load_phantom(args.phantom)
    placement = None
    reported: list[float] | None = None
    if args.joints is not None:
        from mocks.oarm.placement import DEFAULT_CELL_SEED, make_placement, reported_joints

        joints = joints_from_argument(args.joints, args.pose_index)
        placement = make_placement(
            args.placement or "bench",
            args.robot,
            DEFAULT_CELL_SEED if args.cell_seed is None else args.cell_seed,
        )
        from registration.model.kinematics import RobotModel

        RobotModel.load(args.robot).check_joints(joints)  # a joint outside its limit: refused here
        rng = np.random.default_rng(args.seed)
        pose = placement.image_from_phantom_true(joints, rng)
        reported = reported_joints(placement, joints, rng)
    else:
        if args.poses is not None or args.pose_index is not None:
            raise UsageError("--poses and --pose-index need --joints")
        pose = pose_from_string(args.pose)
    extras = _scene_extras(args)
    err = sys.stderr
    if args.preset in CBCT_PRESET_NAMES:
        cb = ConeBeamSettings.preset(args.preset)
        cb = ConeBeamSettings.preset(args.preset, **_overrides(args, cb.photons_per_ray))
        err.write(f"simulating {cb.preset_name} {cb.columns}x{cb.rows}x{cb.n_slices}, {cb.n_views} views\n")
        scan = simulate_cbct(phantom, pose, cb, extras)
    else:
        base = AcquisitionSettings.preset(args.preset)
        settings = AcquisitionSettings.preset(args.preset, **_overrides(args, base.photons_per_ray))
        label = f"{settings.preset_name} {settings.columns}x{settings.rows}x{settings.n_slices}"
        last = [-1]
        t0 = time.perf_counter()

        def progress(f: float) -> None:
            pct = int(f * 100) // 5 * 5
            if pct != last[0]:
                last[0] = pct
                err.write(f"\rsimulating {label}: {pct:3d} %  ({time.perf_counter() - t0:5.1f} s)")
                err.flush()

        fully, partly = spheres_imaged_at(phantom, pose, settings, extras)
        if len(fully) == 0:  # refused before the simulation's cost (seconds to minutes)
            return _refuse_empty(len(partly), phantom.n_spheres)
        scan = simulate_scan(phantom, pose, settings, extras, progress=progress)
        err.write("\n")
    if len(scan.sphere_indices) == 0:  # no empty success: nothing is written
        return _refuse_empty(len(scan.partial_indices), phantom.n_spheres)
    for_uid: str | None = None
    if args.placement is not None or placement is not None:
        from mocks.oarm.placement import placement_frame_of_reference_uid

        for_uid = placement_frame_of_reference_uid(args.placement or "bench")
    res = write_dicom_series(
        scan,
        args.out,
        reverse_order=args.reverse_order,
        unsigned=args.unsigned,
        bits_stored=args.bits_stored,
        frame_of_reference_uid=for_uid,
    )
    out = sys.stdout
    if placement is not None and reported is not None:
        write_joints(Path(args.out), reported, args.robot, placement.name, args.poses)
        out.write(f"joints (as the controller reports them): {Path(args.out) / 'joints.json'}\n")
        if args.poses is not None:
            out.write(f"added to {args.poses}\n")
    out.write(f"series {res.series_uid}: {len(res.paths)} files in {Path(args.out).resolve()}\n")
    out.write(f"frame of reference: {res.frame_of_reference_uid}\n")
    out.write(f"truth: {res.truth_path}\n")
    out.write(
        f"spheres fully imaged: {len(scan.sphere_indices)} of {phantom.n_spheres} "
        f"({len(scan.partial_indices)} cut by the edge of the imaged region); "
        f"simulation {scan.timings_s['total_s']:.1f} s, export {res.elapsed_s:.1f} s\n"
    )
    if args.png:
        from mocks.oarm.simulator import render_slice_png

        png = Path(args.png)
        stem = png.with_suffix("")
        k = render_slice_png(scan, f"{stem}_bone_window.png", window="bone")
        render_slice_png(scan, f"{stem}_soft_window.png", k, window="soft")
        render_slice_png(scan, f"{stem}_zoom_bone_window.png", k, window="bone", zoom=3)
        out.write(f"png: {stem}_{{bone,soft,zoom_bone}}_window.png (slice {k})\n")
    return 0


def _refuse_empty(n_cut: int, n_spheres: int) -> int:
    """No empty success: a pose that images no sphere writes nothing and exits 4 with what to do."""
    from service.error_map import EXIT_INPUT

    sys.stderr.write(
        f"oarmreg simulate: this pose images none of the phantom's {n_spheres} spheres "
        f"({n_cut} cut by the edge of the imaged region); nothing written: move the "
        "phantom into the O-arm's field (other --joints, --placement or pose) and simulate again\n"
    )
    return EXIT_INPUT


def _scene_extras(args: argparse.Namespace) -> Any:
    """What the scan holds besides the phantom (``SceneExtras``), from the flags."""
    from mocks.oarm.simulator import SceneExtras

    return SceneExtras(
        vertebra=args.vertebra,
        rod=args.rod,
        body=args.body,
        sphere_material="plastic" if args.metal_free else args.material,
        hole_tolerance_mm=args.hole_tolerance_mm,
        hole_model=args.hole_model,
    )
