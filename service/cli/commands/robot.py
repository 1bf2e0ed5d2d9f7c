"""``oarmreg robot``: read the robot's joints, or the phantom's sphere centres in the robot frame.

::

    oarmreg robot joints --link simple-message://192.168.0.254:11002 [--watch] [--json]
    oarmreg robot points --link URL [--config FILE] [--phantom FILE] [--robot-model tx60]
                         [--tool0-from-phantom X Y Z ROLL PITCH YAW | --tool0-from-phantom FILE.json]
                         [--still-window-s 0.5] [--out FILE]

``joints`` prints degrees for humans; ``--json`` prints
``{"joints_rad": [...], "received_at": ISO-8601, "link": URL}`` (one line per
state with ``--watch``, else the first state only).  ``points`` prints the
points-file JSON ``{"spheres_mm": [[x, y, z], ...]}`` (robot frame, phantom
sphere order) plus provenance keys (``joints_rad``, ``received_at``, ``link``,
``robot_model``, ``tool0_from_phantom``), after checking that the robot stood
still for ``--still-window-s``.

``--config`` reads the service TOML (``configs/oarmreg.toml``; all keys optional)::

    phantom_file = "phantoms/bai2018_cube.toml"   # relative to the config file
    [robot]
    link_url = "simple-message://192.168.0.254:11002"
    model = "tx60"                     # or a URDF path
    [robot.tool0_from_phantom]
    translation_mm = [0.0, 0.0, 200.0]
    rpy_deg = [180.0, 0.0, 0.0]        # URDF rpy convention
    [stillness]
    max_deviation_rad = 0.0005
    max_gap_s = 0.25

Command-line flags override the file.
"""

from __future__ import annotations

import argparse
import asyncio
import json
import math
import sys
import time
from pathlib import Path
from typing import Any

from registration.io.resources import default_phantom
from service.cli.commands.argtypes import output_file, positive_float

HELP = "read joint angles from the robot controller, or the sphere centres in the robot frame"

DEFAULT_PHANTOM = default_phantom()
WATCH_PRINT_HZ = 10.0
"""Human-readable --watch output is throttled to this rate (the link runs at 50 Hz)."""


def add_arguments(parser: argparse.ArgumentParser) -> None:
    sub = parser.add_subparsers(dest="robot_command", metavar="{joints,points}", required=True)
    j = sub.add_parser("joints", help="print the current joint angles")
    j.add_argument("--link", required=True, help="link URL, e.g. simple-message://HOST:11002")
    j.add_argument("--watch", action="store_true", help="keep printing until Ctrl-C")
    j.add_argument("--json", action="store_true", help="machine-readable output (radians)")
    j.add_argument(
        "--timeout-s", type=positive_float, default=5.0, help="connect timeout in seconds (default 5)"
    )

    p = sub.add_parser("points", help="print the sphere centres in the robot frame (points-file JSON)")
    p.add_argument("--link", help="link URL (default: [robot] link in --config)")
    p.add_argument("--config", type=Path, help="service TOML (configs/oarmreg.toml)")
    p.add_argument("--phantom", type=Path, help=f"phantom TOML (default {DEFAULT_PHANTOM.name})")
    p.add_argument("--robot-model", help="tx60, tx2_60 or a URDF path (default tx60)")
    p.add_argument(
        "--tool0-from-phantom", nargs="+", metavar="V",
        help="connecting rod: X Y Z ROLL PITCH YAW (mm, deg; URDF rpy) or a JSON file with a 4x4 "
        "matrix (default: 200 mm along tool0 z, rolled 180°)",
    )  # fmt: skip
    p.add_argument(
        "--still-window-s", type=positive_float, help="require the robot still this long (default 0.5)"
    )
    p.add_argument(
        "--max-deviation-rad", type=positive_float, help="stillness threshold (default 0.0005 rad)"
    )
    p.add_argument("--out", type=output_file, help="also write the JSON to this file")
    p.add_argument(
        "--timeout-s", type=positive_float, default=5.0, help="connect timeout in seconds (default 5)"
    )


def run(args: argparse.Namespace) -> int:
    if args.robot_command == "joints":
        return asyncio.run(_joints(args))
    return asyncio.run(_points(args))


# --------------------------------------------------------------------------- joints


def _human(state: Any, health: Any) -> str:
    deg = "  ".join(f"J{i + 1} {math.degrees(v):+9.4f}°" for i, v in enumerate(state.joints_rad))
    return f"{deg}   ({state.received_at.isoformat(timespec='milliseconds')}, {health.state})"


async def _joints(args: argparse.Namespace) -> int:
    from drivers.factory import open_link

    link = open_link(args.link)
    await link.connect(timeout_s=args.timeout_s)
    out = sys.stdout
    try:
        first = link.latest()
        assert first is not None
        if not args.watch:
            out.write((json.dumps(first.to_dict()) if args.json else _human(first, link.health())) + "\n")
            return 0
        last_print = 0.0
        try:
            async for state in link.stream():
                if args.json:
                    out.write(json.dumps(state.to_dict()) + "\n")
                elif state.t_s - last_print >= 1.0 / WATCH_PRINT_HZ:
                    out.write(_human(state, link.health()) + "\n")
                    last_print = state.t_s
                out.flush()
        except (asyncio.CancelledError, BrokenPipeError):
            pass  # Ctrl-C, or the reader of our output went away (| head)
        return 0
    finally:
        await link.close()


# --------------------------------------------------------------------------- points


def _load_config(path: Path | None) -> tuple[dict[str, Any], Path]:
    import tomllib

    from registration.errors import ConfigError

    if path is None:
        return {}, Path.cwd()
    try:
        return tomllib.loads(path.read_text(encoding="utf-8")), path.resolve().parent
    except (OSError, tomllib.TOMLDecodeError) as e:
        raise ConfigError(f"cannot read config {path}: {e}") from None


def _resolve(p: str | Path, base: Path) -> Path:
    p = Path(p)
    if p.is_absolute() or p.exists():
        return p
    return base / p


def _refuse_radians(setting: str, rpy_deg: list[float]) -> None:
    """The settings' radians-in-degrees rule (registration.model.mount_checks) for a rod given here."""
    from registration.errors import ConfigError
    from registration.model.mount_checks import rpy_problems

    problems = rpy_problems(setting, [float(a) for a in rpy_deg])
    if problems:
        raise ConfigError(problems[0])


def _rod(cli: list[str] | None, robot_cfg: dict[str, Any]) -> Any:
    import numpy as np

    from registration.errors import ConfigError
    from registration.model.frames import as_transform, transform_from_xyz_rpy
    from registration.model.kinematics import default_tool0_from_phantom

    if cli:
        if len(cli) == 6:
            try:
                v = [float(x) for x in cli]
            except ValueError:
                raise ConfigError(f"--tool0-from-phantom: expected 6 numbers, got {cli}") from None
            _refuse_radians("--tool0-from-phantom ROLL PITCH YAW", v[3:])
            return transform_from_xyz_rpy(v[:3], v[3:])
        if len(cli) == 1:
            try:
                m = json.loads(Path(cli[0]).read_text(encoding="utf-8"))
            except (OSError, ValueError) as e:
                raise ConfigError(
                    f"--tool0-from-phantom {cli[0]}: cannot read a 4x4 JSON matrix ({e})"
                ) from None
            if isinstance(m, dict):
                m = m.get("tool0_from_phantom", m)
            return as_transform(np.asarray(m, dtype=float), "tool0_from_phantom")
        raise ConfigError("--tool0-from-phantom takes X Y Z ROLL PITCH YAW or one JSON file")
    rod = robot_cfg.get("tool0_from_phantom")
    if isinstance(rod, dict):  # the service schema: translation_mm + rpy_deg
        rpy = rod.get("rpy_deg", [180, 0, 0])
        _refuse_radians("robot.tool0_from_phantom", rpy)
        return transform_from_xyz_rpy(rod.get("translation_mm", [0, 0, 200]), rpy)
    if rod is not None:  # a 4 × 4 matrix
        return as_transform(np.asarray(rod, dtype=float), "tool0_from_phantom")
    return default_tool0_from_phantom()


async def _points(args: argparse.Namespace) -> int:
    import numpy as np

    from drivers.errors import LinkConfigError
    from drivers.factory import open_link
    from registration.errors import JointHistoryIncompleteError, RobotMovedError
    from registration.model.kinematics import RobotModel, sphere_centres_robot_mm
    from registration.model.phantom import load_phantom
    from registration.model.stillness import DEFAULT_MAX_DEVIATION_RAD, DEFAULT_MAX_GAP_S, assess_stillness

    cfg, base = _load_config(args.config)
    robot_cfg = cfg.get("robot", {})
    still_cfg = cfg.get("stillness", {})
    url = args.link or robot_cfg.get("link_url")
    if not url:
        raise LinkConfigError("no robot link: pass --link URL or set [robot] link_url in --config")
    model = RobotModel.load(args.robot_model or robot_cfg.get("model", "tx60"))
    phantom_path = args.phantom or cfg.get("phantom_file") or DEFAULT_PHANTOM
    phantom = load_phantom(_resolve(phantom_path, base))
    rod = _rod(args.tool0_from_phantom, robot_cfg)
    window_s = args.still_window_s if args.still_window_s is not None else 0.5
    max_dev = args.max_deviation_rad or still_cfg.get("max_deviation_rad", DEFAULT_MAX_DEVIATION_RAD)
    max_gap_s = still_cfg.get("max_gap_s", DEFAULT_MAX_GAP_S)

    link = open_link(url)
    await link.connect(timeout_s=args.timeout_s)
    try:
        t0 = time.monotonic()
        if window_s > 0:
            await asyncio.sleep(window_s)  # collect the stillness window (not test synchronisation)
        state = link.latest()
        assert state is not None
        if window_s > 0:
            hist = link.history(t0)
            result = assess_stillness(
                np.array([s.t_s for s in hist]), np.array([s.joints_rad for s in hist]).reshape(-1, 6),
                window_end_t_s=state.t_s, window_s=min(window_s, state.t_s - t0),
                max_deviation_rad=max_dev, max_gap_s=max_gap_s,
            )  # fmt: skip
            if not result.still:
                err = RobotMovedError if result.verdict == "moved" else JointHistoryIncompleteError
                raise err(f"{url}: {result.reason}; hold the robot still and retry")
        # a joint within the wire's rounding of a limit is at the limit (as the service's capture
        # reads it): float32 over simple_message puts J1 = 180° 2.4e-7 rad beyond it
        joints_rad = [
            float(v) for v in model.at_limits(state.joints_rad, link.joint_resolution_rad(state.joints_rad))
        ]
    finally:
        await link.close()

    spheres = sphere_centres_robot_mm(model, joints_rad, rod, phantom.centres_phantom_mm)
    doc = {
        "spheres_mm": spheres.round(6).tolist(),
        "joints_rad": joints_rad,
        "received_at": state.received_at.isoformat(),
        "link": url,
        "robot_model": model.name,
        "tool0_from_phantom": np.asarray(rod).round(9).tolist(),
    }
    text = json.dumps(doc, indent=1)
    if args.out:
        args.out.write_text(text + "\n", encoding="utf-8")
    sys.stdout.write(text + "\n")
    return 0
