"""The service's OpenIGTLink stream read by a client built against the reference library (issue #23).

``tests/peers/igtl_ref_client.cxx`` is compiled once per session with g++ against Debian's
``libopenigtlink-dev`` 1.11 (``.ci/run`` installs both when missing).  It reads version-1
TRANSFORMs with ``igtl::TransformMessage::Unpack(1)`` (CRC checked by the library), then sends a
version-2 STATUS as SlicerOpenIGTLink does at connect and reads the version-2 messages that follow.
Before issue #23 the service sent version 2 from the first byte and this client could not read it.
"""

from __future__ import annotations

import subprocess
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from service.events import IgtlClientHeaderVersion
from tests.helpers.igtl_ref import needs_ref_client
from tests.integration.peer_service import PeerService, running_service, send_files, simulated_series

REPO = Path(__file__).resolve().parents[2]
RAS_FROM_LPS = np.diag([-1.0, -1.0, 1.0, 1.0])
CLIENT_TIMEOUT_S = 30.0

pytestmark = needs_ref_client


@dataclass(frozen=True)
class Line:
    version: int
    device: str
    crc_ok: bool
    matrix: np.ndarray | None  # version 1: the upper 3 × 4, from the library's GetMatrix
    metadata: dict[str, str]
    msg_type: str = "TRANSFORM"


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
        if f[0] == "SKIP":  # a version-1 POINT before the switch
            continue
        if f[0] == "V1" and target is before:  # V1 <device> crc=.. 12 numbers
            m = np.eye(4)
            m[:3, :] = np.asarray([float(v) for v in f[3:15]]).reshape(3, 4)
            target.append(Line(1, f[1], f[2] == "crc=ok", m, {}))
        elif f[0] in ("V1", "V2"):  # V<n> <type> <device> crc=.. body=.. [meta k=v; ...]
            meta = {}
            if "meta" in f:
                text = raw.split(" meta", 1)[1]
                meta = dict(kv.strip().split("=", 1) for kv in text.split(";") if kv.strip())
            target.append(Line(int(f[0][1]), f[2], f[3] == "crc=ok", None, meta, f[1]))
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
    assert all(ln.crc_ok for ln in after[first_v2:]), proc.stdout
    # the TRANSFORMs (the POINT has its own test; a ToolToImage whose joints went stale on a loaded
    # machine is a STATUS, never a TRANSFORM: every TRANSFORM says OK)
    v2 = [ln for ln in after[first_v2:] if ln.msg_type == "TRANSFORM"]
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


def query_lines(out: str) -> dict[str, list[str]]:
    """The query mode's lines by their first word."""
    got: dict[str, list[str]] = {}
    for raw in out.splitlines():
        got.setdefault(raw.split(" ", 1)[0], []).append(raw)
    return got


def test_reference_library_queries_are_answered_and_the_spheres_match_the_registration(
    ref_client: Path, svc: tuple[PeerService, dict[str, Any]]
) -> None:
    """Issue #31: the library's ``GET_TRANS`` (what OpenIGTLinkIO sends), ``GET_STATUS``,
    ``GET_CAPABIL`` and ``GET_POINT`` each get their answer, unpacked by the library with its CRC
    check; the ``PhantomSpheres`` POINT list holds the matched spheres in scan RAS, each where
    ``image_from_robot`` maps its robot-frame centre, named with its residual."""
    service, reg = svc
    current = service.client.get("/registration/current").json()
    proc = subprocess.run(
        [str(ref_client), "127.0.0.1", str(service.igtl_port), "query"],
        capture_output=True, text=True, timeout=CLIENT_TIMEOUT_S,
    )  # fmt: skip
    assert proc.returncode == 0, f"client exit {proc.returncode}:\n{proc.stdout}\n{proc.stderr}"
    got = query_lines(proc.stdout)
    assert all(
        "crc=ok" in ln for k in ("TRANSFORM", "STATUS", "CAPABILITY", "POINT") for ln in got.get(k, [])
    )
    answers = got.get("TRANSFORM", []) + got["STATUS"]  # ToolToImage: a STATUS while its joints are stale
    assert any(ln.split(" ")[1] == "ToolToImage" for ln in answers), proc.stdout
    status = next(ln for ln in got["STATUS"] if ln.startswith("STATUS RefClient "))
    assert " code=1 " in status and f"registration {reg['id']} current" in status, status
    types = got["CAPABILITY"][0].split("types=", 1)[1].split(",")
    assert {"TRANSFORM", "POINT", "STATUS", "GET_TRANS", "GET_TRANSFOR", "GET_STATUS", "GET_CAPABIL"} <= set(
        types
    )

    spheres = current["spheres"]
    points = [ln[3:].split("|") for ln in got["PT"]]
    assert got["POINT"][0].startswith(f"POINT PhantomSpheres crc=ok n={len(spheres)}"), got["POINT"]
    assert len(points) == len(spheres) == current["n_matched"]
    want = expected_sphere_centres_ras(service, current)
    for (name, xyz, diameter), sphere, w in zip(points, spheres, want, strict=True):
        assert name == f"{sphere['sphere']} {sphere['residual_mm']:.3f} mm"
        np.testing.assert_allclose([float(v) for v in xyz.split()], w, atol=1e-3)  # float32 on the wire
        assert float(diameter) == pytest.approx(service.ctx.orchestrator.phantom.sphere_diameter_mm)


def expected_sphere_centres_ras(service: PeerService, current: dict[str, Any]) -> np.ndarray:
    """Each matched sphere's centre through ``/registration/current``'s matrix, in RAS: the
    phantom's centre at the scan's joints (the service's robot model and rod), mapped by
    ``image_from_robot`` (LPS), flipped to RAS."""
    from registration.model.kinematics import sphere_centres_robot_mm

    orch = service.ctx.orchestrator
    robot_mm = sphere_centres_robot_mm(
        orch.robot_model, current["joints_rad"], orch.tool0_from_phantom, orch.phantom.centres_phantom_mm
    )
    idx = [s["robot_index"] for s in current["spheres"]]
    homog = np.c_[robot_mm[idx], np.ones(len(idx))]
    return (RAS_FROM_LPS @ np.asarray(current["image_from_robot"]) @ homog.T).T[:, :3]


def test_pyigtl_reads_the_sphere_points_with_their_residuals(svc: tuple[PeerService, dict[str, Any]]) -> None:
    import pyigtl

    from tests.integration.polling import poll_until

    service, _ = svc
    current = service.client.get("/registration/current").json()
    client = pyigtl.OpenIGTLinkClient(host="127.0.0.1", port=service.igtl_port)
    hello = pyigtl.StringMessage("reads header version 2", device_name="Hello")
    hello.header_version = 2
    client.send_message(hello, wait=False)
    try:
        msg = poll_until(
            lambda: (m := client.wait_for_message("PhantomSpheres", timeout=0.2)) is not None
            and m.header_version == 2 and m,
            "the PhantomSpheres POINT in version 2", timeout_s=CLIENT_TIMEOUT_S,
        )  # fmt: skip
    finally:
        client.stop()
    assert msg.metadata["RegistrationId"] == str(current["id"]) and msg.metadata["ImageFrame"] == "RAS"
    residuals = [float(v) for v in msg.metadata["Residuals_mm"].split(",")]
    np.testing.assert_allclose(residuals, [s["residual_mm"] for s in current["spheres"]], atol=1e-4)
    assert msg.metadata["Spheres"].split(",") == [s["sphere"] for s in current["spheres"]]
    np.testing.assert_allclose(
        np.asarray(msg.positions), expected_sphere_centres_ras(service, current), atol=1e-3
    )
