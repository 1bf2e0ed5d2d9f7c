"""``oarmreg detect``: find the phantom's metal spheres in a DICOM series.

Prints a table (index, centre LPS mm, radius, slices, score) and the rejected
candidates with their reasons; ``--overlay PNG`` draws both on the scan
(:mod:`service.registrations.overlay`); ``--json OUT`` writes::

    {"series_uid": ..., "frame": "image", "method": ...,
     "spheres": [{"center_mm": [x, y, z], "radius_mm": r, "n_slices": k, "score": s}, ...],
     "rejected": [{"center_mm": [x, y, z], "reason": ...}, ...],
     "face_offset_mm": β, "face_offset_se_mm": σβ}

With the phantom's spheres paired, each sphere also has ``center_corrected_mm`` (the centre with
the face offset β removed, :mod:`registration.matching.face_offset`); without a pairing
``face_offset_mm`` is null and ``face_offset_reason`` says why.

The centre estimator and sphere size are the phantom file's (``--phantom``, default the built-in
Bai 2018 cube), chosen as the service chooses them, unless ``--method`` / ``--sphere-diameter``
say otherwise.

Exit codes: 0 success, 4 bad input (unreadable / inconsistent series or phantom file, see
:mod:`registration.errors`) and no sphere found (the table and rejections are printed first).
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import TYPE_CHECKING

from registration.io.resources import default_phantom
from service.cli.commands.argtypes import output_file, positive_float
from service.cli.commands.scan_inputs import add_method_argument, detection_params_for_phantom

if TYPE_CHECKING:
    from registration.detection import DetectionResult

DEFAULT_PHANTOM = default_phantom()

HELP = "detect the calibration spheres in an O-arm DICOM series (centres in LPS mm)"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "dicom_dir", metavar="DICOM_DIR", type=Path, help="folder (or DICOMDIR) holding the series"
    )
    parser.add_argument(
        "--json", dest="json_out", metavar="OUT", type=output_file, help="write the result as JSON"
    )
    parser.add_argument(
        "--overlay",
        metavar="PNG",
        type=output_file,
        help="draw the detected centres and the rejected candidates (with their reasons) on a "
        "maximum-intensity projection of the scan",
    )
    parser.add_argument(
        "--phantom",
        type=Path,
        default=DEFAULT_PHANTOM,
        help="phantom TOML: its sphere material chooses the centre estimator and its sphere "
        "diameter the expected size, as the service does (default: %(default)s)",
    )
    add_method_argument(parser)
    parser.add_argument(
        "--sphere-diameter",
        metavar="MM",
        type=positive_float,
        default=None,
        help="sphere diameter in mm instead of the phantom's",
    )
    parser.add_argument("--no-mar", action="store_true", help="skip the polar metal artefact reduction")
    parser.add_argument("--series-uid", metavar="UID", default=None, help="pick this SeriesInstanceUID")


def sphere_fit_columns(radius_mm: float, n_slices: int, score: float) -> tuple[str, str, str]:
    """The table's radius, slices and score, or ``-`` where the estimator did not measure them
    (a NaN radius; no circle slices, whose fraction the score is)."""
    import math

    radius = f"{radius_mm:.3f}" if math.isfinite(radius_mm) else "-"
    if n_slices <= 0:
        return radius, "-", "-"
    return radius, str(n_slices), f"{score:.2f}" if math.isfinite(score) else "-"


def _with_face_offset(result: DetectionResult, phantom_path: Path | None) -> DetectionResult:
    """The detection with the phantom's face offset fitted over its hole grid."""
    from registration.matching.face_offset_grid import grid_face_offset
    from registration.model.phantom import load_phantom

    path = DEFAULT_PHANTOM if phantom_path is None or str(phantom_path).lower() == "none" else phantom_path
    return grid_face_offset(result, load_phantom(path))


def run(args: argparse.Namespace) -> int:
    from registration.detection import detect_spheres
    from registration.dicom import load_series
    from service.error_map import EXIT_INPUT

    overrides: dict[str, object] = {}
    if args.sphere_diameter is not None:
        overrides["sphere_diameter_mm"] = args.sphere_diameter
    if args.no_mar:
        overrides["use_mar"] = False
    params = detection_params_for_phantom(args.phantom, method=args.method, **overrides)

    volume = load_series(args.dicom_dir, series_uid=args.series_uid, unique=True)
    result = detect_spheres(volume, params)
    result = _with_face_offset(result, args.phantom)

    if args.json_out is not None:
        doc = result.to_dict(series_uid=volume.series_uid)
        args.json_out.parent.mkdir(parents=True, exist_ok=True)
        tmp = args.json_out.with_name(f".{args.json_out.name}.part")
        tmp.write_text(json.dumps(doc, indent=2) + "\n")
        tmp.replace(args.json_out)
    if args.overlay is not None:
        from service.registrations.overlay import write_detection_overlay

        write_detection_overlay(volume, result, args.overlay)
    out = sys.stdout
    out.write(
        f"series {volume.series_uid}: {len(result.spheres)} sphere(s), method {result.method}, "
        f"MAR {'on' if params.use_mar else 'off'}, {result.timings_s.get('total_s', 0.0):.3f} s\n"
    )
    out.write(
        f"{'#':>3}  {'x (L) mm':>10} {'y (P) mm':>10} {'z (S) mm':>10}  "
        f"{'radius mm':>9}  {'slices':>6}  {'score':>5}\n"
    )
    unknown = False
    for n, s in enumerate(result.spheres):
        x, y, z = (float(v) for v in s.center_image_mm)
        radius, slices, score = sphere_fit_columns(s.radius_mm, s.n_slices, s.score)
        unknown |= "-" in (radius.strip(), slices.strip(), score.strip())
        out.write(f"{n:>3}  {x:>10.3f} {y:>10.3f} {z:>10.3f}  {radius:>9}  {slices:>6}  {score:>5}\n")
    if unknown:
        out.write(
            f"  (-: not measured by the {result.method} estimator, which fits no circle per slice; "
            "its centres are the result)\n"
        )
    if result.rejections:
        out.write(f"rejected {len(result.rejections)} candidate(s):\n")
        for r in result.rejections:
            x, y, z = r.center_image_mm
            out.write(f"  ({x:.1f}, {y:.1f}, {z:.1f}) mm: {r.reason}\n")
    fo = result.face_offset
    if fo is not None:
        out.write(
            f"face offset β {fo.beta_mm:+.4f} ± {fo.beta_se_mm:.4f} mm along the hole axes "
            "(centres corrected in the JSON; docs/detection-settings.md)\n"
        )
    elif result.face_offset_reason:
        out.write(f"face offset not fitted: {result.face_offset_reason}\n")
    if args.json_out is not None:
        out.write(f"wrote {args.json_out}\n")
    if args.overlay is not None:
        out.write(f"wrote {args.overlay}\n")
    if not result.spheres:  # no empty success
        sys.stderr.write(
            f"oarmreg detect: no sphere found in series {volume.series_uid}: check that this is the phantom "
            "scan and the phantom is inside the O-arm's field (the rejections above say what was seen), "
            "then scan again\n"
        )
        return EXIT_INPUT
    return 0
