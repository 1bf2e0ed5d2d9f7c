"""The service's OpenIGTLink stream read by a client built against the reference library (issue #23).

``tests/peers/igtl_ref_client.cxx`` is compiled once per session with g++ against Debian's
``libopenigtlink-dev`` 1.11 (``.ci/run`` installs both when missing).  It reads version-1
TRANSFORMs with ``igtl::TransformMessage::Unpack(1)`` (CRC checked by the library), then sends a
version-2 STATUS as SlicerOpenIGTLink does at connect and reads the version-2 messages that follow.
Before issue #23 the service sent version 2 from the first byte and this client could not read it.
"""

from __future__ import annotations

import shutil
import subprocess
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from service.events import IgtlClientHeaderVersion
from tests.integration.peer_service import PeerService, running_service, send_files, simulated_series

REPO = Path(__file__).resolve().parents[2]
SOURCE = REPO / "tests" / "peers" / "igtl_ref_client.cxx"
INCLUDE = Path("/usr/include/openigtlink")
GXX = shutil.which("g++")
RAS_FROM_LPS = np.diag([-1.0, -1.0, 1.0, 1.0])
CLIENT_TIMEOUT_S = 30.0

pytestmark = pytest.mark.skipif(
    GXX is None or not (INCLUDE / "igtlTransformMessage.h").is_file(),
    reason="g++ or libopenigtlink-dev not installed (.ci/run installs them)",
)


@pytest.fixture(scope="session")
def ref_client(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The C++ client, built once per session into a temp folder."""
    assert GXX is not None
    exe = tmp_path_factory.mktemp("igtl-ref") / "igtl_ref_client"
    subprocess.run(
        [GXX, "-O1", "-std=c++11", f"-I{INCLUDE}", str(SOURCE), "-lOpenIGTLink", "-o", str(exe)],
        check=True, capture_output=True, timeout=120,
    )  # fmt: skip
    return exe


@dataclass(frozen=True)
class Line:
    version: int
    device: str
    crc_ok: bool
    matrix: np.ndarray | None  # version 1: the upper 3 × 4, from the library's GetMatrix
    metadata: dict[str, str]


def parse(out: str) -> tuple[list[Line], list[Line]]:
    """(lines before ``SENT_V2_STATUS``, lines after) of the client's output."""
    before: list[Line] = []
    after: list[Line] = []
    target = before
    for raw in out.splitlines():
        if raw == "SENT_V2_STATUS":
            target = after
            continue
        f = raw.split(" ")
        if f[0] == "V1" and target is before:  # V1 <device> crc=.. 12 numbers
            m = np.eye(4)
            m[:3, :] = np.asarray([float(v) for v in f[3:15]]).reshape(3, 4)
            target.append(Line(1, f[1], f[2] == "crc=ok", m, {}))
        elif f[0] in ("V1", "V2"):  # V<n> <type> <device> crc=.. body=.. [meta k=v; ...]
            meta = {}
            if "meta" in f:
                text = raw.split(" meta", 1)[1]
                meta = dict(kv.strip().split("=", 1) for kv in text.split(";") if kv.strip())
            target.append(Line(int(f[0][1]), f[2], f[3] == "crc=ok", None, meta))
        else:
            raise AssertionError(f"unexpected client output line {raw!r}:\n{out}")
    return before, after


@pytest.fixture(scope="module")
def svc(
    tmp_path_factory: pytest.TempPathFactory, phantom: Any
) -> Iterator[tuple[PeerService, dict[str, Any]]]:
    root = tmp_path_factory.mktemp("igtl-ref-svc")
    with running_service(root, phantom) as svc:
        uid, files = simulated_series(phantom, root / "outbox")
        assert set(send_files(svc.dicom_port, files)) == {0}
        scan = svc.wait_scan(uid)
        yield svc, svc.wait_registration(scan["id"])


def test_reference_library_reads_v1_then_v2_after_a_v2_status(
    ref_client: Path, svc: tuple[PeerService, dict[str, Any]]
) -> None:
    service, reg = svc
    current = service.client.get("/registration/current").json()
    assert current["id"] == reg["id"]
    image_from_robot = np.asarray(current["image_from_robot"])
    joints = service.client.get("/robot/joints").json()["joints_rad"]
    tool0_from_tcp = service.ctx.settings.igtl.tool0_from_tcp.matrix()
    robot_from_tcp = service.ctx.robot_model.robot_from_tool0(joints) @ tool0_from_tcp

    proc = subprocess.run(
        [str(ref_client), "127.0.0.1", str(service.igtl_port), "2", "2"],  # RobotToImage counts
        capture_output=True, text=True, timeout=CLIENT_TIMEOUT_S,
    )  # fmt: skip
    assert proc.returncode == 0, f"client exit {proc.returncode}:\n{proc.stdout}\n{proc.stderr}"
    before, after = parse(proc.stdout)

    # version 1, read by the library itself with its CRC check; the documented conversion
    assert before and all(ln.version == 1 and ln.crc_ok for ln in before), proc.stdout
    robot = [ln for ln in before if ln.device == "RobotToImage"]
    tool = [ln for ln in before if ln.device == "ToolToImage"]
    assert len(robot) == 2 and tool, proc.stdout
    want_robot = RAS_FROM_LPS @ image_from_robot
    want_tool = RAS_FROM_LPS @ image_from_robot @ robot_from_tcp
    for ln, want in [*((r, want_robot) for r in robot), *((t, want_tool) for t in tool)]:
        assert ln.matrix is not None
        np.testing.assert_allclose(ln.matrix[:3, 3], want[:3, 3], atol=1e-4)  # mm, float32 on the wire
        np.testing.assert_allclose(ln.matrix[:3, :3], want[:3, :3], atol=1e-6)

    # after the version-2 STATUS: version 1 only for what was already in flight, then version 2 only
    versions = [ln.version for ln in after]
    first_v2 = versions.index(2)
    assert set(versions[first_v2:]) == {2}, proc.stdout
    v2 = after[first_v2:]
    assert all(ln.crc_ok for ln in v2), proc.stdout
    assert {ln.device for ln in v2} == {"RobotToImage", "ToolToImage"}
    for ln in v2:
        assert ln.metadata["TransformStatus"] == "OK", ln
        assert ln.metadata["RegistrationId"] == str(reg["id"])
        assert ln.metadata["ImageFrame"] == "RAS"
    assert float(next(ln for ln in v2 if ln.device == "RobotToImage").metadata["FRE_mm"]) == pytest.approx(
        reg["fre_mm"], rel=1e-5
    )
    switched = service.events(IgtlClientHeaderVersion)
    assert switched and switched[-1].header_version == 2
