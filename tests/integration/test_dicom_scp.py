"""DICOM Storage SCP over loopback with dcmtk's echoscu/storescu and pynetdicom as peers
(issue #12).  Every SCP binds port 0."""

from __future__ import annotations

import errno
import os
import subprocess
import threading
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import pydicom
import pytest
from pydantic import ValidationError
from pydicom.dataset import Dataset, FileMetaDataset
from pydicom.uid import (
    CTImageStorage,
    EnhancedCTImageStorage,
    ExplicitVRLittleEndian,
    JPEG2000Lossless,
    MRImageStorage,
    generate_uid,
)
from pynetdicom import AE

from dicomnet.scu import associate
from service.intake.storage_scp import (
    STATUS_DATASET_MISMATCH,
    STATUS_OUT_OF_RESOURCES,
    DicomScpConfigError,
    ScpCallbacks,
    ScpRefusal,
    StorageScp,
    atomic_write,
)
from service.settings import DicomSettings
from tests.helpers.system_tools import system_tool

DEADLINE_S = 10.0
STORESCU = system_tool("storescu")
ECHOSCU = system_tool("echoscu")
needs_dcmtk = pytest.mark.skipif(not (STORESCU and ECHOSCU), reason="dcmtk storescu/echoscu not installed")


@dataclass
class Recorder:
    """Collects callbacks; ``changed`` is set on each one (tests wait on it with a deadline)."""

    released: list[tuple[Path, int, str]] = field(default_factory=list)
    aborted: list[tuple[list[Path], str]] = field(default_factory=list)
    refused: list[ScpRefusal] = field(default_factory=list)
    changed: threading.Condition = field(default_factory=threading.Condition)

    def callbacks(self) -> ScpCallbacks:
        return ScpCallbacks(self._released, self._aborted, self._refused)

    def _add(self, lst: list[Any], item: Any) -> None:
        with self.changed:
            lst.append(item)
            self.changed.notify_all()

    def _released(self, d: Path, n: int, ae: str) -> None:
        self._add(self.released, (d, n, ae))

    def _aborted(self, dirs: list[Path], reason: str) -> None:
        self._add(self.aborted, (dirs, reason))

    def _refused(self, r: ScpRefusal) -> None:
        self._add(self.refused, r)

    def wait(self, what: str, pred: Any) -> None:
        with self.changed:
            if not self.changed.wait_for(pred, DEADLINE_S):
                raise AssertionError(f"timed out after {DEADLINE_S} s waiting for {what}")


@pytest.fixture(scope="module")
def simulated_series(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A small simulated O-arm series (mocks/oarm through the CLI), .dcm files only."""
    from service.cli.main import main

    out = tmp_path_factory.mktemp("sim")
    assert main(["simulate", "--out", str(out), "--preset", "small", "--slices", "24"]) == 0
    (out / "truth.json").unlink()
    for p in out.iterdir():
        if p.suffix != ".dcm":
            p.unlink()
    return out


@pytest.fixture
def scp(tmp_path: Path) -> Iterator[tuple[StorageScp, Recorder]]:
    rec = Recorder()
    server = StorageScp(DicomSettings(port=0), tmp_path / "intake", rec.callbacks())
    server.start()
    try:
        yield server, rec
    finally:
        server.stop()


def ct(rows: int = 16, cols: int = 16, **over: Any) -> Dataset:
    """A minimal valid CT Image Storage dataset (Explicit VR LE)."""
    ds = Dataset()
    ds.file_meta = FileMetaDataset()
    ds.file_meta.TransferSyntaxUID = ExplicitVRLittleEndian
    ds.SOPClassUID, ds.SOPInstanceUID = CTImageStorage, generate_uid()
    ds.StudyInstanceUID, ds.SeriesInstanceUID = over.pop("study", "1.2.3.4"), over.pop("series", "1.2.3.4.5")
    ds.FrameOfReferenceUID = "1.2.3.4.6"
    ds.Modality, ds.PatientName, ds.PatientID = "CT", "PHANTOM^CUBE", "P1"
    ds.ImagePositionPatient, ds.ImageOrientationPatient = [0, 0, 0], [1, 0, 0, 0, 1, 0]
    ds.PixelSpacing, ds.InstanceNumber = [0.5, 0.5], 1
    ds.Rows, ds.Columns, ds.SamplesPerPixel, ds.PhotometricInterpretation = rows, cols, 1, "MONOCHROME2"
    ds.BitsAllocated, ds.BitsStored, ds.HighBit, ds.PixelRepresentation = 16, 16, 15, 1
    ds.PixelData = (np.arange(rows * cols, dtype=np.int16) % 1000).tobytes()
    for k, v in over.items():
        if v is None:
            delattr(ds, k)
        else:
            setattr(ds, k, v)
    return ds


def scu(
    ae_title: str = "OARM",
    contexts: tuple[str, ...] = (CTImageStorage, EnhancedCTImageStorage),
    ts: Any = None,
) -> AE:
    ae = AE(ae_title=ae_title)
    for c in contexts:
        ae.add_requested_context(c, ts or [ExplicitVRLittleEndian])
    return ae


def store(port: int, datasets: list[Dataset], **kw: Any) -> list[int]:
    assoc = associate(scu(**kw), "127.0.0.1", port, ae_title="OARMREG")
    assert assoc.is_established
    try:
        return [int(assoc.send_c_store(ds).Status) for ds in datasets]
    finally:
        assoc.release()


def files(root: Path, pattern: str = "*.dcm") -> list[Path]:
    return sorted(root.rglob(pattern))


# --------------------------------------------------------------------------- dcmtk peers


@needs_dcmtk
def test_echoscu_is_answered(scp: tuple[StorageScp, Recorder]) -> None:
    server, _ = scp
    r = subprocess.run([ECHOSCU, "-aet", "OARM", "-aec", "OARMREG", "127.0.0.1", str(server.port)],
                       capture_output=True, text=True, timeout=30)  # fmt: skip
    assert r.returncode == 0, r.stderr
    assert server.counters["echoes"] == 1


@needs_dcmtk
def test_storescu_series_stored_atomically_then_identical_resend_changes_nothing(
    scp: tuple[StorageScp, Recorder], simulated_series: Path
) -> None:
    server, rec = scp
    cmd = [STORESCU, "-aet", "OARM", "-aec", "OARMREG", "+sd", "+r", "127.0.0.1", str(server.port),
           str(simulated_series)]  # fmt: skip
    r = subprocess.run(cmd, capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr
    src = sorted(simulated_series.glob("*.dcm"))
    rec.wait("the series released", lambda: len(rec.released) == 1)
    series_dir, n, calling = rec.released[0]
    first = pydicom.dcmread(src[0])
    assert series_dir == server.intake_dir / first.StudyInstanceUID / first.SeriesInstanceUID
    assert (n, calling) == (len(src), "OARM")
    stored = files(server.intake_dir)
    assert [p.name for p in stored] == sorted(f"{pydicom.dcmread(p).SOPInstanceUID}.dcm" for p in src)
    assert files(server.intake_dir, ".*.part") == []
    for s in src[:3]:
        a, b = pydicom.dcmread(s), pydicom.dcmread(series_dir / f"{pydicom.dcmread(s).SOPInstanceUID}.dcm")
        assert a.PixelData == b.PixelData and a.ImagePositionPatient == b.ImagePositionPatient
    before = {p: p.stat().st_mtime_ns for p in stored}
    r = subprocess.run(cmd, capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr
    rec.wait("the resend released", lambda: len(rec.released) == 2)
    assert {p: p.stat().st_mtime_ns for p in files(server.intake_dir)} == before
    assert server.counters["stored"] == len(src) and server.counters["duplicates"] == len(src)


@needs_dcmtk
def test_echoscu_with_calling_ae_not_on_the_list_is_rejected(tmp_path: Path) -> None:
    rec = Recorder()
    cfg = DicomSettings(port=0, allowed_calling_ae_titles=("OARM",))
    with StorageScp(cfg, tmp_path, rec.callbacks()) as server:
        r = subprocess.run([ECHOSCU, "-aet", "INTRUDER", "-aec", "OARMREG", "127.0.0.1", str(server.port)],
                           capture_output=True, text=True, timeout=30)  # fmt: skip
        assert r.returncode != 0
        rec.wait("the refusal", lambda: len(rec.refused) == 1)
        ok = subprocess.run([ECHOSCU, "-aet", "OARM", "-aec", "OARMREG", "127.0.0.1", str(server.port)],
                            capture_output=True, text=True, timeout=30)  # fmt: skip
        assert ok.returncode == 0, ok.stderr
    assert rec.refused[0].kind == "calling_ae" and "INTRUDER" in rec.refused[0].reason


# --------------------------------------------------------------------------- pynetdicom SCU


@pytest.mark.filterwarnings("ignore:Invalid value for VR UI", "ignore:The value length")
@pytest.mark.parametrize(
    ("change", "why"),
    [
        ({"SOPClassUID": EnhancedCTImageStorage}, "NumberOfFrames"),  # a CT image sent as Enhanced CT
        ({"Modality": "MR"}, "Modality"),
        ({"ImagePositionPatient": None}, "ImagePositionPatient"),
        ({"PixelData": None}, "PixelData"),
        ({"study": "1.2.3.04"}, "malformed UID"),
        ({"series": "1.2.3.4.5.0" + ".1" * 40}, "malformed UID"),
    ],
)
def test_dataset_not_matching_its_sop_class_is_a900(
    scp: tuple[StorageScp, Recorder], change: dict[str, Any], why: str
) -> None:
    server, rec = scp
    assert store(server.port, [ct(**change)]) == [STATUS_DATASET_MISMATCH]
    assert files(server.intake_dir, "*") == [] or files(server.intake_dir) == []
    rec.wait("the refusal", lambda: len(rec.refused) == 1)
    assert rec.refused[0].kind == "dataset" and why in rec.refused[0].reason
    assert rec.refused[0].status == STATUS_DATASET_MISMATCH


def test_mr_series_refused_at_negotiation(scp: tuple[StorageScp, Recorder]) -> None:
    server, rec = scp
    assoc = associate(scu(contexts=(MRImageStorage,)), "127.0.0.1", server.port, ae_title="OARMREG")
    assert not assoc.is_established  # no context accepted: the requestor gives up
    mixed = associate(
        scu(contexts=(MRImageStorage, CTImageStorage)), "127.0.0.1", server.port, ae_title="OARMREG"
    )
    try:
        with pytest.raises(ValueError, match="presentation context"):
            mixed.send_c_store(ct(SOPClassUID=MRImageStorage, Modality="MR"))
    finally:
        mixed.release()
    rec.wait("the context refusals", lambda: len(rec.refused) == 2)
    assert all(r.kind == "context" and "MR Image Storage" in r.reason for r in rec.refused)
    assert files(server.intake_dir) == []


def test_aborted_association_reports_its_series(scp: tuple[StorageScp, Recorder]) -> None:
    server, rec = scp
    assoc = associate(scu(), "127.0.0.1", server.port, ae_title="OARMREG")
    statuses = [int(assoc.send_c_store(ct()).Status) for _ in range(3)]
    assoc.abort()
    rec.wait("the abort callback", lambda: len(rec.aborted) == 1)
    dirs, reason = rec.aborted[0]
    assert statuses == [0, 0, 0]
    assert dirs == [server.intake_dir / "1.2.3.4" / "1.2.3.4.5"] and "abort" in reason.lower()
    assert len(files(server.intake_dir)) == 3 and rec.released == []


def test_duplicate_resend_changes_nothing_and_different_content_replaces(
    scp: tuple[StorageScp, Recorder],
) -> None:
    server, _ = scp
    ds = ct()
    assert store(server.port, [ds]) == [0]
    (path,) = files(server.intake_dir)
    stat = path.stat()
    assert store(server.port, [ds]) == [0]
    assert path.stat().st_mtime_ns == stat.st_mtime_ns and path.stat().st_ino == stat.st_ino
    ds.WindowCenter = 40
    assert store(server.port, [ds]) == [0]
    assert pydicom.dcmread(path).WindowCenter == 40
    assert (server.counters["stored"], server.counters["duplicates"], server.counters["replaced"]) == (
        1,
        1,
        1,
    )


def test_calling_ae_not_on_the_list_rejected_with_reason(tmp_path: Path) -> None:
    rec = Recorder()
    with StorageScp(
        DicomSettings(port=0, allowed_calling_ae_titles=("OARM",)), tmp_path, rec.callbacks()
    ) as s:
        bad = associate(scu("INTRUDER"), "127.0.0.1", s.port, ae_title="OARMREG")
        assert bad.is_rejected
        assert store(s.port, [ct()], ae_title="OARM") == [0]
    assert [r.kind for r in rec.refused] == ["calling_ae"]


def test_peer_address_not_on_the_list_rejected(tmp_path: Path) -> None:
    rec = Recorder()
    with StorageScp(
        DicomSettings(port=0, allowed_peer_addresses=("127.0.0.2",)), tmp_path, rec.callbacks()
    ) as s:
        bad = associate(scu(), "127.0.0.1", s.port, ae_title="OARMREG")
        assert bad.is_rejected
        good = associate(scu(), "127.0.0.1", s.port, ae_title="OARMREG", bind_address=("127.0.0.2", 0))
        assert good.is_established
        good.release()
    assert [r.kind for r in rec.refused] == ["peer"] and "127.0.0.1" in rec.refused[0].reason


def test_jpeg2000_lossless_instance_accepted_as_sent(scp: tuple[StorageScp, Recorder]) -> None:
    server, _ = scp
    ds = ct(rows=32, cols=32)
    try:
        ds.compress(JPEG2000Lossless)
    except Exception as e:  # no encoder plugin installed
        pytest.skip(f"cannot JPEG 2000-encode here: {e}")
    assert store(server.port, [ds], ts=[JPEG2000Lossless]) == [0]
    (path,) = files(server.intake_dir)
    back = pydicom.dcmread(path)
    assert back.file_meta.TransferSyntaxUID == JPEG2000Lossless
    np.testing.assert_array_equal(back.pixel_array, ct(rows=32, cols=32).pixel_array)


# --------------------------------------------------------------------------- full disk


def enospc_after(n_bytes: int) -> Any:
    """An ``os.write`` that fails with ENOSPC once ``n_bytes`` have been written in total."""
    state = {"left": n_bytes}

    def write(fd: int, data: memoryview) -> int:
        if state["left"] <= 0:
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
        n = os.write(fd, data[: state["left"]])
        state["left"] -= n
        return n

    return write


def test_disk_full_injected_is_a700_and_nothing_half_written(tmp_path: Path) -> None:
    rec = Recorder()
    big = [ct(rows=64, cols=64) for _ in range(3)]  # 8 KiB of pixels each
    with StorageScp(DicomSettings(port=0), tmp_path, rec.callbacks(), write=enospc_after(12_000)) as s:
        statuses = store(s.port, big)
    assert statuses == [0, STATUS_OUT_OF_RESOURCES, STATUS_OUT_OF_RESOURCES]
    assert [p.name for p in files(tmp_path)] == [f"{big[0].SOPInstanceUID}.dcm"]
    assert files(tmp_path, ".*.part") == []
    assert pydicom.dcmread(files(tmp_path)[0]).SOPInstanceUID == big[0].SOPInstanceUID
    assert [r.kind for r in rec.refused] == ["disk", "disk"] and "free space" in rec.refused[0].reason


@pytest.fixture
def tiny_tmpfs(tmp_path: Path) -> Iterator[Path]:
    d = tmp_path / "tmpfs"
    d.mkdir()
    r = subprocess.run(["mount", "-t", "tmpfs", "-o", "size=1m", "tmpfs", str(d)], capture_output=True)
    if r.returncode != 0:
        pytest.skip(f"cannot mount a tmpfs here ({r.stderr.decode().strip()}); the injected test covers it")
    try:
        yield d
    finally:
        subprocess.run(["umount", str(d)], check=False)


def test_disk_full_on_a_real_1mb_tmpfs_is_a700(tiny_tmpfs: Path) -> None:
    rec = Recorder()
    big = [ct(rows=384, cols=384) for _ in range(4)]  # 288 KiB each: the 4th cannot fit in 1 MiB
    with StorageScp(DicomSettings(port=0), tiny_tmpfs, rec.callbacks()) as s:
        statuses = store(s.port, big)
    assert statuses[:3] == [0, 0, 0] and statuses[3] == STATUS_OUT_OF_RESOURCES
    assert files(tiny_tmpfs, ".*.part") == []
    assert len(files(tiny_tmpfs)) == 3
    for p in files(tiny_tmpfs):
        assert len(pydicom.dcmread(p).PixelData) == 384 * 384 * 2


def test_atomic_write_leaves_old_file_on_failure(tmp_path: Path) -> None:
    p = tmp_path / "x.dcm"
    p.write_bytes(b"old")
    with pytest.raises(OSError, match="No space"):
        atomic_write(p, b"new" * 1000, write=enospc_after(10))
    assert p.read_bytes() == b"old" and sorted(tmp_path.iterdir()) == [p]


# --------------------------------------------------------------------------- config


@pytest.mark.parametrize("host", ["0.0.0.0", "10.1.2.3"])
def test_non_loopback_without_allow_lists_refuses_to_start(host: str, tmp_path: Path) -> None:
    """The rule lives in ``DicomSettings``; an SCP built from a section (even one not marked
    enabled) is held to it, so no listener can bypass it."""
    with pytest.raises(DicomScpConfigError, match="allow-lists empty"):
        StorageScp(DicomSettings(host=host), tmp_path)
    with pytest.raises(ValidationError, match="allow-lists empty"):
        DicomSettings(host=host, enabled=True)
    StorageScp(DicomSettings(host=host, allowed_calling_ae_titles=("OARM",)), tmp_path)
    StorageScp(DicomSettings(host=host, allowed_peer_addresses=("10.1.2.0/24",)), tmp_path)


@pytest.mark.parametrize("title", ["A_TITLE_LONGER_THAN_16", "    ", "ÄRZTE"])
def test_bad_ae_title_refused(title: str) -> None:
    with pytest.raises(ValidationError, match="ae_title"):
        DicomSettings(ae_title=title)
