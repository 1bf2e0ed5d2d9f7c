"""``oarmreg verify``: per-sphere errors of a registration on a second scan (paper eq. 10, Figure 7)."""

from __future__ import annotations

import argparse
import sys
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

from service.commands.argtypes import output_file, positive_float
from service.commands.register import add_common_image_arguments, load_image_points, sha256_of, write_refusal

HELP = "verify a registration on a second scan: predicted vs. detected sphere centres, errors and histogram"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    add_common_image_arguments(parser)
    parser.add_argument(
        "--registration",
        type=Path,
        required=True,
        metavar="REG.json",
        help="the `oarmreg register --json` output to verify",
    )
    parser.add_argument(
        "--histogram", type=output_file, metavar="PNG", help="write the error histogram (Figure 7) here"
    )
    parser.add_argument(
        "--gate-mm", type=positive_float, help="pairing gate around each predicted sphere (mm)"
    )


def run(args: argparse.Namespace) -> int:
    import numpy as np

    from registration import __version__
    from registration.errors import OarmRegError
    from registration.io.points import read_points, read_registration, write_json
    from registration.matching.verification import verify_registration

    timings: dict[str, float] = {}
    provenance: dict[str, Any] = {
        "software": f"oarmreg {__version__}",
        "created_utc": datetime.now(UTC).isoformat(timespec="seconds"),
        "registration_file": str(args.registration),
        "robot_points_file": str(args.robot_points),
    }
    try:
        image_from_robot = read_registration(args.registration)
        robot = read_points(args.robot_points)
        provenance["robot_points_sha256"] = sha256_of(args.robot_points)
        image = np.asarray(load_image_points(args, provenance, timings), dtype=np.float64).reshape(-1, 3)
        res = verify_registration(image_from_robot, robot, image, gate_mm=args.gate_mm)
    except OarmRegError as e:
        write_refusal(args.json, e)
        raise
    out = {**res.to_dict(), "timings_s": timings, "provenance": provenance}
    if args.histogram:  # files first: the result must not depend on stdout staying open
        from service.histogram import write_error_histogram

        write_error_histogram(res.errors_mm, args.histogram)
        out["histogram"] = str(args.histogram)
    if args.json:
        write_json(args.json, out)
    sys.stdout.write(
        f"verification: {res.n_expected} expected, {res.n_detected} detected, {res.n_matched} matched "
        f"(gate {res.gate_mm:g} mm)\n"
        f"position error: mean {res.mean_mm:.3f} mm, RMS {res.rms_mm:.3f} mm, p95 {res.p95_mm:.3f} mm, "
        f"max {res.max_mm:.3f} mm\n"
    )
    if args.histogram:
        sys.stdout.write(f"histogram: {args.histogram}\n")
    if args.json:
        sys.stdout.write(f"written: {args.json}\n")
    return 0
