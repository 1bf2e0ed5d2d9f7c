"""``oarmreg restore IN``: put a backup folder (``oarmreg backup``) or a bare database copy (the
service's ``*.recovered-*`` rescue file) back in place.  Refused while a service holds the database;
what it replaces is moved aside as ``*.before-restore-<UTC time>``."""

from __future__ import annotations

import argparse
from pathlib import Path

from service.cli.commands.argtypes import add_data_arguments, db_path_from_args

HELP = "restore the database and calibrations from a backup (the service must be stopped)"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "source", type=Path, metavar="IN", help="backup folder, or a database file to restore"
    )
    add_data_arguments(parser)


def run(args: argparse.Namespace) -> int:
    import sys

    from service.store.backup import restore

    check_source(args.source)
    db_path = db_path_from_args(args)
    moved = restore(args.source, db_path)
    aside = f"; moved aside: {', '.join(str(p) for p in moved)}" if moved else ""
    print(f"restored {args.source} to {db_path}{aside}", file=sys.stdout)  # noqa: T201
    return 0


def check_source(source: Path) -> None:
    """``source`` is there and readable, before anything opens it (SQLite would create a missing
    database file where the user only named one to read).

    Raises
    ------
    ConfigError
        ``source`` does not exist (or is neither a folder nor a file).
    """
    from registration.errors import ConfigError

    if not (source.is_dir() or source.is_file()):
        raise ConfigError(
            f"{source}: no such backup folder or database file; give the folder `oarmreg backup` wrote "
            "(or a *.recovered-* database copy)"
        )
