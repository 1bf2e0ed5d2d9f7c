"""``oarmreg simulate``: simulate an O-arm scan of the phantom and write a DICOM series + truth.json."""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

from registration.io.resources import default_phantom
from service.commands.argtypes import UsageError, output_dir, output_file, positive_float, positive_int

HELP = "simulate an O-arm scan of the calibration phantom; write a DICOM CT series and truth.json"

DEFAULT_PHANTOM = default_phantom()


def add_arguments(parser: argparse.ArgumentParser) -> None:
    from mocks.oarm.cbct import CBCT_PRESET_NAMES
    from mocks.oarm.physics import SPHERE_MATERIALS
    from mocks.oarm.simulator import DEMO_POSE_XYZ_RPY, ORIENTATIONS, PRESET_NAMES

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
    parser.add_argument(
        "--png",
        type=output_file,
        default=None,
        help="render the slice cutting most spheres: FILE stem + _bone/_soft/_zoom_bone + _window.png",
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
    if args.scatter_spr is not None:
        overrides["scatter_spr"] = args.scatter_spr
    return overrides


SIMULATED_FILES = ("*.dcm", "truth.json")
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


def run(args: argparse.Namespace) -> int:
    from mocks.oarm.cbct import CBCT_PRESET_NAMES, ConeBeamSettings, simulate_cbct
    from mocks.oarm.dicom_export import write_dicom_series
    from mocks.oarm.simulator import AcquisitionSettings, SceneExtras, pose_from_string, simulate_scan
    from registration.errors import ConfigError
    from registration.model.phantom import load_phantom

    if args.dose <= 0:
        raise ConfigError(f"--dose must be > 0, got {args.dose}")
    clear_output_folder(args.out, replace=args.replace)
    phantom = load_phantom(args.phantom)
    pose = pose_from_string(args.pose)
    extras = SceneExtras(
        vertebra=args.vertebra,
        rod=args.rod,
        body=args.body,
        sphere_material="plastic" if args.metal_free else args.material,
        hole_tolerance_mm=args.hole_tolerance_mm,
    )
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

        scan = simulate_scan(phantom, pose, settings, extras, progress=progress)
        err.write("\n")
    res = write_dicom_series(
        scan, args.out, reverse_order=args.reverse_order, unsigned=args.unsigned, bits_stored=args.bits_stored
    )
    out = sys.stdout
    out.write(f"series {res.series_uid}: {len(res.paths)} files in {Path(args.out).resolve()}\n")
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
