"""``oarmreg verify``: per-sphere errors of a registration on a second scan (paper eq. 10, Figure 7).

PASS when the largest error is at most ``quality.max_verification_error_mm`` (the service's
verification gate, read from ``--config`` and ``OARMREG_*`` as ``oarmreg serve`` reads it;
``--max-error-mm`` overrides it), else FAIL and exit 7 (docs/cli.md), as ``POST /verify`` judges.
``--pairing-gate-mm`` is a different thing: how far from its predicted position a detected sphere
may be to be paired with it.
"""

from __future__ import annotations

import argparse
import sys
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

from service.cli.commands.argtypes import output_file, positive_float, renamed
from service.cli.commands.scan_inputs import (
    add_common_image_arguments,
    add_joints_arguments,
    load_image_points,
    robot_points,
    write_refusal,
)
from service.errors import VerificationFailedError

HELP = "verify a registration on a second scan: predicted vs. detected sphere centres, errors and histogram"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    add_common_image_arguments(parser)
    add_joints_arguments(parser, calibration_default="the one REG.json was registered through, else nominal")
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
        "--pairing-gate-mm",
        type=positive_float,
        help="pairing gate: a detected sphere is paired with a predicted one within this distance (mm; "
        "default: the registration parameters' verify gate). Not the pass/fail limit",
    )
    parser.add_argument(
        "--max-error-mm",
        type=positive_float,
        help="pass/fail limit on the largest error (mm; default: quality.max_verification_error_mm from "
        "--config / OARMREG_*, as the service judges POST /verify)",
    )
    parser.add_argument(
        "--config", type=Path, default=None, help="service TOML settings file (configs/oarmreg.toml)"
    )
    parser.add_argument(
        "--gate-mm",
        type=renamed("--pairing-gate-mm", "the pass/fail limit is --max-error-mm"),
        help=argparse.SUPPRESS,
    )


def pass_limit_mm(args: argparse.Namespace) -> tuple[float, str]:
    """The pass/fail limit and where it came from (``--max-error-mm`` or the settings)."""
    if args.max_error_mm is not None:
        return float(args.max_error_mm), "--max-error-mm"
    from service.settings import load_settings

    settings = load_settings(args.config)
    where = f"quality.max_verification_error_mm ({args.config or 'defaults and OARMREG_* environment'})"
    return float(settings.quality.max_verification_error_mm), where


def calibration_of(registration: Path) -> Path | None:
    """The calibration folder ``registration`` (REG.json) was registered through, if any: verifying
    through another model would judge the wrong chain."""
    from registration.io.points import read_json

    doc = read_json(registration)
    cal = (doc.get("provenance") or {}).get("calibration") if isinstance(doc, dict) else None
    folder = cal.get("dir") if isinstance(cal, dict) else None
    return Path(folder) if isinstance(folder, str) and folder else None


def run(args: argparse.Namespace) -> int:
    import numpy as np

    from registration import __version__
    from registration.errors import OarmRegError
    from registration.io.points import read_registration, write_json
    from registration.matching.verification import verify_registration

    timings: dict[str, float] = {}
    provenance: dict[str, Any] = {
        "software": f"oarmreg {__version__}",
        "created_utc": datetime.now(UTC).isoformat(timespec="seconds"),
        "registration_file": str(args.registration),
    }
    limit_mm, limit_source = pass_limit_mm(args)  # a bad --config: exit 3 before any work
    try:
        image_from_robot = read_registration(args.registration)
        if args.joints is not None and args.calibration is None:
            args.calibration = calibration_of(args.registration)
        robot = robot_points(args, provenance)
        image = np.asarray(load_image_points(args, provenance, timings), dtype=np.float64).reshape(-1, 3)
        res = verify_registration(image_from_robot, robot, image, gate_mm=args.pairing_gate_mm)
    except OarmRegError as e:
        write_refusal(args.json, e)
        raise
    passed = float(res.max_mm) <= limit_mm
    out = {
        **res.to_dict(),
        "passed": passed,
        "max_verification_error_mm": limit_mm,
        "max_verification_error_source": limit_source,
        "timings_s": timings,
        "provenance": provenance,
    }
    if args.histogram:  # files first: the result must not depend on stdout staying open
        from service.registrations.histogram import write_error_histogram

        write_error_histogram(res.errors_mm, args.histogram, gate_mm=limit_mm)
        out["histogram"] = str(args.histogram)
    if args.json:
        write_json(args.json, out)
    sys.stdout.write(
        f"verification: {res.n_expected} expected, {res.n_detected} detected, {res.n_matched} matched "
        f"(pairing gate {res.gate_mm:g} mm)\n"
        f"position error: mean {res.mean_mm:.3f} mm, RMS {res.rms_mm:.3f} mm, p95 {res.p95_mm:.3f} mm, "
        f"max {res.max_mm:.3f} mm\n"
        f"{'PASS' if passed else 'FAIL'}: max {res.max_mm:.3f} mm {'<=' if passed else '>'} "
        f"{limit_mm:g} mm ({limit_source})\n"
    )
    if args.histogram:
        sys.stdout.write(f"histogram: {args.histogram}\n")
    if args.json:
        sys.stdout.write(f"written: {args.json}\n")
    if not passed:
        raise VerificationFailedError(
            f"verification FAILED: max error {res.max_mm:.3f} mm > {limit_mm:g} mm ({limit_source}); do not "
            "use this registration: check the phantom mount and that the O-arm has not moved, rescan and "
            "register again (an uncalibrated cell: calibrate, docs/calibration.md)"
        )
    return 0
