"""Fault suite, issue 19: one scan lifecycle for both intakes, driven through the O-arm's network path.

The real service (uvicorn thread, mock simple-message controller with the robot still at Q1, the
DICOM Storage SCP on port 0, auto-register off) receives series from a real SCU (pynetdicom, as
the O-arm's "send to"; dcmtk's ``storescu`` where it is installed) and raw sockets (a peer that
stalls half-way through an A-ASSOCIATE-RQ).  One service for the numbered items 1–4 and 6, one with
a 1 kB retention quota for item 5, and ``serve`` forked from the zygote for the kill -9 test.
Every wait polls with a deadline; nothing sleeps.

Items (issue 19): 1 replaced content withdraws its registration, 2 a reopened series withdraws its
registration, 3 a series whose tail the SCP refused is not complete, 4 an extra instance that
cannot load makes the series invalid, 5 retention covers ``dicom-intake/``, 6 half-open peers are
dropped; then kill -9 during a reopen and a replacement (and a file changed while the service was
down) leaves nothing stale current.
"""

from __future__ import annotations

import contextlib
import copy
import socket
import struct
import subprocess
import sys
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any, TypeVar

import httpx
import numpy as np
import pydicom
import pytest
from pydicom.dataset import Dataset
from pydicom.uid import CTImageStorage, ExplicitVRLittleEndian, generate_uid
from pynetdicom import AE

from dicomnet.scu import associate
from registration.model.frames import transform_from_xyz_rpy
from service.events import Event, RegistrationWithdrawn, ScanReopened, ScanReplaced
from tests.faults._service import (
    DEADLINE_S,
    TOKEN,
    ForkedServe,
    Svc,
    factory_series,
    free_port,
    in_process_service,
    wait_for,
    write_config,
)
from tests.faults.conftest import closed_by_peer
from tests.helpers.scan_cache import simulated_scan
from tests.helpers.system_tools import system_tool

E = TypeVar("E", bound=Event)

AE_TITLE = "OARMREG"
IMAGE_FROM_PHANTOM = transform_from_xyz_rpy([2.0, -3.0, 1.0], [10.0, -6.0, 20.0])
STORESCU = system_tool("storescu")
SCP_BOUNDS = {
    "dicom.socket_timeout_s": 1.0,  # a stalled peer is dropped after 1 s here (10 s by default)
    "dicom.acse_timeout_s": 2.0,
}


def _supported(kw: dict[str, Any]) -> dict[str, Any]:
    """``kw`` minus the ``[dicom]`` settings this checkout does not know (so the module also runs
    against the code before issue 19, where each numbered test must fail on its assertion)."""
    from service.settings import DicomSettings

    return {k: v for k, v in kw.items() if k.split(".", 1)[1] in DicomSettings.model_fields}


# ---------------------------------------------------------------------------- SCU and data


class AssociationFailed(Exception):
    """The SCP sent no response to a C-STORE (the association was aborted or timed out)."""


def send(
    port: int,
    datasets: list[Dataset],
    *,
    after: Callable[[int], bool] | None = None,
) -> list[int]:
    """C-STORE ``datasets`` over one association (pynetdicom's SCU), released at the end.

    ``after(k)`` runs after the k-th response; if it returns True the association is abandoned
    there (aborted, not released: the peer died or the service was killed)."""
    ae = AE(ae_title="OARM_TEST")
    ae.add_requested_context(CTImageStorage, [ExplicitVRLittleEndian])
    assoc = associate(ae, "127.0.0.1", port, ae_title=AE_TITLE)
    assert assoc.is_established, "the SCP did not accept the association"
    raw = getattr(getattr(assoc.dul, "socket", None), "socket", None)
    if raw is not None:  # see mocks.oarm.cstore: without it each C-STORE waits for a delayed ACK
        raw.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
    statuses: list[int] = []
    try:
        for ds in datasets:
            rsp = assoc.send_c_store(ds)
            if "Status" not in rsp:  # no response: the association failed (aborted, timed out)
                raise AssociationFailed(f"no C-STORE response after {len(statuses)} instance(s)")
            statuses.append(int(rsp.Status))
            if after is not None and after(len(statuses)):
                assoc.abort()
                return statuses
    finally:
        if assoc.is_established:
            assoc.release()
    return statuses


def read_all(files: list[Path]) -> list[Dataset]:
    return [pydicom.dcmread(f) for f in files]


def with_new_uid(ds: Dataset, **changes: Any) -> Dataset:
    out = copy.deepcopy(ds)
    out.SOPInstanceUID = out.file_meta.MediaStorageSOPInstanceUID = generate_uid()
    for k, v in changes.items():
        setattr(out, k, v)
    return out


def extension(datasets: list[Dataset], n: int) -> list[Dataset]:
    """``n`` more slices continuing the series past its last one (new SOP Instance UIDs, contiguous)."""
    ipp = [np.array([float(v) for v in ds.ImagePositionPatient]) for ds in datasets]
    order = np.argsort([ds.InstanceNumber for ds in datasets])
    first, last = ipp[order[0]], ipp[order[-1]]
    step = (last - first) / (len(datasets) - 1)
    tail = datasets[order[-1]]
    return [
        with_new_uid(
            tail,
            ImagePositionPatient=[f"{v:.6f}" for v in last + (i + 1) * step],
            InstanceNumber=int(tail.InstanceNumber) + i + 1,
        )
        for i in range(n)
    ]


@dataclass
class Lc:
    svc: Svc
    port: int
    scan: Any
    root: Path

    @property
    def client(self) -> httpx.Client:
        return self.svc.client

    def scan_of(self, uid: str, status: str | None = None) -> dict[str, Any]:
        return self.svc.scan_where(
            lambda s: s["series_uid"] == uid and (status is None or s["status"] == status),
            f"series {uid} recorded {status or ''}",
        )

    def events(self, kind: type[E]) -> list[E]:
        """The recent events of one class (:meth:`service.event_bus.EventBus.recent`)."""
        return [p.event for p in self.svc.ctx.bus.recent() if isinstance(p.event, kind)]

    def export(self, name: str) -> tuple[str, list[Path]]:
        """The module's simulated O-arm scan written as a new series (own Series Instance UID)."""
        from mocks.oarm.dicom_export import write_dicom_series

        res = write_dicom_series(self.scan, self.root / "outbox" / name, write_truth=False)
        return str(res.series_uid), sorted(Path(p) for p in res.paths)

    def registered(self, name: str) -> tuple[int, int, list[Dataset]]:
        """A new series sent by C-STORE, the robot still, registered and current: (scan, reg, datasets)."""
        uid, files = self.export(name)
        datasets = read_all(files)
        self.svc.wait_still()
        assert set(send(self.port, datasets)) == {0}
        scan = self.scan_of(uid, "complete")
        r = self.client.post("/register", json={"scan_id": scan["id"]})
        assert r.status_code == 200, r.text
        assert self.client.get("/registration/current").json()["id"] == r.json()["id"]
        return int(scan["id"]), int(r.json()["id"]), datasets

    def wait_withdrawn(self, scan_id: int, reg_id: int) -> str:
        """Until ``/registration/current`` answers 409; its detail (names the scan and the change)."""

        def gone() -> str | None:
            r = self.client.get("/registration/current")
            return str(r.json()["detail"]) if r.status_code == 409 else None

        detail: str = wait_for(gone, f"registration {reg_id} of scan {scan_id} withdrawn")
        assert f"scan {scan_id}" in detail, detail
        reg = self.client.get(f"/registrations/{reg_id}").json()
        assert reg["status"] == "withdrawn", reg
        return detail


@pytest.fixture(scope="module")
def sim_scan(phantom: Any) -> Any:
    from mocks.oarm.simulator import AcquisitionSettings

    return simulated_scan(phantom, IMAGE_FROM_PHANTOM, AcquisitionSettings.preset("small"))


INTAKE_TESTS_MAX_GAP_S = 0.5
"""These tests judge the intake, not stillness (tests/faults/test_stillness_*.py do): the mock
controller shares the machine, and in the module's service its process, with the DICOM decoding,
and on a loaded machine (CI, the coverage tracer) its sender fell 0.26 s behind — a correct
"joint history incomplete" refusal of the mock, not of the intake.  Still below the 0.6 s window."""


@pytest.fixture(scope="module")
def lc(tmp_path_factory: pytest.TempPathFactory, phantom: Any, sim_scan: Any) -> Iterator[Lc]:
    from registration.model.kinematics import RobotModel

    root = tmp_path_factory.mktemp("lifecycle")
    kw = {"dicom.enabled": True, "dicom.port": 0, "dicom.ae_title": AE_TITLE, **_supported(SCP_BOUNDS),
          "stillness.max_gap_s": INTAKE_TESTS_MAX_GAP_S}  # fmt: skip
    with in_process_service(root, phantom, RobotModel.load("tx60"), **kw) as svc:
        port = int(svc.client.get("/status").json()["listeners"]["dicom"]["port"])
        yield Lc(svc, port, sim_scan, root)


# ---------------------------------------------------------------------------- items 1–4


def test_item1_content_replaced_with_the_same_uids_withdraws_its_registration(lc: Lc) -> None:
    scan_id, reg_id, datasets = lc.registered("item1")
    z0 = lc.client.get("/scans").json()
    before = next(s for s in z0 if s["id"] == scan_id)["image_from_voxel"]
    moved = []
    for ds in datasets:  # same Series / SOP Instance UIDs, every ImagePositionPatient 10 mm along z
        m = copy.deepcopy(ds)
        x, y, z = (float(v) for v in m.ImagePositionPatient)
        m.ImagePositionPatient = [f"{x:.6f}", f"{y:.6f}", f"{z + 10.0:.6f}"]
        moved.append(m)
    assert set(send(lc.port, moved)) == {0}
    detail = lc.wait_withdrawn(scan_id, reg_id)
    assert "replaced" in detail, detail
    # the record describes the content the service now holds, and says what happened
    after = wait_for(
        lambda: next(
            (s for s in lc.client.get("/scans").json() if s["id"] == scan_id and s["status"] == "complete"
             and s["image_from_voxel"] != before),
            None,
        ),
        "the replaced series judged again",
    )  # fmt: skip
    assert after["image_from_voxel"][2][3] == pytest.approx(before[2][3] + 10.0, abs=1e-6)
    assert any(e.scan_id == scan_id for e in lc.events(ScanReplaced))
    assert any(
        scan_id == e.scan_id and reg_id in e.registration_ids for e in lc.events(RegistrationWithdrawn)
    )
    changes = lc.svc.ctx.db.scans.changes(scan_id)
    assert [c[2] for c in changes][-2:] == ["replaced", "complete"], changes


def test_item2_instances_added_in_a_later_association_withdraw_its_registration(lc: Lc) -> None:
    scan_id, reg_id, datasets = lc.registered("item2")
    assert set(send(lc.port, extension(datasets, 4))) == {0}  # a second association: 4 more slices
    detail = lc.wait_withdrawn(scan_id, reg_id)
    assert "added" in detail, detail
    done = lc.scan_of(lc.svc.ctx.db.scans.get(scan_id).series_uid, "complete")
    assert done["id"] == scan_id and done["n_slices"] == len(datasets) + 4
    assert any(e.scan_id == scan_id for e in lc.events(ScanReopened))
    # registering the completed scan again is what the reason says to do, and works
    r = lc.client.post("/register", json={"scan_id": scan_id})
    assert r.status_code == 200, r.text


def test_item3_a_series_whose_tail_the_scp_refused_is_not_complete(lc: Lc) -> None:
    files = sorted(factory_series(lc.root / "outbox" / "item3", 8))
    datasets = read_all(files)
    uid = str(datasets[0].SeriesInstanceUID)
    tail = [copy.deepcopy(ds) for ds in datasets[6:]]
    for ds in tail:
        ds.Modality = "OT"  # → 0xA900 (dataset does not match the SOP class)
    statuses = send(lc.port, datasets[:6] + tail)
    assert statuses == [0] * 6 + [0xA900] * 2
    scan = lc.svc.scan_where(lambda s: s["series_uid"] == uid and s["status"] != "receiving", "a verdict")
    assert scan["status"] == "invalid", scan
    assert "2 of the 8 instance(s)" in scan["reason"] and "0xA900" in scan["reason"], scan["reason"]
    r = lc.client.post("/register", json={"scan_id": scan["id"]})
    assert r.status_code == 422 and "2 of the 8" in r.json()["detail"], r.text
    # sending the whole series again (fixed) completes it
    assert set(send(lc.port, datasets)) == {0}
    assert lc.scan_of(uid, "complete")["n_slices"] == 8


@pytest.mark.skipif(STORESCU is None, reason="dcmtk storescu not installed")
def test_item4_an_extra_instance_that_cannot_load_makes_the_series_invalid(lc: Lc) -> None:
    files = sorted(factory_series(lc.root / "outbox" / "item4", 6))
    uid = str(pydicom.dcmread(files[0]).SeriesInstanceUID)
    r = subprocess.run([STORESCU, "-aec", AE_TITLE, "127.0.0.1", str(lc.port), *map(str, files)],
                       capture_output=True, text=True, timeout=60)  # fmt: skip
    assert r.returncode == 0, r.stdout + r.stderr
    scan = lc.scan_of(uid, "complete")
    # an extra instance: new SOP Instance UID, the position of an existing slice
    extra = with_new_uid(pydicom.dcmread(files[2]), InstanceNumber=99)
    path = lc.root / "outbox" / "item4-extra.dcm"
    extra.save_as(path, enforce_file_format=True)
    r = subprocess.run([STORESCU, "-aec", AE_TITLE, "127.0.0.1", str(lc.port), str(path)],
                       capture_output=True, text=True, timeout=60)  # fmt: skip
    assert r.returncode == 0, r.stdout + r.stderr
    bad = lc.scan_of(uid, "invalid")
    assert bad["id"] == scan["id"] and "position" in bad["reason"].lower(), bad["reason"]
    r2 = lc.client.post("/register", json={"scan_id": scan["id"]})
    assert r2.status_code == 422 and "unusable" in r2.json()["detail"], r2.text


def test_folder_path_same_rule_a_file_replaced_in_place_withdraws_its_registration(lc: Lc) -> None:
    """The watch folder follows the same content rule: one slice re-exported with other bytes (same
    name, same count; before issue 19 only a growing slice count reopened a folder series)."""
    import os

    from tests.helpers.dicom_factory import rewrite_with_other_pixels

    uid, files = lc.export("folder-staging")
    lc.svc.wait_still()
    folder = lc.svc.watch / "folder-scan"
    lc.svc.watch.mkdir(parents=True, exist_ok=True)
    os.replace(files[0].parent, folder)  # the O-arm's folder export, atomically
    scan = lc.scan_of(uid, "complete")
    r = lc.client.post("/register", json={"scan_id": scan["id"]})
    assert r.status_code == 200, r.text
    victim = sorted(folder.glob("*.dcm"))[40]
    rewrite_with_other_pixels(victim)
    detail = lc.wait_withdrawn(scan["id"], int(r.json()["id"]))
    assert "replaced" in detail and victim.name in detail, detail
    assert lc.scan_of(uid, "complete")["id"] == scan["id"]  # judged again: complete, new content


# ---------------------------------------------------------------------------- item 6


A_ASSOCIATE_RQ_HEAD = struct.pack(">BBL", 0x01, 0x00, 200) + b"\x00\x01\x00\x00" + b"OARMREG".ljust(16)
"""The first 26 bytes of an A-ASSOCIATE-RQ announcing 200 (PS3.8 9.3.2); the rest never comes."""


def test_item6_half_open_peers_are_dropped_and_the_oarm_gets_through(lc: Lc) -> None:
    files = sorted(factory_series(lc.root / "outbox" / "item6", 4))
    with contextlib.ExitStack() as stack:
        socks = []
        for _ in range(10):  # pynetdicom's default maximum_associations: every slot
            s = stack.enter_context(socket.create_connection(("127.0.0.1", lc.port), timeout=DEADLINE_S / 2))
            s.sendall(A_ASSOCIATE_RQ_HEAD)
            socks.append(s)
        for s in socks:  # the service drops each stalled peer (closed: EOF or reset) ...
            assert closed_by_peer(s), "a peer stalled half-way through its A-ASSOCIATE-RQ was never dropped"
    # ... and the O-arm can associate again
    statuses = wait_for(lambda: _try_send(lc.port, read_all(files)), "an association after the stall")
    assert set(statuses) == {0}


def _try_send(port: int, datasets: list[Dataset]) -> list[int] | None:
    try:
        return send(port, datasets)
    except AssertionError:
        return None


# ---------------------------------------------------------------------------- item 5


def test_item5_retention_covers_the_cstore_intake_folder_and_withdraws_nothing(
    tmp_path: Path, phantom: Any
) -> None:
    from registration.model.kinematics import RobotModel

    kw = {"dicom.enabled": True, "dicom.port": 0, "dicom.ae_title": AE_TITLE,
          "retention.max_disk_mb": 0.001, "retention.interval_s": 1.0}  # fmt: skip
    with in_process_service(tmp_path, phantom, RobotModel.load("tx60"), **kw) as svc:
        port = int(svc.client.get("/status").json()["listeners"]["dicom"]["port"])
        files = sorted(factory_series(tmp_path / "outbox", 6))
        uid = str(pydicom.dcmread(files[0]).SeriesInstanceUID)
        assert set(send(port, read_all(files))) == {0}
        scan = svc.scan_where(lambda s: s["series_uid"] == uid and s["status"] == "complete", "the scan")
        intake = svc.data / "dicom-intake"
        logged = wait_for(
            lambda: svc.ctx.db._conn.query("SELECT scan_id, folder FROM retention_log"),
            "retention to delete the C-STORE scan's files",
            timeout_s=20.0,
        )
        assert not any(intake.rglob("*.dcm")), list(intake.rglob("*"))
        assert [int(r[0]) for r in logged] == [scan["id"]] and "dicom-intake" in logged[0][1]
        # a deletion is not a change of content: the record stays complete, nothing is withdrawn
        after = svc.scan_where(lambda s: s["id"] == scan["id"], "the scan")
        assert after["status"] == "complete", after
        names = [p.event.name for p in svc.ctx.bus.recent()]
        assert "scan_files_deleted" in names and "scan_replaced" not in names and "scan_invalid" not in names


# ---------------------------------------------------------------------------- kill -9


@contextlib.contextmanager
def _forked_service(root: Path) -> Iterator[tuple[ForkedServe, int, Any]]:
    """The service forked, and the mock controller in a process of its own (``oarmreg mock robot``,
    still): in this process it would share the GIL with the SCU encoding the series, and its own
    frames would go missing, which the service rightly refuses as an incomplete joint history."""
    mock = subprocess.Popen(
        [sys.executable, "-m", "service.cli", "mock", "robot", "--link", "simple-message://127.0.0.1:0"],
        stdout=subprocess.PIPE,
        text=True,
    )
    try:
        assert mock.stdout is not None
        mock_url = mock.stdout.readline().strip()
        assert mock_url.startswith("simple-message://"), mock_url
        cfg, port, dicom_port = root / "oarmreg.toml", free_port(), free_port()
        write_config(cfg, {
            "watch_dir": str(root / "watch"), "data_dir": str(root / "data"), "api_token": TOKEN,
            "port": port, "robot.link_url": mock_url, "robot.connect_timeout_s": 2.0,
            "stillness.window_s": 0.6, "stillness.max_gap_s": INTAKE_TESTS_MAX_GAP_S,
            "watcher.quiet_period_s": 0.3, "watcher.poll_interval_s": 0.2,
            "dicom.enabled": True, "dicom.port": dicom_port, "dicom.ae_title": AE_TITLE,
        })  # fmt: skip
        forked = ForkedServe(cfg, port, root / "forked.log")
        forked.open()
        try:
            yield forked, dicom_port, None
        finally:
            forked.close()
    finally:
        mock.terminate()
        mock.wait(30)


def _current(c: httpx.Client) -> tuple[int, str]:
    r = c.get("/registration/current")
    return r.status_code, r.text


def _register_new(c: httpx.Client, dicom_port: int, datasets: list[Dataset]) -> tuple[int, int]:
    """Send ``datasets`` (a fresh series) once the robot has been seen still, register it.  A delivery
    whose association fails on the way (seen once on a loaded machine, right after a restart) is sent
    again whole: this is the set-up of a scan, not the change under test."""
    wait_for(lambda: c.get("/status").json()["link"]["history_s"] > 0.6, "the joint history")
    try:
        statuses = send(dicom_port, datasets)
    except AssociationFailed:
        statuses = send(dicom_port, datasets)
    assert set(statuses) == {0}
    uid = str(datasets[0].SeriesInstanceUID)

    def recorded() -> dict[str, Any] | None:
        return next(
            (s for s in c.get("/scans").json() if s["series_uid"] == uid and s["status"] == "complete"), None
        )

    scan = wait_for(recorded, "the scan recorded complete")
    r = c.post("/register", json={"scan_id": scan["id"]})
    assert r.status_code == 200, r.text
    return int(scan["id"]), int(r.json()["id"])


SETUP_ATTEMPTS = 3
"""Fresh series tried for one set-up registration (see _register_fresh)."""


def _register_fresh(c: httpx.Client, dicom_port: int, base: list[Dataset]) -> tuple[list[Dataset], int, int]:
    """A fresh series of ``base`` sent and registered (_register_new).  On a loaded machine the mock
    controller in this process can be starved past the joint-history gap limit (seen at load 10:
    "the longest receive gap is 0.570 s"); the service then rightly refuses that scan as
    joint-history-incomplete.  That is the set-up of a scan, not the change under test, so only that
    refusal is met with another fresh series, at most SETUP_ATTEMPTS times; any other answer fails."""
    for _ in range(SETUP_ATTEMPTS - 1):
        datasets = _fresh_series(base)
        try:
            return (datasets, *_register_new(c, dicom_port, datasets))
        except AssertionError as e:
            if "joint-history-incomplete" not in str(e):
                raise
    datasets = _fresh_series(base)
    return (datasets, *_register_new(c, dicom_port, datasets))


def _fresh_series(datasets: list[Dataset]) -> list[Dataset]:
    uid = generate_uid()
    out = []
    for ds in datasets:
        d = with_new_uid(ds)
        d.SeriesInstanceUID = uid
        out.append(d)
    return out


def test_kill_9_during_a_reopen_and_a_replacement_leaves_nothing_stale_current(
    tmp_path: Path, sim_scan: Any
) -> None:
    from mocks.oarm.dicom_export import write_dicom_series

    base = read_all(sorted(write_dicom_series(sim_scan, tmp_path / "outbox", write_truth=False).paths))
    with (
        _forked_service(tmp_path) as (forked, dicom_port, _robot),
        httpx.Client(base_url=forked.base_url, headers={"Authorization": f"Bearer {TOKEN}"},
                     timeout=DEADLINE_S) as c,
    ):  # fmt: skip
        forked.start()
        # 1. kill -9 during a reopen: the first added instance is acknowledged, then the service dies
        a, a_scan, a_reg = _register_fresh(c, dicom_port, base)
        with contextlib.suppress(Exception):
            send(dicom_port, extension(a, 3), after=lambda k: (forked.kill9(), True)[1])
        forked.start()
        status, text = _current(c)
        assert status == 409 and f"scan {a_scan}" in text, text
        assert c.get(f"/registrations/{a_reg}").json()["status"] == "withdrawn"

        # 2. kill -9 during a replacement: 5 instances re-sent with other pixels, then the service dies
        b, b_scan, b_reg = _register_fresh(c, dicom_port, base)
        changed = []
        for ds in b[:20]:
            m = copy.deepcopy(ds)
            px = bytearray(m.PixelData)
            px[0:2] = b"\xff\x0f"
            m.PixelData = bytes(px)
            changed.append(m)
        with contextlib.suppress(Exception):
            send(dicom_port, changed, after=lambda k: k == 5 and (forked.kill9(), True)[1])
        forked.start()
        status, text = _current(c)
        assert status == 409 and f"scan {b_scan}" in text, text
        assert c.get(f"/registrations/{b_reg}").json()["status"] == "withdrawn"

        # 3. the state a wrong crash order would leave: a stored instance replaced on disk, the
        #    withdrawal never committed (kill -9 of an idle service, then the file changes)
        d, d_scan, d_reg = _register_fresh(c, dicom_port, base)
        forked.kill9()
        folder = next((tmp_path / "data" / "dicom-intake").glob(f"*/{d[0].SeriesInstanceUID}"))
        victim = sorted(folder.glob("*.dcm"))[10]
        data = bytearray(victim.read_bytes())
        data[-2:] = b"\x00\x08"
        victim.write_bytes(bytes(data))
        forked.start()
        status, text = _current(c)
        assert (
            status == 409 and f"scan {d_scan}" in text and "changed while the service was stopped" in text
        ), text
        assert c.get(f"/registrations/{d_reg}").json()["status"] == "withdrawn"
        assert forked.kills == 3


# ---------------------------------------------------------------------------- item 3, full disk

INTAKE_FS_KB = 1024
"""The size of the tmpfs mounted over ``dicom-intake/``: room for a few 128 KiB slices, not 24."""


@contextlib.contextmanager
def _small_tmpfs(at: Path, size_kb: int) -> Iterator[None]:
    """A tmpfs of ``size_kb`` at ``at`` (root only; skips where mounting is not allowed)."""
    at.mkdir(parents=True, exist_ok=True)
    r = subprocess.run(["mount", "-t", "tmpfs", "-o", f"size={size_kb}k,mode=0700", "tmpfs", str(at)],
                       capture_output=True, text=True)  # fmt: skip
    if r.returncode != 0:
        pytest.skip(f"cannot mount a tmpfs here (root and CAP_SYS_ADMIN needed): {r.stderr.strip()}")
    try:
        yield
    finally:
        subprocess.run(["umount", "-l", str(at)], check=True)


def test_item3_full_disk_a_series_whose_tail_could_not_be_written_is_not_complete(lc: Lc) -> None:
    """The C-STORE intake folder fills up part-way through a series: the instances answered 0xA700
    leave it ``invalid`` naming how many of how many, never ``complete`` with the slices that fit."""
    from tests.helpers.dicom_factory import ramp_volume, write_series

    files = sorted(write_series(lc.root / "outbox" / "item3-full", ramp_volume(24, 256, 256)))
    datasets = read_all(files)
    uid = str(datasets[0].SeriesInstanceUID)
    intake = lc.svc.data / "dicom-intake"
    with _small_tmpfs(intake, INTAKE_FS_KB):
        statuses = send(lc.port, datasets)
        n_ok = statuses.count(0)
        assert 0 < n_ok < len(datasets) and statuses == [0] * n_ok + [0xA700] * (len(datasets) - n_ok), (
            statuses
        )
        scan = lc.svc.scan_where(lambda s: s["series_uid"] == uid and s["status"] != "receiving", "a verdict")
        assert scan["status"] == "invalid", scan
        assert f"{len(datasets) - n_ok} of the {len(datasets)} instance(s)" in scan["reason"], scan["reason"]
        assert "0xA700" in scan["reason"], scan["reason"]
        r = lc.client.post("/register", json={"scan_id": scan["id"]})
        assert r.status_code == 422, r.text
        status = lc.client.get("/status").json()
        assert not status["healthy"], status
        assert "C-STORE intake refuses writes" in [p["title"] for p in status["problem_details"]], status
    # space again: the next instance stored clears the problem
    send(lc.port, read_all(sorted(write_series(lc.root / "outbox" / "item3-after", ramp_volume(2)))))
    status = lc.client.get("/status").json()
    assert "C-STORE intake refuses writes" not in [p["title"] for p in status["problem_details"]], status
