"""``oarmreg backup OUT``: copy the database (SQLite online backup, safe while serving) and the
data folders into the new folder OUT, with a manifest of checksums (:mod:`service.store.backup`)."""

from __future__ import annotations

import argparse
import logging

from service.cli.commands.argtypes import add_data_arguments, db_path_from_args

HELP = "back up the database and calibrations into a new folder (safe while the service runs)"

log = logging.getLogger(__name__)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    from service.cli.commands.argtypes import output_dir

    parser.add_argument(
        "out",
        type=output_dir,
        metavar="OUT",
        help="new (or empty) folder for the backup (parent must exist)",
    )
    add_data_arguments(parser)


def run(args: argparse.Namespace) -> int:
    import sys

    from service.store.backup import backup

    manifest = backup(db_path_from_args(args), args.out)
    print(  # noqa: T201
        f"backup written to {args.out}: schema version {manifest['schema_version']}, "
        f"{len(manifest['files'])} files",
        file=sys.stdout,
    )
    return 0
