"""``oarmreg token``: print a new random API token (``secrets.token_urlsafe(32)``: 43 characters,
256 random bits) for ``api_token`` / ``api_readonly_token``; it passes the strength rule of
:mod:`service.token_strength` by a wide margin."""

from __future__ import annotations

import argparse
import secrets
import sys

HELP = "print a new random API token (for OARMREG_API_TOKEN / OARMREG_API_READONLY_TOKEN)"
TOKEN_BYTES = 32
"""Random bytes of a new token (256 bits; the rule needs about 16)."""


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--env", metavar="NAME", default=None,
        help="print NAME=<token> (e.g. --env OARMREG_API_TOKEN) for an environment file",
    )  # fmt: skip


def run(args: argparse.Namespace) -> int:
    token = secrets.token_urlsafe(TOKEN_BYTES)
    sys.stdout.write((f"{args.env}={token}" if args.env else token) + "\n")
    return 0
