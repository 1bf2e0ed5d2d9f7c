"""DICOM Storage SCP: C-STORE throughput for a 512×512×192 CT series (≈ 100 MB).

The series is synthetic (pydicom, int16, Explicit VR Little Endian, CT Image Storage) and
written once to a temp folder; each run sends it over loopback to a fresh
:class:`service.intake.storage_scp.StorageScp` (atomic write with fsync per instance) with dcmtk's
``storescu -R +sd`` (only the contexts it needs) when installed, else a pynetdicom SCU.
Prints the median of ``--runs``.

Run: ``.venv/bin/python -m benchmarks.bench_dicom_scp [--slices 192] [--runs 3]``
"""

from __future__ import annotations

import argparse
import shutil
import statistics
import subprocess
import tempfile
import time
from pathlib import Path

import numpy as np
from pydicom.dataset import Dataset, FileMetaDataset
from pydicom.uid import CTImageStorage, ExplicitVRLittleEndian, generate_uid

from service.intake.storage_scp import StorageScp
from service.settings import DicomSettings


def write_series(folder: Path, n: int, size: int = 512) -> int:
    """Write ``n`` slices; returns the total bytes on disk."""
    study, series, for_uid = generate_uid(), generate_uid(), generate_uid()
    rng = np.random.default_rng(0)
    pixels = rng.integers(-1000, 2000, size=(size, size), dtype=np.int16)
    total = 0
    for i in range(n):
        ds = Dataset()
        ds.file_meta = FileMetaDataset()
        ds.file_meta.TransferSyntaxUID = ExplicitVRLittleEndian
        ds.SOPClassUID, ds.SOPInstanceUID = CTImageStorage, generate_uid()
        ds.StudyInstanceUID, ds.SeriesInstanceUID, ds.FrameOfReferenceUID = study, series, for_uid
        ds.Modality, ds.PatientID, ds.InstanceNumber = "CT", "BENCH", i + 1
        ds.ImagePositionPatient, ds.ImageOrientationPatient = [0, 0, 0.8 * i], [1, 0, 0, 0, 1, 0]
        ds.PixelSpacing = [0.4, 0.4]
        ds.Rows = ds.Columns = size
        ds.SamplesPerPixel, ds.PhotometricInterpretation = 1, "MONOCHROME2"
        ds.BitsAllocated, ds.BitsStored, ds.HighBit, ds.PixelRepresentation = 16, 16, 15, 1
        ds.PixelData = np.roll(pixels, i).tobytes()
        p = folder / f"CT{i:04d}.dcm"
        ds.save_as(p, enforce_file_format=True)
        total += p.stat().st_size
    return total


def send(folder: Path, port: int) -> None:
    storescu = shutil.which("storescu")
    if storescu:
        cmd = [storescu, "-aet", "BENCH", "-aec", "OARMREG", "-R", "+sd", "127.0.0.1", str(port), str(folder)]
        subprocess.run(cmd, check=True, capture_output=True)
        return
    from pynetdicom import AE

    from dicomnet.scu import associate

    ae = AE(ae_title="BENCH")
    ae.add_requested_context(CTImageStorage, [ExplicitVRLittleEndian])
    assoc = associate(ae, "127.0.0.1", port, ae_title="OARMREG")
    try:
        for p in sorted(folder.glob("*.dcm")):
            assert assoc.send_c_store(p).Status == 0
    finally:
        assoc.release()


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--slices", type=int, default=192)
    ap.add_argument("--runs", type=int, default=3)
    args = ap.parse_args(argv)
    with tempfile.TemporaryDirectory() as tmp:
        src = Path(tmp) / "series"
        src.mkdir()
        total = write_series(src, args.slices)
        rates = []
        for run in range(args.runs):
            intake = Path(tmp) / f"intake{run}"
            with StorageScp(DicomSettings(port=0), intake) as scp:
                t0 = time.perf_counter()
                send(src, scp.port)
                dt = time.perf_counter() - t0
                assert scp.counters["stored"] == args.slices, scp.counters
            rates.append(total / dt / 1e6)
            shutil.rmtree(intake)
    peer = "dcmtk storescu" if shutil.which("storescu") else "pynetdicom SCU"
    print(f"C-STORE {args.slices} × 512² int16 ({total / 1e6:.1f} MB) via {peer}, fsync per instance: "
          f"median {statistics.median(rates):.1f} MB/s over {args.runs} runs "
          f"({', '.join(f'{r:.1f}' for r in rates)})")  # fmt: skip
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
