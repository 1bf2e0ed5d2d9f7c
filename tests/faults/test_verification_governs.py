"""Issue #31 item 1 against the real service: a verification governs the current registration, and
making a registration current is a rule (docs/safety.md, "Which registration may be current").

One service per module (mock simple_message controller, uvicorn on loopback); the scans are the
simulator's ``small`` preset, simulated once.  The displaced-phantom scans are the Q2 scan exported
with its geometry shifted (the phantom appears ``shift`` mm away from where the robot put it: a
knocked phantom or a moved O-arm, as the verification sees it).  Each test registers its own scan
first, so any one passes alone and in any order.  No sleeps: waits poll with a deadline or read
server-sent events.
"""

from __future__ import annotations

import contextlib
import socket
import subprocess
import threading
from collections.abc import Iterator
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from registration.model.frames import invert, transform_from_xyz_rpy
from tests.faults._service import DEADLINE_S, Q1, Events, Svc, in_process_service
from tests.helpers.igtl_ref import needs_ref_client
from tests.helpers.scan_cache import simulated_scan

Q2 = (*Q1[:5], Q1[5] + 0.3)
"""The verification pose: J6 turned 0.3 rad (the phantom spins about its own axis)."""
GATE_MM = 1.5
"""quality.max_verification_error_mm of this module's service: above the nominal model's chain
figure (1.0 mm), so a failure here is blamed on the phantom or the O-arm, not the calibration (the
browser test covers the other cause with the default 1.0 mm gate)."""


@dataclass
class World:
    phantom: Any
    model: Any
    scan1: Any
    scan2: Any


@pytest.fixture(scope="module")
def world(phantom: Any) -> World:
    from mocks.oarm.simulator import AcquisitionSettings
    from registration.model.kinematics import RobotModel

    model = RobotModel.load("tx60")
    t0p = transform_from_xyz_rpy([0, 0, 200], [180, 0, 0])
    image_from_phantom_1 = transform_from_xyz_rpy([2.0, -3.0, 1.0], [10.0, -6.0, 20.0])
    image_from_robot = image_from_phantom_1 @ invert(model.robot_from_tool0(Q1) @ t0p)
    small = AcquisitionSettings.preset("small")
    scan1 = simulated_scan(phantom, image_from_phantom_1, small)
    image_from_phantom_2 = image_from_robot @ model.robot_from_tool0(Q2) @ t0p
    scan2 = simulated_scan(phantom, image_from_phantom_2, AcquisitionSettings.preset("small", seed=1))
    return World(phantom, model, scan1, scan2)


@pytest.fixture(scope="module")
def svc(tmp_path_factory: pytest.TempPathFactory, world: World) -> Iterator[Svc]:
    root = tmp_path_factory.mktemp("governs")
    # OpenIGTLink on, with a push period far beyond any wait here: what a client sees after a
    # withdrawal must come from the withdrawal itself, not from the next periodic push
    with in_process_service(
        root,
        world.phantom,
        world.model,
        **{
            "quality.max_verification_error_mm": GATE_MM,
            "igtl.enabled": True,
            "igtl.port": 0,
            "igtl.period_s": 60.0,
        },
    ) as s:
        yield s


def _export(svc: Svc, scan: Any, q: tuple[float, ...], *, shift_mm: float = 0.0, for_uid: str = "") -> Any:
    """Hold the robot at ``q``, export ``scan`` (its image shifted ``shift_mm`` along x, its
    FrameOfReferenceUID set when given) into the watch folder; the scan record once complete."""
    from mocks.oarm.dicom_export import write_dicom_series

    if not np.allclose(svc.robot.joints_rad_at(), q, atol=1e-9):
        svc.robot.move_to(q, duration_s=0.01)
    svc.wait_still()
    if shift_mm:
        moved = scan.image_from_voxel.copy()
        moved[0, 3] += shift_mm
        scan = replace(scan, image_from_voxel=moved)
    svc.n += 1
    staging = svc.watch.parent / f"staging-{svc.n}"
    exported = write_dicom_series(scan, staging, write_truth=False, frame_of_reference_uid=for_uid or None)
    uid = str(exported.series_uid)
    staging.rename(svc.watch / f"scan-{svc.n}")
    return svc.scan_where(
        lambda s: s["series_uid"] == uid and s["status"] == "complete" and s["joints"] is not None,
        f"scan {uid} recorded complete",
    )


def _registered(svc: Svc, world: World, for_uid: str = "") -> dict[str, Any]:
    scan = _export(svc, world.scan1, Q1, for_uid=for_uid)
    r = svc.client.post("/register", json={"scan_id": scan["id"]})
    assert r.status_code == 200, r.text
    assert svc.client.get("/registration/current").json()["id"] == r.json()["id"]
    return r.json()  # type: ignore[no-any-return]


class IgtlWatch:
    """A plain OpenIGTLink client (socket + :mod:`service.navigation.igtl.wire`, the decoder the demo shares
    with
    pyigtl: tests/integration/test_or_integration.py) that records every message on a thread."""

    def __init__(self, port: int) -> None:
        self.sock = socket.create_connection(("127.0.0.1", port), timeout=DEADLINE_S)
        self.messages: list[Any] = []
        self.cond = threading.Condition()
        self.thread = threading.Thread(target=self._read, daemon=True)
        self.thread.start()

    def _exact(self, n: int) -> bytes:
        buf = b""
        while len(buf) < n:
            chunk = self.sock.recv(n - len(buf))
            if not chunk:
                raise EOFError
            buf += chunk
        return buf

    def _read(self) -> None:
        from service.navigation.igtl import wire

        with contextlib.suppress(OSError, EOFError):
            while True:
                head = self._exact(wire.HEADER_SIZE)
                header = wire.unpack_header(head)
                msg = wire.unpack_body(header, self._exact(header.body_size))
                with self.cond:
                    self.messages.append(msg)
                    self.cond.notify_all()

    def wait(self, pred: Any, what: str, timeout_s: float = DEADLINE_S) -> Any:
        with self.cond:
            got = self.cond.wait_for(lambda: any(pred(m) for m in self.messages), timeout_s)
            seen = [(m.header.type, m.header.device_name) for m in self.messages]
            assert got, f"no OpenIGTLink message: {what}; got {seen}"
            return next(m for m in self.messages if pred(m))

    def close(self) -> None:
        self.sock.close()
        self.thread.join(DEADLINE_S)


def _igtl_port(svc: Svc) -> int:
    return int(svc.client.get("/status").json()["listeners"]["igtl"]["port"])


def _problem(r: Any, status: int) -> dict[str, Any]:
    assert r.status_code == status, r.text
    assert r.headers["content-type"].startswith("application/problem+json")
    return r.json()  # type: ignore[no-any-return]


@needs_ref_client
@pytest.mark.parametrize("shift_mm", [2.0, 10.0])
def test_a_failed_verification_withdraws_the_registration(
    svc: Svc, world: World, shift_mm: float, ref_client: Path
) -> None:
    from service.navigation.igtl import wire

    reg = _registered(svc, world)
    displaced = _export(svc, world.scan2, Q2, shift_mm=shift_mm)
    igtl = IgtlWatch(_igtl_port(svc))
    try:
        igtl.wait(lambda m: (m.header.type, m.header.device_name) == ("TRANSFORM", "RobotToImage"),
                  "RobotToImage on connect while the registration is current")  # fmt: skip
        with Events(svc) as events:
            v = svc.client.post("/verify", json={"scan_id": displaced["id"]})
            withdrawn = events.wait("registration_withdrawn", lambda d: d["registration_ids"] == [reg["id"]])
        # navigation learns it at once (well inside the 60 s period): a non-OK STATUS under the device's name
        status = igtl.wait(lambda m: (m.header.type, m.header.device_name) == ("STATUS", "RobotToImage"),
                           "RobotToImage STATUS after the withdrawal", timeout_s=20.0)  # fmt: skip
        code, _sub, _name, text = wire.unpack_status_content(status.content)
        assert code != 1 and "withdrawn" in text, (code, text)
        n_after = igtl.messages.index(status)
        after = [(m.header.type, m.header.device_name) for m in igtl.messages[n_after:]]
        # Slicer's query (OpenIGTLinkIO's GET_TRANS, sent by the reference library) gets a STATUS
        # naming the withdrawal, never a matrix
        ref = subprocess.run(
            [str(ref_client), "127.0.0.1", str(_igtl_port(svc)), "query", "RobotToImage"],
            capture_output=True, text=True, timeout=DEADLINE_S,
        )  # fmt: skip
        assert ref.returncode == 0, f"reference client exit {ref.returncode}:\n{ref.stdout}\n{ref.stderr}"
        assert "TRANSFORM RobotToImage" not in ref.stdout, ref.stdout
        answer = next(ln for ln in ref.stdout.splitlines() if ln.startswith("STATUS RobotToImage "))
        assert "crc=ok" in answer and " code=1 " not in answer and "withdrawn" in answer, answer
        assert ("TRANSFORM", "RobotToImage") not in after, "a RobotToImage matrix after the withdrawal"
    finally:
        igtl.close()
    if shift_mm < 5.0:  # measured: fails its gate
        ver = v.json()
        assert v.status_code == 200 and not ver["passed"] and ver["max_mm"] > GATE_MM, v.text
        ver_id = ver["id"]
    else:  # beyond what matching bridges (verify_gate_mm 5 mm): cannot be computed
        body = _problem(v, 409)
        assert f"registration {reg['id']} is withdrawn" in body["detail"], body
        ver_id = None
    assert withdrawn["was_current"] and withdrawn["scan_id"] == reg["scan_id"]
    assert withdrawn["verification_scan_id"] == displaced["id"]
    assert withdrawn.get("verification_id") == ver_id
    # nothing is served any more, and the refusal names the verification
    cur = _problem(svc.client.get("/registration/current"), 409)
    assert cur["registration_id"] == reg["id"] and cur["verification_scan_id"] == displaced["id"]
    assert cur["verification_id"] == ver_id
    named = (
        f"verification {ver_id} (scan {displaced['id']})"
        if ver_id
        else f"verification of scan {displaced['id']}"
    )
    assert named in cur["detail"], cur["detail"]
    assert cur["likely_cause"] == "phantom-or-oarm-moved"
    assert "check the phantom's mount" in cur["action"] and "register" in cur["action"]
    ready = svc.client.get("/ready")
    assert ready.status_code == 503, ready.text
    problems = {p["type"]: p for p in ready.json()["problems"]}
    assert f"registration {reg['id']} was withdrawn" in problems["registration-withdrawn"]["detail"]
    status = svc.client.get("/status").json()
    assert status["current_registration"] is None
    assert status["registration_withdrawal"]["registration_id"] == reg["id"]
    stored = svc.client.get(f"/registrations/{reg['id']}").json()
    assert stored["status"] == "withdrawn" and stored["withdrawn_by_scan"] == displaced["id"]
    assert stored["withdrawn_by_verification"] == ver_id
    # the withdrawn registration's scan may not be made current again (rule B), naming the verification scan
    again = _problem(svc.client.post("/register", json={"scan_id": reg["scan_id"]}), 409)
    assert again["title"] == "Superseded by a newer scan" and again["newer_scan_id"] == displaced["id"]
    assert again["rule"] == "withdrawn"
    assert svc.client.get("/registration/current").status_code == 409


@needs_ref_client
def test_a_client_switching_to_version_2_gets_the_metadata_at_once(
    svc: Svc, world: World, ref_client: Path
) -> None:
    """Issue #31 item 4, read by the reference library as Slicer connects: it reads version 1, then
    sends a version-2 STATUS (SlicerOpenIGTLink's first message) and must get ``RobotToImage`` with
    its metadata at once. This service's push period is 60 s and the client gives up after 10 s
    without a message for it, so only the switch itself can send it (before: the next periodic
    push, 16.8 s later in the report)."""
    reg = _registered(svc, world)
    proc = subprocess.run(
        [str(ref_client), "127.0.0.1", str(_igtl_port(svc)), "1", "1"],  # 1 RobotToImage v1, then 1 v2
        capture_output=True, text=True, timeout=DEADLINE_S,
    )  # fmt: skip
    assert proc.returncode == 0, f"reference client exit {proc.returncode}:\n{proc.stdout}\n{proc.stderr}"
    v2 = [ln for ln in proc.stdout.splitlines() if ln.startswith("V2 TRANSFORM RobotToImage ")]
    assert v2 and "crc=ok" in v2[0], proc.stdout
    assert "TransformStatus=OK" in v2[0] and f"RegistrationId={reg['id']}" in v2[0], v2[0]


def _evidence_over_igtl(svc: Svc, ref_client: Path) -> str:
    """``Evidence`` of ``RobotToImage`` as the reference library reads it (version 2, as Slicer)."""
    proc = subprocess.run(
        [str(ref_client), "127.0.0.1", str(_igtl_port(svc)), "1", "1"],
        capture_output=True, text=True, timeout=DEADLINE_S,
    )  # fmt: skip
    assert proc.returncode == 0, f"reference client exit {proc.returncode}:\n{proc.stdout}\n{proc.stderr}"
    v2 = next(ln for ln in proc.stdout.splitlines() if ln.startswith("V2 TRANSFORM RobotToImage "))
    return next(w.split("=", 1)[1].rstrip(";") for w in v2.split() if w.startswith("Evidence="))


@needs_ref_client
def test_a_passing_verification_at_a_moved_pose_keeps_the_registration_current_and_first_the_chain_figure(
    svc: Svc, world: World, ref_client: Path
) -> None:
    reg = _registered(svc, world)
    # issue #31 item 6: the honest figure first, the one-scan TRE labelled as what it is
    body = svc.client.get("/registration/current").json()
    assert list(body)[:2] == ["evidence", "expected_error"]  # what backs the robot side, then the figure
    assert body["evidence"]["level"] == "unverified"
    assert _evidence_over_igtl(svc, ref_client) == "unverified"  # issue 40, as Slicer reads it
    e = body["expected_error"]
    assert e["predicted_chain_error_mm"] == reg["predicted_chain_error_mm"] == 1.0  # the nominal prior
    assert e["calibrated"] is False and "not calibrated" in e["basis"]
    assert e["one_scan_tre_max_mm"] == max(body["predicted_tre_mm"])
    assert e["one_scan_tre_label"] == "one-scan TRE, this pose only"
    scan = _export(svc, world.scan2, Q2)
    v = svc.client.post("/verify", json={"scan_id": scan["id"]})
    assert v.status_code == 200 and v.json()["passed"], v.text
    cur = svc.client.get("/registration/current")
    assert cur.status_code == 200 and cur.json()["id"] == reg["id"]
    # issue 40: a pass at another pose upgrades the evidence, on REST and OpenIGTLink alike
    assert cur.json()["evidence"]["level"] == "verified"
    assert _evidence_over_igtl(svc, ref_client) == "verified"
    ready = svc.client.get("/ready").json()
    assert "registration-withdrawn" not in {p["type"] for p in ready["problems"]}, ready
    assert svc.client.get("/status").json()["registration_withdrawal"] is None


def test_an_older_scan_is_not_made_current_over_a_newer_ones_registration(svc: Svc, world: World) -> None:
    from pydicom.uid import generate_uid

    placement = str(generate_uid())
    older = _registered(svc, world, for_uid=placement)
    newer_scan = _export(svc, world.scan1, Q1, for_uid=placement)
    # the newer scan's arrival withdraws nothing by itself
    assert svc.client.get("/registration/current").json()["id"] == older["id"]
    newer = svc.client.post("/register", json={"scan_id": newer_scan["id"]})
    assert newer.status_code == 200, newer.text
    body = _problem(svc.client.post("/register", json={"scan_id": older["scan_id"]}), 409)
    assert body["newer_scan_id"] == newer_scan["id"] and body["rule"] == "newer-registration"
    assert f"newer scan {newer_scan['id']}" in body["detail"] and "allow_superseded" in body["detail"]
    assert svc.client.get("/registration/current").json()["id"] == newer.json()["id"]
    # the override needs a reason
    _problem(svc.client.post("/register", json={"scan_id": older["scan_id"], "allow_superseded": True}), 422)
    why = "newer scan was of the wrong level; surgeon confirmed"
    r = svc.client.post(
        "/register", json={"scan_id": older["scan_id"], "allow_superseded": True, "reason": why}
    )
    assert r.status_code == 200, r.text
    over = r.json()["provenance"]["superseded_override"]
    assert over["newer_scan_id"] == newer_scan["id"] and over["reason"] == why
    assert svc.client.get("/registration/current").json()["id"] == r.json()["id"]
    audit = [e for e in svc.client.get("/audit").json() if e["target_id"] == r.json()["id"]]
    assert ("register", "superseded-override") in {(e["action"], e["outcome"]) for e in audit}, audit
    assert any(why in e["detail"] and f"newer scan {newer_scan['id']}" in e["detail"] for e in audit), audit
