"""``oarmreg send DIR --to AE@HOST:PORT``: send a DICOM series by C-STORE, as the O-arm's "send to"
does, to test the service's DICOM listener (or a PACS) from the command line.

One association for the whole folder, released at the end (:func:`mocks.oarm.cstore.send_series`,
the mock O-arm's own push). Every DICOM Part-10 file under DIR is sent (recursively; a DICOMDIR and
files without the 'DICM' marker are skipped and counted).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from service.cli.commands.argtypes import ae_address

HELP = "send a DICOM series by C-STORE (to test the service's DICOM listener), as the O-arm does"
DEFAULT_CALLING_AE = "OARMREG_SEND"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "folder", type=Path, metavar="DIR", help="folder holding the series (searched recursively)"
    )
    parser.add_argument(
        "--to",
        type=ae_address,
        required=True,
        metavar="AE@HOST:PORT",
        help="the receiver: the service's dicom.ae_title, host and dicom.port (e.g. OARMREG@127.0.0.1:11112)",
    )
    parser.add_argument(
        "--aet",
        default=DEFAULT_CALLING_AE,
        help="calling AE title (must be in the service's dicom.allowed_calling_ae_titles when that is set; "
        "default %(default)s)",
    )


def run(args: argparse.Namespace) -> int:
    from mocks.oarm.cstore import dicom_files, send_series
    from registration.errors import DicomSeriesError, InputFileUnreadableError

    folder: Path = args.folder
    if not folder.is_dir():
        raise InputFileUnreadableError(f"{folder}: not a folder; give the folder of the DICOM export")
    files, skipped = dicom_files([folder])
    if not files:
        raise DicomSeriesError(
            f"{folder}: no DICOM Part-10 file ({len(skipped)} other file(s) skipped); "
            "point at the export folder"
        )
    called, host, port = args.to
    res = send_series(files, host, port, called_ae=called, calling_ae=args.aet)
    bad = sorted({s for s in res.statuses if s != 0})
    sys.stdout.write(
        f"sent {len(files)} instance(s) to {called}@{host}:{port} as {args.aet}: {res.n_bytes / 1e6:.1f} MB "
        f"in {res.seconds:.2f} s; {len(res.statuses) - sum(s == 0 for s in res.statuses)} refused"
        + (f"; {len(skipped)} non-DICOM file(s) skipped" if skipped else "")
        + "\n"
    )
    if bad:
        raise DicomSeriesError(
            f"{called}@{host}:{port} refused {sum(s != 0 for s in res.statuses)} of {len(files)} instance(s) "
            f"(C-STORE status {', '.join(f'0x{s:04X}' for s in bad)}); "
            "the service's log and GET /status say why"
        )
    return 0
