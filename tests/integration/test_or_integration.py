"""The service's operating-room interfaces with real third-party peers on loopback (issue #12).

One running service per module (real uvicorn over TLS, a mock simple_message controller, the
DICOM Storage SCP and the OpenIGTLink server on port 0, auto-register on).  Peers: dcmtk's
``storescu`` / ``echoscu``, pynetdicom's SCU, pyigtl's ``OpenIGTLinkClient``, dicom3tools'
``dciodvfy``, ``curl --cacert`` and a raw socket that never reads.  Each test sets up what it
needs (fixtures), so any one passes alone and in any order; every wait polls with a deadline.
"""

from __future__ import annotations

import socket
import ssl
import subprocess
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from io import BytesIO
from pathlib import Path
from typing import Any, TypeVar

import httpx
import numpy as np
import pydicom
import pytest
from pydicom.uid import CTImageStorage, MRImageStorage, generate_uid
from pynetdicom import AE

from dicomnet.scu import associate
from registration.model.frames import invert, transform_from_xyz_rpy
from service.events import (
    DicomAssociationAborted,
    DicomAssociationReleased,
    DicomRefused,
    Event,
    IgtlClientConnected,
    IgtlClientHeaderVersion,
    RegistrationRefused,
)
from tests.helpers.scan_cache import simulated_scan
from tests.helpers.system_tools import system_tool
from tests.helpers.tokens import make_token
from tests.integration.polling import wait_for

E = TypeVar("E", bound=Event)

pyigtl = pytest.importorskip("pyigtl")

TOKEN = make_token()
WINDOW_S = 0.6
DEADLINE_S = 60.0
AE_TITLE = "OARMREG"
ALLOWED_AETS = ("STORESCU", "ECHOSCU", "OARM_TEST")
Q1 = (0.0, 0.0, np.pi / 2, 0.0, np.pi / 4, 0.0)
IMAGE_FROM_PHANTOM_1 = transform_from_xyz_rpy([2.0, -3.0, 1.0], [10.0, -6.0, 20.0])
RAS_FROM_LPS = np.diag([-1.0, -1.0, 1.0, 1.0])
STORESCU, ECHOSCU, DCIODVFY, CURL, OPENSSL = (
    system_tool(n) for n in ("storescu", "echoscu", "dciodvfy", "curl", "openssl")
)


def make_tls(folder: Path) -> tuple[Path, Path, Path]:
    """A throwaway CA and a server certificate for 127.0.0.1 (openssl CLI)."""
    assert OPENSSL is not None
    ca_key, ca, key, csr, cert = (folder / n for n in ("ca.key", "ca.pem", "srv.key", "srv.csr", "srv.pem"))
    ext = folder / "ext.cnf"
    ext.write_text("subjectAltName = IP:127.0.0.1, DNS:localhost\n")

    def run(*args: str | Path) -> None:
        subprocess.run([OPENSSL, *map(str, args)], check=True, capture_output=True, timeout=60)

    run("req", "-x509", "-newkey", "rsa:2048", "-nodes", "-keyout", ca_key, "-out", ca, "-days", "2",
        "-subj", "/CN=oarmreg test CA")  # fmt: skip
    run("req", "-newkey", "rsa:2048", "-nodes", "-keyout", key, "-out", csr, "-subj", "/CN=127.0.0.1")
    run("x509", "-req", "-in", csr, "-CA", ca, "-CAkey", ca_key, "-CAcreateserial", "-out", cert,
        "-days", "2", "-extfile", ext)  # fmt: skip
    return ca, cert, key


@dataclass
class Service:
    client: httpx.Client
    ctx: Any
    robot: Any
    base_url: str
    ca: Path
    dicom_port: int
    igtl_port: int
    root: Path
    scan1: Any

    def events(self, kind: type[E]) -> list[E]:
        """The recent events of one class (:meth:`service.event_bus.EventBus.recent`)."""
        return [p.event for p in self.ctx.bus.recent() if isinstance(p.event, kind)]

    def scan(self, uid: str) -> dict[str, Any] | None:
        r = self.client.get("/scans", params={"limit": 1000})
        r.raise_for_status()
        return next((s for s in r.json() if s["series_uid"] == uid), None)

    def wait_scan(self, uid: str, status: str | None = None) -> dict[str, Any]:
        def ok() -> dict[str, Any] | None:
            s = self.scan(uid)
            return s if s is not None and (status is None or s["status"] == status) else None

        return wait_for(ok, f"series {uid} recorded {status or ''}")  # type: ignore[no-any-return]

    def wait_released(self, uid: str, n_before: int = 0) -> DicomAssociationReleased:
        def ok() -> DicomAssociationReleased | None:
            evs = [e for e in self.events(DicomAssociationReleased) if e.series_uid == uid]
            return evs[-1] if len(evs) > n_before else None

        return wait_for(ok, f"the association release of {uid} to be processed")  # type: ignore[no-any-return]


@pytest.fixture(scope="module")
def svc(tmp_path_factory: pytest.TempPathFactory, phantom: Any) -> Iterator[Service]:
    if OPENSSL is None:
        pytest.skip("openssl CLI not installed")
    from mocks.oarm.simulator import AcquisitionSettings
    from mocks.robot.robot import ScriptedRobot
    from mocks.robot.runner import run_mock_controller
    from registration.model.kinematics import RobotModel
    from service.cli.commands.serve import serve_in_thread
    from service.http.app import create_app
    from service.http.tls import uvicorn_ssl_options
    from service.settings import load_settings

    root = tmp_path_factory.mktemp("or")
    ca, cert, key = make_tls(root)
    model = RobotModel.load("tx60")
    scan1 = simulated_scan(phantom, IMAGE_FROM_PHANTOM_1, AcquisitionSettings.preset("small"))
    robot = ScriptedRobot(Q1)
    with run_mock_controller("simple-message", robot) as mock:
        settings = load_settings(None, {
            "watch_dir": root / "watch", "data_dir": root / "data", "api_token": TOKEN,
            "robot.link_url": mock.url, "robot.connect_timeout_s": 2.0,
            "stillness.window_s": WINDOW_S, "stillness.max_gap_s": 0.5,
            "watcher.quiet_period_s": 0.3, "watcher.poll_interval_s": 0.2,
            "dicom.enabled": True, "dicom.port": 0, "dicom.ae_title": AE_TITLE,
            "dicom.allowed_calling_ae_titles": list(ALLOWED_AETS),
            "igtl.enabled": True, "igtl.port": 0, "igtl.period_s": 0.5,
            "tls.cert_file": cert, "tls.key_file": key, "service.auto_register": True,
        })  # fmt: skip
        app = create_app(settings, phantom=phantom, robot_model=model)
        with (
            serve_in_thread(app, ssl_options=uvicorn_ssl_options(settings)) as server,
            httpx.Client(
                base_url=server.base_url, headers={"Authorization": f"Bearer {TOKEN}"}, timeout=60.0,
                verify=ssl.create_default_context(cafile=str(ca)),
            ) as client,
        ):  # fmt: skip
            ctx = app.state.ctx
            lst = client.get("/status").json()["listeners"]
            s = Service(client, ctx, robot, server.base_url, ca, lst["dicom"]["port"], lst["igtl"]["port"],
                        root, scan1)  # fmt: skip
            wait_for(lambda: client.get("/status").json()["link"]["history_s"] > WINDOW_S, "joint history")
            yield s


def send_files(
    port: int, files: list[Path], *, calling_ae: str = "OARM_TEST", abort_after: int | None = None
) -> list[int]:
    """C-STORE ``files`` with pynetdicom's SCU (as the O-arm would); return the statuses."""
    ae = AE(ae_title=calling_ae)
    ae.add_requested_context(CTImageStorage)
    assoc = associate(ae, "127.0.0.1", port, ae_title=AE_TITLE)
    assert assoc.is_established, f"association from {calling_ae} not established"
    statuses = []
    try:
        for i, f in enumerate(files):
            if abort_after is not None and i == abort_after:
                assoc.abort()
                return statuses
            st = assoc.send_c_store(pydicom.dcmread(f))
            assert "Status" in st, f"no C-STORE response for {f.name} (association aborted or timed out)"
            statuses.append(int(st.Status))
    finally:
        if assoc.is_established:
            assoc.release()
    return statuses


def write_scan(svc: Service, scan: Any, name: str) -> tuple[str, list[Path]]:
    from mocks.oarm.dicom_export import write_dicom_series

    res = write_dicom_series(scan, svc.root / "outbox" / name, write_truth=False)
    return str(res.series_uid), sorted(Path(p) for p in res.paths)


def synthetic_512(folder: Path, n_slices: int) -> tuple[str, list[Path]]:
    """A 512 × 512 × ``n_slices`` CT series (noise), as a thin O-arm slab."""
    from tests.helpers.dicom_factory import write_series

    rng = np.random.default_rng(7)
    stored = rng.integers(-1000, 2000, size=(n_slices, 512, 512), dtype=np.int16)
    uid = generate_uid()
    paths = write_series(
        folder, stored, series_uid=uid, pixel_spacing_mm=(0.415, 0.415), slice_spacing_mm=0.833
    )
    return uid, paths


@dataclass(frozen=True)
class Current:
    registration: dict[str, Any]


@pytest.fixture(scope="module")
def current(svc: Service) -> Current:
    """Scan 1 sent by C-STORE with the robot still at Q1 → auto-registered → current."""
    uid, files = write_scan(svc, svc.scan1, "scan1")
    assert set(send_files(svc.dicom_port, files)) == {0}
    scan = svc.wait_scan(uid, "complete")

    def accepted() -> dict[str, Any] | None:
        regs = svc.client.get("/registrations").json()
        return next((r for r in regs if r["scan_id"] == scan["id"] and r["status"] == "accepted"), None)

    reg = wait_for(accepted, "the auto-registration of scan 1")
    return Current(reg)


# ---------------------------------------------------------------------------- DICOM


@pytest.mark.skipif(not (STORESCU and ECHOSCU), reason="dcmtk storescu/echoscu not installed")
def test_dcmtk_echoscu_and_storescu_512_series_is_recorded(svc: Service) -> None:
    r = subprocess.run([ECHOSCU, "-aec", AE_TITLE, "127.0.0.1", str(svc.dicom_port)],
                       capture_output=True, text=True, timeout=30)  # fmt: skip
    assert r.returncode == 0, r.stderr
    folder = svc.root / "outbox" / "dcmtk512"
    uid, paths = synthetic_512(folder, 24)
    r = subprocess.run([STORESCU, "-aec", AE_TITLE, "127.0.0.1", str(svc.dicom_port), *map(str, paths)],
                       capture_output=True, text=True, timeout=60)  # fmt: skip
    assert r.returncode == 0, r.stdout + r.stderr
    scan = svc.wait_scan(uid, "complete")
    assert (scan["n_slices"], scan["rows"], scan["columns"]) == (24, 512, 512)
    ev = svc.wait_released(uid)
    assert ev.outcome == "complete" and ev.calling_ae == "STORESCU" and ev.scan_id == scan["id"]
    # the volume decoded on arrival equals the loader's, voxel for voxel
    from registration.dicom import load_series

    vol = svc.ctx.volumes.get(uid)
    assert vol is not None and vol.meta.get("decoded_on_arrival")
    ref = load_series(scan["folder"], series_uid=uid)
    np.testing.assert_array_equal(vol.voxels, ref.voxels)
    np.testing.assert_array_equal(vol.image_from_voxel, ref.image_from_voxel)


def test_bad_input_over_cstore_is_refused_or_recorded_and_nothing_is_lost(svc: Service) -> None:
    from tests.helpers.dicom_factory import ramp_volume, write_series

    out = svc.root / "outbox"
    good_files = sorted(Path(p) for p in write_series(out / "good", ramp_volume(6, 32, 32)))
    good_uid = str(pydicom.dcmread(good_files[0]).SeriesInstanceUID)
    assert set(send_files(svc.dicom_port, good_files)) == {0}
    before = svc.wait_scan(good_uid, "complete")
    # the scan is recorded before its release event is published: wait for that event, then count
    assert svc.wait_released(good_uid).outcome == "complete"
    n_released = len([e for e in svc.events(DicomAssociationReleased) if e.series_uid == good_uid])

    # an identical re-send changes nothing
    assert set(send_files(svc.dicom_port, good_files)) == {0}
    assert svc.wait_released(good_uid, n_released).outcome == "unchanged"
    assert svc.scan(good_uid) == before

    # junk: a CT dataset without pixel data or geometry → 0xA900, nothing recorded
    junk = pydicom.dcmread(good_files[0])
    del junk.PixelData, junk.ImagePositionPatient
    junk.SOPInstanceUID = junk.file_meta.MediaStorageSOPInstanceUID = generate_uid()
    junk.SeriesInstanceUID = junk_uid = generate_uid()
    ae = AE(ae_title="OARM_TEST")
    ae.add_requested_context(CTImageStorage)
    ae.add_requested_context(MRImageStorage)
    assoc = associate(ae, "127.0.0.1", svc.dicom_port, ae_title=AE_TITLE)
    assert assoc.is_established
    assert int(assoc.send_c_store(junk).Status) == 0xA900
    # an MR series: its presentation context is refused at negotiation
    mr = pydicom.dcmread(good_files[1])
    mr.SOPClassUID = mr.file_meta.MediaStorageSOPClassUID = MRImageStorage
    mr.Modality = "MR"
    with pytest.raises(ValueError, match="presentation context"):
        assoc.send_c_store(mr)
    assoc.release()
    wait_for(
        lambda: any("MR Image Storage" in e.reason for e in svc.events(DicomRefused)),
        "the MR refusal event",
    )
    assert any(e.kind == "dataset" and e.status == 0xA900 for e in svc.events(DicomRefused))
    assert svc.scan(junk_uid) is None

    # a slice missing → recorded invalid with the loader's reason
    miss_files = sorted(Path(p) for p in write_series(out / "missing", ramp_volume(8, 32, 32)))
    miss_uid = str(pydicom.dcmread(miss_files[0]).SeriesInstanceUID)
    assert set(send_files(svc.dicom_port, miss_files[:3] + miss_files[4:])) == {0}
    miss = svc.wait_scan(miss_uid, "invalid")
    assert "missing" in miss["reason"].lower() or "spacing" in miss["reason"].lower(), miss["reason"]
    # ...then the missing slice arrives: the series reopens and completes
    assert send_files(svc.dicom_port, [miss_files[3]]) == [0]
    assert svc.wait_scan(miss_uid, "complete")["id"] == miss["id"]

    # an association aborted mid-series → partial series recorded invalid with the reason
    ab_files = sorted(Path(p) for p in write_series(out / "aborted", ramp_volume(8, 32, 32)))
    ab_uid = str(pydicom.dcmread(ab_files[0]).SeriesInstanceUID)
    send_files(svc.dicom_port, ab_files, abort_after=4)
    ab = svc.wait_scan(ab_uid, "invalid")
    assert "aborted" in ab["reason"]
    wait_for(lambda: any(e.series_uid == ab_uid for e in svc.events(DicomAssociationAborted)), "abort event")

    # a calling AE title not on the allow-list → association rejected
    ae = AE(ae_title="INTRUDER")
    ae.add_requested_context(CTImageStorage)
    assoc = associate(ae, "127.0.0.1", svc.dicom_port, ae_title=AE_TITLE)
    assert assoc.is_rejected
    wait_for(lambda: any(e.kind == "calling_ae" for e in svc.events(DicomRefused)), "calling-AE refusal")

    # the service keeps serving; what was stored is still there
    assert svc.client.get("/status").status_code == 200
    assert svc.scan(good_uid) == before


def test_folder_and_cstore_paths_run_at_once(svc: Service) -> None:
    from tests.helpers.dicom_factory import ramp_volume, write_series

    staging = svc.root / "staging-folder-path"
    folder_files = write_series(staging, ramp_volume(6, 32, 32))
    folder_uid = str(pydicom.dcmread(folder_files[0]).SeriesInstanceUID)
    sops = {str(pydicom.dcmread(f).SOPInstanceUID) for f in folder_files}
    cstore_files = sorted(Path(p) for p in write_series(svc.root / "outbox" / "both", ramp_volume(6, 32, 32)))
    cstore_uid = str(pydicom.dcmread(cstore_files[0]).SeriesInstanceUID)
    (svc.root / "watch").mkdir(exist_ok=True)
    staging.rename(svc.root / "watch" / "series-a")  # the O-arm's folder export, atomically
    assert set(send_files(svc.dicom_port, cstore_files)) == {0}
    a, b = svc.wait_scan(folder_uid, "complete"), svc.wait_scan(cstore_uid, "complete")
    assert "dicom-intake" in b["folder"] and "dicom-intake" not in a["folder"]
    expected = {folder_uid: sops, cstore_uid: {str(pydicom.dcmread(f).SOPInstanceUID) for f in cstore_files}}
    for uid, want in expected.items():  # what the SRO references, stored on both paths
        inst = wait_for(lambda u=uid: svc.ctx.db.scan_instances.get(u), f"instance UIDs of {uid}")
        assert set(inst.sop_instance_uids) == want


# ---------------------------------------------------------------------------- OpenIGTLink


def receive(client: Any, device: str, pred: Callable[[Any], bool], what: str) -> Any:
    def one() -> Any:
        m = client.wait_for_message(device, timeout=0.2)
        return m if m is not None and pred(m) else None

    return wait_for(one, what, timeout_s=20)


def test_igtl_registration_equals_rest_and_tool_follows_the_robot(svc: Service, current: Current) -> None:
    reg = svc.client.get("/registration/current").json()
    m_lps = np.asarray(reg["image_from_robot"])
    clients = [pyigtl.OpenIGTLinkClient(host="127.0.0.1", port=svc.igtl_port) for _ in range(2)]
    stalled = socket.create_connection(("127.0.0.1", svc.igtl_port))  # never reads, never writes
    stalled.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4096)
    for c in clients:  # as Slicer does at connect: announce header version 2 to get the metadata
        hello = pyigtl.StringMessage("reads header version 2", device_name="Hello")
        hello.header_version = 2
        c.send_message(hello, wait=False)
    try:
        for c in clients:
            rx = receive(c, "RobotToImage", lambda m: m.metadata.get("RegistrationId") == str(reg["id"]),
                         "RobotToImage of the current registration")  # fmt: skip
            assert rx.metadata["TransformStatus"] == "OK"
            assert rx.metadata["Evidence"] == reg["evidence"]["level"]  # issue 40: what backs the robot side
            chain_mm = float(rx.metadata["ChainError_pred_mm"])  # the registration's chain figure
            assert chain_mm == pytest.approx(reg["predicted_chain_error_mm"], abs=1e-3)
            expected = RAS_FROM_LPS @ m_lps  # the documented conversion
            assert np.abs(rx.matrix[:3, 3] - expected[:3, 3]).max() <= 1e-4  # mm
            assert np.abs(rx.matrix[:3, :3] - expected[:3, :3]).max() <= 1e-6
        # move the robot: ToolToImage follows at the link rate, for both clients
        q2 = tuple(a + b for a, b in zip(Q1, (0.0, 0.0, 0.0, 0.0, 0.0, 0.3), strict=True))
        svc.robot.move_to(q2, 0.3)
        joints = wait_for(
            lambda: (
                (j := svc.client.get("/robot/joints").json())
                and np.allclose(j["joints_rad"], q2, atol=1e-6)
                and j
            ),
            "the link to report the new joints",
        )
        fk = svc.ctx.robot_model.robot_from_tool0(joints["joints_rad"])
        expected_tool = RAS_FROM_LPS @ m_lps @ fk
        for c in clients:
            rx = receive(c, "ToolToImage",
                         lambda m: m.metadata.get("TransformStatus") == "OK"
                         and np.abs(m.matrix[:3, 3] - expected_tool[:3, 3]).max() < 1e-3
                         and np.abs(m.matrix[:3, :3] - expected_tool[:3, :3]).max() < 1e-5,
                         "ToolToImage at the robot's new pose")  # fmt: skip
            assert rx.metadata["RegistrationId"] == str(reg["id"])
            assert rx.metadata["Evidence"] == reg["evidence"]["level"]
        listeners = svc.client.get("/status").json()["listeners"]["igtl"]
        assert listeners["clients"] >= 3
        versions = {p["peer"]: p["header_version"] for p in listeners["peers"]}
        stalled_peer = "{}:{}".format(*stalled.getsockname())
        assert versions[stalled_peer] == 1  # it never wrote: version 1 (issue #23)
        assert sorted(versions.values()).count(2) >= 2  # the two pyigtl clients announced version 2
        assert {e.header_version for e in svc.events(IgtlClientHeaderVersion)} == {2}
        assert {e.peer.split(":")[0] for e in svc.events(IgtlClientConnected)} == {"127.0.0.1"}
    finally:
        for c in clients:
            c.stop()
        stalled.close()
    svc.robot.move_to(Q1, 0.01)


def test_own_decoder_and_pyigtl_agree_on_the_wire(svc: Service, current: Current) -> None:
    """The demo's fallback (plain socket + service.navigation.igtl.wire) reads what pyigtl reads."""
    from service.navigation.igtl.probe import _receive_raw, receive_transform

    rid = str(current.registration["id"])
    a = receive_transform("127.0.0.1", svc.igtl_port, "RobotToImage", registration_id=rid)
    b = _receive_raw("127.0.0.1", svc.igtl_port, "RobotToImage", rid, 10.0)
    assert a.via.startswith("pyigtl") and b.via.startswith("service.navigation.igtl.wire")
    np.testing.assert_array_equal(a.matrix, b.matrix)
    assert a.metadata["RegistrationId"] == b.metadata["RegistrationId"] == rid


# ---------------------------------------------------------------------------- SRO, TLS


@pytest.mark.skipif(DCIODVFY is None, reason="dicom3tools dciodvfy not installed")
def test_sro_from_the_api_has_no_dciodvfy_errors(svc: Service, current: Current, tmp_path: Path) -> None:
    from registration.io.sro import image_from_robot_of
    from service.registrations.robot_frame import robot_frame_uid

    reg = current.registration
    r = svc.client.get(f"/registrations/{reg['id']}/dicom")
    assert r.status_code == 200 and r.headers["content-type"] == "application/dicom"
    path = tmp_path / "sro.dcm"
    path.write_bytes(r.content)
    out = subprocess.run([DCIODVFY, str(path)], capture_output=True, text=True, timeout=60)
    text = out.stdout + out.stderr
    assert [ln for ln in text.splitlines() if ln.startswith("Error")] == [], text
    ds = pydicom.dcmread(path)
    m = image_from_robot_of(ds, robot_frame_uid(svc.root / "data"))
    np.testing.assert_allclose(m, np.asarray(reg["image_from_robot"]), atol=1e-9)
    refs = ds.ReferencedSeriesSequence[0]
    assert refs.SeriesInstanceUID == reg["series_uid"] and len(refs.ReferencedInstanceSequence) > 10
    assert svc.client.get(f"/registrations/{reg['id']}/dicom").content == r.content  # stable UIDs
    assert svc.client.get("/registrations/999999/dicom").status_code == 404
    assert svc.client.get("/registrations/0/dicom").status_code == 422


def test_reg_read_as_slicerrt_equals_robot_to_image(svc: Service, current: Current) -> None:
    """Issue 31 item 5: the REG object from the API, read as SlicerRT reads it
    (tests/helpers/slicerrt_sro.py), is the transform pyigtl receives as ``RobotToImage``: the same
    robot point lands at the same RAS point (825 mm apart before, with both sides flipped)."""
    from tests.helpers.slicerrt_sro import slicerrt_transform_to_parent

    rid = str(current.registration["id"])
    r = svc.client.get(f"/registrations/{rid}/dicom")
    assert r.status_code == 200
    slicer = slicerrt_transform_to_parent(pydicom.dcmread(BytesIO(r.content)))
    client = pyigtl.OpenIGTLinkClient(host="127.0.0.1", port=svc.igtl_port)
    hello = pyigtl.StringMessage("reads header version 2", device_name="Hello")
    hello.header_version = 2
    client.send_message(hello, wait=False)
    try:
        rx = receive(client, "RobotToImage", lambda m: m.metadata.get("RegistrationId") == rid,
                     "RobotToImage of the registration")  # fmt: skip
    finally:
        client.stop()
    for p_robot in ([350.0, 120.0, 40.0], [-400.0, 300.0, 250.0], [0.0, 0.0, 0.0]):
        p = np.array([*p_robot, 1.0])
        assert np.abs(slicer @ p - rx.matrix @ p).max() <= 1e-3, (p_robot, slicer @ p, rx.matrix @ p)


def test_refused_registration_has_no_sro_and_is_pushed_as_last_refusal(svc: Service) -> None:
    """Auto-register refuses a scan without spheres: the refusal is stored (no SRO) and reaches an
    OpenIGTLink client as ``LastRefusal`` (the bus's ``registration_refused`` → the IGTL publisher)."""
    from tests.helpers.dicom_factory import ramp_volume, write_series

    client = pyigtl.OpenIGTLinkClient(host="127.0.0.1", port=svc.igtl_port)
    hello = pyigtl.StringMessage("reads header version 2", device_name="Hello")
    hello.header_version = 2  # the metadata needs version 2
    client.send_message(hello, wait=False)
    try:
        files = sorted(
            Path(p) for p in write_series(svc.root / "outbox" / "nospheres", ramp_volume(6, 32, 32))
        )
        uid = str(pydicom.dcmread(files[0]).SeriesInstanceUID)
        send_files(svc.dicom_port, files)
        scan = svc.wait_scan(uid, "complete")
        refused = wait_for(
            lambda: next(
                (r for r in svc.client.get("/registrations").json() if r["scan_id"] == scan["id"]), None
            ),
            "the auto-registration attempt",
        )
        assert refused["status"] == "refused"
        assert any(e.registration_id == refused["id"] for e in svc.events(RegistrationRefused))
        rx = receive(client, "RobotToImage",
                     lambda m: m.metadata.get("LastRefusal", "").startswith(f"{refused['id']}: "),
                     "RobotToImage naming the refusal")  # fmt: skip
        assert refused["reason"][:100] in rx.metadata["LastRefusal"]
    finally:
        client.stop()
    r = svc.client.get(f"/registrations/{refused['id']}/dicom")
    assert r.status_code == 409 and r.headers["content-type"].startswith("application/problem+json")


@pytest.mark.skipif(CURL is None, reason="curl not installed")
def test_curl_reaches_the_api_over_tls(svc: Service) -> None:
    url = svc.base_url + "/status"
    assert url.startswith("https://")
    auth = f"Authorization: Bearer {TOKEN}"
    r = subprocess.run([CURL, "-sS", "--fail", "--cacert", str(svc.ca), "-H", auth, url],
                       capture_output=True, text=True, timeout=30)  # fmt: skip
    assert r.returncode == 0, r.stderr
    assert '"listeners"' in r.stdout
    r = subprocess.run([CURL, "-sS", url], capture_output=True, text=True, timeout=30)  # no CA: refused
    assert r.returncode == 60, (r.returncode, r.stderr)


def test_hidden_transform_recovered(svc: Service, current: Current) -> None:
    """The auto-registration of the C-STORE scan recovers the simulator's hidden transform."""
    t0p = transform_from_xyz_rpy([0, 0, 200], [180, 0, 0])
    truth = IMAGE_FROM_PHANTOM_1 @ invert(svc.ctx.robot_model.robot_from_tool0(Q1) @ t0p)
    m = np.asarray(current.registration["image_from_robot"])
    assert np.abs(m[:3, 3] - truth[:3, 3]).max() < 1.0
