"""The mock O-arm's DICOM push: send an exported series by C-STORE (pynetdicom's SCU), as the
O-arm's "send to" does, over one association released at the end.

Users send a folder with ``oarmreg send DIR --to AE@HOST:PORT`` (:mod:`service.cli.commands.send`);
``python -m mocks.oarm.cstore HOST PORT FILE_OR_FOLDER... [--aec OARMREG] [--aet OARM_SIM]`` is the
same for the tests and benchmarks.
"""

from __future__ import annotations

import argparse
import socket
import sys
import time
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

from registration.errors import DicomSeriesError


@dataclass(frozen=True)
class SendResult:
    statuses: tuple[int, ...]
    n_bytes: int
    """Bytes of the files sent (their size on disk)."""
    seconds: float
    """From the association request to the release confirmation."""
    released_at_s: float
    """``time.perf_counter()`` when the release was confirmed."""

    @property
    def mb_per_s(self) -> float:
        return self.n_bytes / 1e6 / self.seconds if self.seconds > 0 else float("nan")


def send_series(
    files: Sequence[Path], host: str, port: int, *, called_ae: str = "OARMREG", calling_ae: str = "OARM_SIM"
) -> SendResult:
    """C-STORE every file over one association, then release it.

    Raises
    ------
    DicomSeriesError
        The association was rejected or not established (wrong AE title, peer not allowed, no
        listener), naming the address and AE titles.
    """
    from pydicom import dcmread
    from pydicom.uid import (
        CTImageStorage,
        EnhancedCTImageStorage,
        ExplicitVRLittleEndian,
        ImplicitVRLittleEndian,
    )
    from pynetdicom import AE

    from dicomnet.scu import associate

    ae = AE(ae_title=calling_ae)
    for sop in (CTImageStorage, EnhancedCTImageStorage):
        ae.add_requested_context(sop, [ExplicitVRLittleEndian, ImplicitVRLittleEndian])
    t0 = time.perf_counter()
    assoc = associate(ae, host, port, ae_title=called_ae)
    if not assoc.is_established:
        raise DicomSeriesError(
            f"C-STORE to {called_ae}@{host}:{port} as {calling_ae}: association "
            f"{'rejected' if assoc.is_rejected else 'not established'}; check the port, the called AE title "
            "and the service's dicom.allowed_calling_ae_titles / allowed_peer_addresses"
        )
    # pynetdicom writes each PDU separately: without TCP_NODELAY every C-STORE waits ~40 ms for the
    # SCP's delayed ACK (Nagle); measured on loopback 62 → 20 ms per 50 kB instance.
    raw = getattr(getattr(assoc.dul, "socket", None), "socket", None)
    if raw is not None:
        raw.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
    statuses, n_bytes = [], 0
    try:
        for f in files:
            statuses.append(int(assoc.send_c_store(dcmread(f)).Status))
            n_bytes += Path(f).stat().st_size
    finally:
        assoc.release()
    t1 = time.perf_counter()
    return SendResult(tuple(statuses), n_bytes, t1 - t0, t1)


def dicom_files(paths: Sequence[Path]) -> tuple[list[Path], list[Path]]:
    """(DICOM Part-10 files, other regular files) under ``paths``: a file as given, a folder searched
    recursively; a DICOMDIR and files without the 'DICM' marker at byte 128 are the others."""
    found: list[Path] = []
    others: list[Path] = []
    for path in paths:
        for f in sorted(path.rglob("*")) if path.is_dir() else [path]:
            if not f.is_file() or f.is_symlink():
                continue
            with f.open("rb") as fh:
                head = fh.read(132)
            (found if head[128:132] == b"DICM" and f.name.upper() != "DICOMDIR" else others).append(f)
    return found, others


def main(argv: Sequence[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=(__doc__ or "").split("\n\n")[0].replace("\n", " "))
    p.add_argument("host")
    p.add_argument("port", type=int)
    p.add_argument("paths", nargs="+", type=Path)
    p.add_argument("--aec", default="OARMREG", help="called AE title (the service's dicom.ae_title)")
    p.add_argument("--aet", default="OARM_SIM", help="calling AE title")
    a = p.parse_args(argv)
    files, _ = dicom_files(a.paths)
    res = send_series(files, a.host, a.port, called_ae=a.aec, calling_ae=a.aet)
    bad = [s for s in res.statuses if s != 0]
    sys.stdout.write(
        f"sent {len(files)} instances, {res.n_bytes / 1e6:.1f} MB in {res.seconds:.2f} s "
        f"({res.mb_per_s:.1f} MB/s); {len(bad)} non-success statuses\n"
    )
    return 1 if bad else 0


if __name__ == "__main__":
    raise SystemExit(main())
