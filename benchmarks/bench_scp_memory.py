"""DICOM Storage SCP memory under concurrent large instances (issue 19 item 6).

pynetdicom buffers a whole C-STORE dataset in memory before ``EVT_C_STORE`` unless
``_config.STORE_RECV_CHUNKED_DATASET`` is set; :class:`service.intake.storage_scp.StorageScp` sets it, so
each instance goes to a temp file and is streamed into place.  This starts the SCP in this process,
has ``--associations`` dcmtk ``storescu`` processes (pynetdicom SCUs if dcmtk is missing) each send
one ``--mb`` MB CT instance at once, and reports the SCP process' peak resident memory above its
resting level (``VmHWM`` after ``clear_refs``, Linux) with the bytes received.

Run: ``.venv/bin/python -m benchmarks.bench_scp_memory [--associations 4] [--mb 64]``.  Run it with
``PYTHONPATH`` at another checkout to measure that code (``StorageScp(config, folder)`` is the same).
"""

from __future__ import annotations

import argparse
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np
from pydicom.dataset import Dataset, FileMetaDataset
from pydicom.uid import CTImageStorage, ExplicitVRLittleEndian, generate_uid

from service.intake.storage_scp import StorageScp
from service.settings import DicomSettings


def write_instance(path: Path, mb: int, series: str, k: int) -> int:
    """One CT Image Storage instance of about ``mb`` MB (square int16 frame); its size on disk."""
    side = int(np.sqrt(mb * 1024**2 / 2))
    ds = Dataset()
    ds.file_meta = FileMetaDataset()
    ds.file_meta.TransferSyntaxUID = ExplicitVRLittleEndian
    ds.SOPClassUID, ds.SOPInstanceUID = CTImageStorage, generate_uid()
    ds.StudyInstanceUID, ds.SeriesInstanceUID, ds.FrameOfReferenceUID = "1.2.3", series, "1.2.4"
    ds.Modality, ds.PatientID, ds.InstanceNumber = "CT", "BENCH", k + 1
    ds.ImagePositionPatient, ds.ImageOrientationPatient = [0, 0, float(k)], [1, 0, 0, 0, 1, 0]
    ds.PixelSpacing = [0.4, 0.4]
    ds.Rows = ds.Columns = side
    ds.SamplesPerPixel, ds.PhotometricInterpretation = 1, "MONOCHROME2"
    ds.BitsAllocated, ds.BitsStored, ds.HighBit, ds.PixelRepresentation = 16, 16, 15, 1
    ds.PixelData = np.full((side, side), k, dtype=np.int16).tobytes()
    ds.save_as(path, enforce_file_format=True)
    return path.stat().st_size


def _kb(field: str) -> int:
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith(field + ":"):
            return int(line.split()[1])
    raise RuntimeError(f"{field} not in /proc/self/status")


def _sender(path: Path, port: int) -> list[str]:
    storescu = shutil.which("storescu")
    if storescu:
        return [storescu, "-aet", "BENCH", "-aec", "OARMREG", "-R", "127.0.0.1", str(port), str(path)]
    return [sys.executable, "-m", "mocks.oarm.cstore", "127.0.0.1", str(port), str(path), "--aet", "BENCH"]


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0] if __doc__ else None)
    p.add_argument("--associations", type=int, default=4)
    p.add_argument("--mb", type=int, default=64)
    a = p.parse_args(argv)
    with tempfile.TemporaryDirectory(prefix="oarmreg-scp-mem-") as tmp:
        out, intake = Path(tmp) / "out", Path(tmp) / "intake"
        out.mkdir()
        series = generate_uid()
        files = [out / f"CT{k}.dcm" for k in range(a.associations)]
        total = sum(write_instance(f, a.mb, series, k) for k, f in enumerate(files))
        scp = StorageScp(DicomSettings(port=0, allowed_calling_ae_titles=("BENCH",)), intake)
        scp.start()
        try:
            Path("/proc/self/clear_refs").write_text("5")  # reset VmHWM to the current RSS
            rest_kb = _kb("VmRSS")
            procs = [subprocess.Popen(_sender(f, scp.port), stdout=subprocess.DEVNULL) for f in files]
            codes = [proc.wait(600) for proc in procs]
            peak_kb = _kb("VmHWM")
        finally:
            scp.stop()
        stored = len(list(intake.rglob("*.dcm")))
    print(
        f"{a.associations} concurrent associations x {a.mb} MB ({total / 1024**2:.0f} MB sent, "
        f"{stored} stored, exit codes {codes}): SCP peak RSS {(peak_kb - rest_kb) / 1024:.0f} MB "
        f"above its resting {rest_kb / 1024:.0f} MB"
    )
    return 0 if stored == a.associations else 1


if __name__ == "__main__":
    raise SystemExit(main())
