"""``oarmreg config check [--config FILE]``: validate the settings and show where each one came from.

Loads the settings exactly as ``oarmreg serve`` does (defaults < TOML file < ``OARMREG_*``
environment), then also loads the phantom file and the robot model and parses the robot link URL,
and prints every effective setting with its source: ``default``, ``file``, or ``env NAME``.  The
API token is never printed (only whether it is set, and from where).

Exit codes: 0 valid; 3 a configuration error, the message naming the key (a misspelt key:
``unknown setting 'api.alowed_origins' in FILE``) — the same as ``serve`` would refuse with.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import tomllib
from pathlib import Path
from typing import Any

HELP = "validate the settings (file and OARMREG_* environment); show each effective value and its source"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    sub = parser.add_subparsers(dest="config_action", metavar="ACTION", required=True)
    check = sub.add_parser("check", help=HELP, description=HELP)
    check.add_argument("--config", type=Path, default=None, help="TOML settings file (configs/oarmreg.toml)")
    check.add_argument("--json", action="store_true", help="print the settings and sources as JSON")


def flatten(d: dict[str, Any], prefix: str = "") -> dict[str, Any]:
    """``{"robot": {"model": "tx60"}}`` → ``{"robot.model": "tx60"}`` (lists stay values)."""
    out: dict[str, Any] = {}
    for k, v in d.items():
        key = f"{prefix}{k}"
        if isinstance(v, dict):
            out.update(flatten(v, key + "."))
        else:
            out[key] = v
    return out


def env_source(key: str, environ: dict[str, str]) -> str | None:
    """The environment variable that sets ``key`` (itself, or a parent section as JSON), if any."""
    from service.settings import ENV_PREFIX

    upper = {k.upper(): k for k in environ}
    parts = key.split(".")
    for n in range(len(parts), 0, -1):
        name = ENV_PREFIX + "__".join(parts[:n]).upper()
        if name in upper:
            return upper[name]
    return None


def sources(settings: Any, config_file: Path | None, environ: dict[str, str]) -> list[tuple[str, Any, str]]:
    """(key, effective value, source) for every setting, the token reduced to whether it is set."""
    in_file: dict[str, Any] = {}
    if config_file is not None:
        in_file = flatten(tomllib.loads(config_file.read_text(encoding="utf-8")))
    values = flatten(settings.model_dump(mode="json", exclude={"api_token", "api_readonly_token"}))
    for name in ("api_token", "api_readonly_token"):
        token = getattr(settings, name)
        values[name] = (
            f"<set, {len(token.get_secret_value())} characters>" if token is not None else "<not set>"
        )
    rows = []
    for key in sorted(values, key=lambda k: (k.count("."), k)):
        env = env_source(key, environ)
        if env is not None:
            src = f"env {env}"
        elif key in in_file and not (key.startswith("api_") and key.endswith("token") and in_file[key] == ""):
            src = f"file {config_file}"
        else:
            src = "default"
        rows.append((key, values[key], src))
    return rows


def validate_resources(settings: Any) -> None:
    """What ``serve`` checks at start-up besides the settings themselves: every problem in one
    ConfigError, each naming its key (not only the first found)."""
    from drivers.errors import LinkConfigError
    from drivers.factory import open_link
    from registration.errors import ConfigError
    from registration.model.kinematics import RobotModel
    from registration.model.phantom import load_phantom

    problems = []
    try:
        phantom = load_phantom(settings.phantom_file)
    except ConfigError as e:
        problems.append(f"setting 'phantom_file' ({settings.phantom_file}): {e}")
    else:
        try:
            settings.check_robot_side(phantom.size_mm)
        except ConfigError as e:
            problems.append(str(e))
    try:
        RobotModel.load(settings.robot.model)
    except ConfigError as e:
        problems.append(f"setting 'robot.model' ({settings.robot.model!r}): {e}")
    try:
        open_link(settings.robot.link_url)  # parses the URL and its options; connects nothing
    except LinkConfigError as e:
        problems.append(f"setting 'robot.link_url' ({settings.robot.link_url!r}): {e}")
    if len(problems) == 1:
        raise ConfigError(problems[0])
    if problems:
        raise ConfigError(f"{len(problems)} problems: " + "; ".join(problems))


def run(args: argparse.Namespace) -> int:
    from service.settings import load_settings

    settings = load_settings(args.config)
    validate_resources(settings)
    rows = sources(settings, args.config, dict(os.environ))
    notes = []
    if settings.api.auth == "token" and settings.api_token is None:
        notes.append(
            "api_token is not set: `oarmreg serve` refuses to start until OARMREG_API_TOKEN holds a "
            "random token (`oarmreg token` makes one; or, on a loopback bind, "
            "api.auth = 'none-loopback-only')"
        )
    if args.json:
        doc = {"config_file": str(args.config) if args.config else None, "valid": True, "notes": notes,
               "settings": [{"key": k, "value": v, "source": s} for k, v, s in rows]}  # fmt: skip
        sys.stdout.write(json.dumps(doc, indent=2) + "\n")
        return 0
    width = max(len(k) for k, _, _ in rows)
    out = [f"oarmreg config check: {args.config or 'no file (defaults and environment)'}: valid"]
    out += [f"  {k:<{width}} = {json.dumps(v)}  ({s})" for k, v, s in rows]
    out += [f"note: {n}" for n in notes]
    sys.stdout.write("\n".join(out) + "\n")
    return 0
