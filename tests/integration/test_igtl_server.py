"""OpenIGTLink server against pyigtl's client (an independent peer) and raw sockets, over
loopback (issue #12).  Every server binds port 0."""

from __future__ import annotations

import asyncio
import contextlib
import math
import socket
import statistics
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import pyigtl
import pytest
from polling import wait_until
from pydantic import ValidationError

from drivers.factory import open_link
from mocks.robot.robot import ScriptedRobot
from mocks.robot.runner import run_mock_controller
from registration.model.kinematics import RobotModel
from service.errors import IgtlConfigError
from service.navigation.igtl import wire
from service.navigation.igtl.server import (
    RAS_FROM_LPS,
    IgtlServer,
    IgtlStateSource,
    JointView,
    Refusal,
    RegistrationState,
    RegistrationView,
    SpherePoint,
    registration_messages,
)
from service.settings import IgtlSettings

RX_TIMEOUT_S = 5.0


def rigid(rx_deg: float, rz_deg: float, t: Sequence[float]) -> np.ndarray:
    a, c = math.radians(rx_deg), math.radians(rz_deg)
    rx = np.array([[1, 0, 0], [0, math.cos(a), -math.sin(a)], [0, math.sin(a), math.cos(a)]])
    rz = np.array([[math.cos(c), -math.sin(c), 0], [math.sin(c), math.cos(c), 0], [0, 0, 1]])
    m = np.eye(4)
    m[:3, :3] = rz @ rx
    m[:3, 3] = t
    return m


IMAGE_FROM_ROBOT = rigid(23.0, -71.0, [-412.25, 233.5, -80.125])
REG = RegistrationView(IMAGE_FROM_ROBOT, "reg-0007", fre_mm=0.4123, tre_pred_mm=0.61)


@dataclass
class Holder:
    """A scripted state source the tests mutate."""

    reg: RegistrationState
    joints: JointView | None = None

    def source(self, fk: Callable[[Sequence[float]], np.ndarray] | None = None, tcp: Any = None) -> Any:
        return IgtlStateSource(
            registration=lambda: self.reg,
            joints=lambda: self.joints,
            robot_from_tool0=fk or (lambda q: rigid(0.0, math.degrees(q[0]), [q[1], 0.0, 0.0])),
            tool0_from_tcp=np.eye(4) if tcp is None else tcp,
        )


def assert_transform_close(got: np.ndarray, want: np.ndarray) -> None:
    np.testing.assert_allclose(got[:3, :3], want[:3, :3], atol=1e-6)
    np.testing.assert_allclose(got[:3, 3], want[:3, 3], atol=1e-4)


async def receive(
    client: pyigtl.OpenIGTLinkClient, device: str, pred: Callable[[Any], bool], *, v2: bool = True
) -> Any:
    """The first message from ``device`` satisfying ``pred`` (deadline, no sleeps); with ``v2``
    only header-version-2 messages count (the server sends version 1 until the client wrote v2)."""
    deadline = time.monotonic() + RX_TIMEOUT_S
    while time.monotonic() < deadline:
        msg = await asyncio.to_thread(client.wait_for_message, device, 0.5)
        if msg is not None and (msg.header_version == 2 or not v2) and pred(msg):
            return msg
    raise AssertionError(f"no {device} message satisfying the condition within {RX_TIMEOUT_S} s")


def status_is(s: str) -> Callable[[Any], bool]:
    return lambda m: m.metadata.get("TransformStatus") == s


class RawClient:
    """A client on a plain socket that records every message (pyigtl skips STATUS and
    CAPABILITY); with ``v2`` it first announces header version 2 with a STATUS, as Slicer does."""

    def __init__(self) -> None:
        self.messages: list[wire.Message] = []
        self.task: asyncio.Task[None] | None = None
        self.writer: asyncio.StreamWriter | None = None

    @classmethod
    async def connect(cls, port: int, *, v2: bool) -> RawClient:
        self = cls()
        reader, self.writer = await asyncio.open_connection("127.0.0.1", port)
        if v2:
            self.writer.write(wire.pack_status("Hello", timestamp_s=time.time()))
        self.task = asyncio.create_task(self._read(reader))
        return self

    async def _read(self, reader: asyncio.StreamReader) -> None:
        with contextlib.suppress(asyncio.IncompleteReadError, ConnectionError):
            while True:
                head = wire.unpack_header(await reader.readexactly(wire.HEADER_SIZE))
                self.messages.append(wire.unpack_body(head, await reader.readexactly(head.body_size)))

    def send(self, raw: bytes) -> None:
        assert self.writer is not None
        self.writer.write(raw)

    async def wait(self, pred: Callable[[wire.Message], bool], what: str, *, after: int = 0) -> wire.Message:
        """The first message from index ``after`` on that satisfies ``pred``."""
        found: list[wire.Message] = []

        def hit() -> bool:
            found[:] = [m for m in self.messages[after:] if pred(m)]
            return bool(found)

        await wait_until(hit, what, RX_TIMEOUT_S)
        return found[0]

    async def close(self) -> None:
        if self.writer is not None:
            self.writer.close()
        if self.task is not None:
            self.task.cancel()
            await asyncio.gather(self.task, return_exceptions=True)


def is_msg(msg_type: str, device: str, **meta: str) -> Callable[[wire.Message], bool]:
    return lambda m: (
        m.header.type == msg_type
        and m.header.device_name == device
        and all(m.metadata.get(k) == v for k, v in meta.items())
    )


async def started(holder: Holder, **cfg: Any) -> IgtlServer:
    server = IgtlServer(IgtlSettings(port=0, **cfg), holder.source())
    await server.start()
    return server


def pyigtl_client(port: int, *, announce_v2: bool = True) -> pyigtl.OpenIGTLinkClient:
    """pyigtl's client; with ``announce_v2`` it first sends a version-2 STRING, as Slicer sends its
    version-2 STATUS at connect (pyigtl itself sends nothing unasked and packs version 1 by default)."""
    client = pyigtl.OpenIGTLinkClient(host="127.0.0.1", port=port)
    if announce_v2:
        hello = pyigtl.StringMessage("reads header version 2", device_name="Hello")
        hello.header_version = 2
        client.send_message(hello, wait=False)
    return client


def test_registration_sent_in_ras_with_figures() -> None:
    async def main() -> None:
        server = await started(Holder(RegistrationState(REG)))
        client = pyigtl_client(server.port)
        try:
            msg = await receive(client, "RobotToImage", status_is("OK"))
        finally:
            client.stop()
            await server.stop()
        # The documented matrix: ras_from_robot = diag(-1,-1,1,1) @ image_from_robot(LPS).
        assert_transform_close(np.asarray(msg.matrix), RAS_FROM_LPS @ IMAGE_FROM_ROBOT)
        assert msg.header_version == 2
        assert msg.metadata["RegistrationId"] == "reg-0007"
        assert float(msg.metadata["FRE_mm"]) == pytest.approx(0.4123)
        assert float(msg.metadata["TRE_pred_mm"]) == pytest.approx(0.61)
        assert msg.metadata["ImageFrame"] == "RAS"

    asyncio.run(main())


def test_invalid_device_is_a_status_never_a_matrix_then_refusal_keeps_previous_ok() -> None:
    """Issue #31 item 2: without a registration no TRANSFORM reaches any client (an identity used to
    go out, which a version-1 client shows as the tool at the image origin); each device is a
    STATUS with a non-OK code and the reason instead, in both header versions."""
    holder = Holder(RegistrationState(None, no_current_reason="registration 4 was withdrawn: scan changed"))

    async def main() -> None:
        server = await started(holder)
        v1, v2 = await RawClient.connect(server.port, v2=False), await RawClient.connect(server.port, v2=True)
        try:
            for c in (v1, v2):
                for dev in ("RobotToImage", "ToolToImage"):
                    st = await c.wait(is_msg("STATUS", dev), f"{dev} STATUS")
                    code, _, name, text = wire.unpack_status_content(st.content)
                    assert (code, name) == (wire.STATUS_NOT_READY, "INVALID")
                    assert "registration 4 was withdrawn" in text
            await v2.wait(
                lambda m: m.header.version == 2 and m.metadata.get("TransformStatus") == "INVALID", "v2"
            )
            await wait_until(lambda: server.counters["sent"] >= 8, "a few pushes")
            assert not [m for c in (v1, v2) for m in c.messages if m.header.type == "TRANSFORM"]
            holder.reg = RegistrationState(REG)
            server.notify()
            for c in (v1, v2):
                m = await c.wait(is_msg("TRANSFORM", "RobotToImage"), "the transform once current")
                assert_transform_close(
                    wire.unpack_transform_content(m.content), RAS_FROM_LPS @ IMAGE_FROM_ROBOT
                )
            holder.reg = RegistrationState(REG, Refusal("reg-0008", "ambiguous: symmetry margin 0.3 < 2"))
            msg = await v2.wait(lambda m: "LastRefusal" in m.metadata, "the refusal")
        finally:
            await v1.close()
            await v2.close()
            await server.stop()
        assert msg.metadata["TransformStatus"] == "OK"
        assert msg.metadata["RegistrationId"] == "reg-0007"
        assert msg.metadata["LastRefusal"].startswith("reg-0008: ambiguous")

    asyncio.run(main())


def test_send_invalid_transforms_v2_reaches_version_2_clients_only() -> None:
    async def main() -> None:
        server = await started(Holder(RegistrationState(None)), send_invalid_transforms_v2=True, period_s=0.1)
        v1, v2 = await RawClient.connect(server.port, v2=False), await RawClient.connect(server.port, v2=True)
        try:
            m = await v2.wait(is_msg("TRANSFORM", "RobotToImage", TransformStatus="INVALID"), "INVALID v2")
            assert m.metadata["Reason"] == "no current registration"
            await v1.wait(is_msg("STATUS", "RobotToImage"), "the v1 client's STATUS")
            await wait_until(lambda: len(v1.messages) >= 6, "a few pushes to the version-1 client")
        finally:
            await v1.close()
            await v2.close()
            await server.stop()
        assert not [m for m in v1.messages if m.header.type == "TRANSFORM"]

    asyncio.run(main())


def test_two_pyigtl_clients_both_receive_on_connect_and_on_change() -> None:
    holder = Holder(RegistrationState(REG))

    async def main() -> None:
        server = await started(holder)
        clients = [pyigtl_client(server.port), pyigtl_client(server.port)]
        try:
            for c in clients:
                await receive(c, "RobotToImage", status_is("OK"))
            await wait_until(lambda: server.client_count == 2, "two clients")
            other = RegistrationView(rigid(5.0, 10.0, [1.0, 2.0, 3.0]), "reg-0009", fre_mm=0.3)
            holder.reg = RegistrationState(other)
            for c in clients:
                msg = await receive(
                    c, "RobotToImage", lambda m: m.metadata.get("RegistrationId") == "reg-0009"
                )
                assert_transform_close(np.asarray(msg.matrix), RAS_FROM_LPS @ other.image_from_robot)
        finally:
            for c in clients:
                c.stop()
            await server.stop()
        assert server.counters["connects"] == 2

    asyncio.run(main())


def test_tool_to_image_follows_mock_controller_joints_and_goes_invalid_when_stale() -> None:
    model = RobotModel.load("tx60")
    tool0_from_tcp = rigid(0.0, 0.0, [0.0, 0.0, 150.0])
    q1 = [math.radians(d) for d in (10, -20, 95, 5, 30, 45)]
    q2 = [math.radians(d) for d in (-35, 15, 80, -10, 60, 120)]
    robot = ScriptedRobot(q1)

    def expected(q: Sequence[float]) -> np.ndarray:
        q32 = [float(v) for v in np.asarray(q, dtype=np.float32)]  # what the link delivers
        return RAS_FROM_LPS @ IMAGE_FROM_ROBOT @ model.robot_from_tool0(q32) @ tool0_from_tcp

    async def main() -> None:
        with run_mock_controller("simple-message", robot) as mock:
            async with open_link(mock.url, stale_after_s=0.2) as link:

                def joints() -> JointView | None:
                    s, h = link.latest(), link.health()
                    return None if s is None else JointView(s.joints_rad, s.t_s, h.state, h.reason)

                src = IgtlStateSource(
                    lambda: RegistrationState(REG), joints, model.robot_from_tool0, tool0_from_tcp
                )
                server = IgtlServer(IgtlSettings(port=0, send_invalid_transforms_v2=True), src)
                await server.start()
                client = pyigtl_client(server.port)
                try:

                    def close_to(want: np.ndarray) -> Callable[[Any], bool]:
                        return lambda m: status_is("OK")(m) and np.allclose(m.matrix, want, atol=1e-4)

                    await receive(client, "ToolToImage", close_to(expected(q1)))
                    robot.hold(q2)
                    msg = await receive(client, "ToolToImage", close_to(expected(q2)))
                    assert_transform_close(np.asarray(msg.matrix), expected(q2))
                    mock.stall()
                    msg = await receive(client, "ToolToImage", status_is("INVALID"))
                    assert "stale" in msg.metadata["Reason"] or "old" in msg.metadata["Reason"]
                    mock.resume()
                    await receive(client, "ToolToImage", status_is("OK"))
                finally:
                    client.stop()
                    await server.stop()

    asyncio.run(main())


class ChangingJoints:
    """A joint source with a new sample on every call (drives ToolToImage at the poll rate)."""

    def __call__(self) -> JointView:
        t = time.monotonic()
        return JointView((t % 1.0, 0.0), t, "connected")


async def read_ids(reader: asyncio.StreamReader, ids: list[int], arrivals: list[float]) -> None:
    """MSG_IDs of the version-2 messages (the version-1 ones before the switch have none)."""
    while True:
        head = wire.unpack_header(await reader.readexactly(wire.HEADER_SIZE))
        msg = wire.unpack_body(head, await reader.readexactly(head.body_size))
        if head.version == 1:
            assert not ids, "a version-1 message after version-2 ones"
            continue
        ids.append(msg.message_id)
        arrivals.append(time.monotonic())


def test_client_that_never_reads_does_not_delay_the_others_and_is_disconnected() -> None:
    holder = Holder(RegistrationState(REG))
    cfg = IgtlSettings(
        port=0, poll_period_s=0.005, client_queue_max=32, client_buffer_bytes=1024,
        socket_send_buffer_bytes=16 * 1024, slow_client_timeout_s=0.5,
    )  # fmt: skip

    async def main() -> None:
        src = IgtlStateSource(lambda: holder.reg, ChangingJoints(), holder.source().robot_from_tool0)
        server = IgtlServer(cfg, src)
        await server.start()
        ids: list[int] = []
        arrivals: list[float] = []
        reader, writer = await asyncio.open_connection("127.0.0.1", server.port)
        writer.write(wire.pack_status("Hello", timestamp_s=time.time()))
        fast = asyncio.create_task(read_ids(reader, ids, arrivals))
        stuck = socket.socket()
        stuck.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4096)
        stuck.connect(("127.0.0.1", server.port))  # never reads
        try:
            await wait_until(lambda: server.client_count == 2, "both clients connected")
            n_before = len(ids)
            t0 = time.monotonic()
            await wait_until(lambda: server.counters["slow_disconnects"] >= 1, "the stuck client cut", 15.0)
            t1 = time.monotonic()
            n_during = len(ids) - n_before
            await wait_until(lambda: len(ids) > n_before + n_during + 10, "more messages after the cut")
        finally:
            fast.cancel()
            writer.close()
            stuck.close()
            await server.stop()
        gaps = np.diff([a for a in arrivals if t0 <= a <= t1])
        print(f"\nstuck client cut after {t1 - t0:.2f} s; fast client got {n_during} messages meanwhile, "
              f"median gap {statistics.median(gaps) * 1e3:.1f} ms, max {gaps.max() * 1e3:.1f} ms; "
              f"dropped for the stuck one: {server.counters['dropped']}")  # fmt: skip
        assert ids == list(range(ids[0], ids[0] + len(ids))), "the reading client lost or reordered messages"
        assert n_during > 20, f"only {n_during} messages reached the reading client while the other was stuck"
        assert server.counters["dropped"] > 0  # the stuck client's queue overflowed, oldest dropped
        assert server.client_count == 0

    asyncio.run(main())


def test_peer_not_on_allow_list_is_closed_and_listed_peer_served() -> None:
    async def main() -> None:
        server = await started(Holder(RegistrationState(REG)), allowed_peer_addresses=("127.0.0.2",))
        try:
            reader, writer = await asyncio.open_connection("127.0.0.1", server.port)  # from 127.0.0.1
            assert await reader.read(1) == b""
            writer.close()
            await wait_until(lambda: server.counters["refused_peers"] == 1, "the refusal counted")
            reader, writer = await asyncio.open_connection(
                "127.0.0.1", server.port, local_addr=("127.0.0.2", 0)
            )
            head = wire.unpack_header(await reader.readexactly(wire.HEADER_SIZE))
            assert head.device_name in ("RobotToImage", "ToolToImage")
            writer.close()
        finally:
            await server.stop()

    asyncio.run(main())


@pytest.mark.parametrize("host", ["0.0.0.0", "192.168.10.5", "::"])
def test_non_loopback_bind_without_allow_list_refuses_to_start(host: str) -> None:
    """The rule lives in ``IgtlSettings``; a server built from a section (even one not marked
    enabled) is held to it."""
    src = Holder(RegistrationState(REG)).source()
    with pytest.raises(IgtlConfigError, match="allowed_peer_addresses"):
        IgtlServer(IgtlSettings(host=host), src)
    with pytest.raises(ValidationError, match="allowed_peer_addresses"):
        IgtlSettings(host=host, enabled=True)
    IgtlServer(IgtlSettings(host=host, allowed_peer_addresses=("10.0.0.0/24",)), src)  # explicit list: fine


def test_bad_allow_list_entry_refused() -> None:
    with pytest.raises(ValidationError, match="allowed_peer_addresses"):
        IgtlSettings(allowed_peer_addresses=("not-an-ip",))


def test_failing_callbacks_give_invalid_not_a_dead_server() -> None:
    def boom() -> RegistrationState:
        raise RuntimeError("database is locked")

    async def main() -> None:
        src = IgtlStateSource(boom, lambda: None, lambda q: np.eye(4))
        server = IgtlServer(IgtlSettings(port=0), src)
        await server.start()
        client = await RawClient.connect(server.port, v2=True)
        try:
            msg = await client.wait(is_msg("STATUS", "RobotToImage", TransformStatus="INVALID"), "INVALID")
        finally:
            await client.close()
            await server.stop()
        assert "could not be read" in wire.unpack_status_content(msg.content)[3]

    asyncio.run(main())


def query(msg_type: str, device: str = "", *, version: int = 1) -> bytes:
    return wire.pack_message(msg_type, device, b"", timestamp_s=time.time(), header_version=version)


def test_get_trans_in_both_spellings_answers_the_named_device_only() -> None:
    """Issue #31 item 3: the reference library's ``GET_TRANS`` (what OpenIGTLinkIO sends) got
    nothing; ``GET_TRANSFOR`` answered both devices whatever the name.  A 60 s period keeps the
    periodic pushes out of the way: after the on-connect push, only answers arrive."""
    holder = Holder(RegistrationState(REG))

    async def main() -> None:
        server = await started(holder, period_s=60.0)
        c = await RawClient.connect(server.port, v2=False)
        try:
            await c.wait(is_msg("POINT", "PhantomSpheres"), "the on-connect push")
            for spelling in ("GET_TRANS", "GET_TRANSFOR"):
                for device, want in (
                    ("RobotToImage", ["RobotToImage"]),
                    ("ToolToImage", ["ToolToImage"]),
                    ("", ["RobotToImage", "ToolToImage"]),
                ):
                    n = len(c.messages)
                    c.send(query(spelling, device))
                    c.send(query("GET_CAPABIL"))  # a fence: everything before it was answered
                    fence = await c.wait(lambda m: m.header.type == "CAPABILITY", "the fence", after=n)
                    got = c.messages[n : c.messages.index(fence, n)]
                    assert [m.header.device_name for m in got] == want, (spelling, device, got)
            n = len(c.messages)
            c.send(query("GET_TRANS", "NoSuchTool"))
            st = await c.wait(
                lambda m, n=n: c.messages.index(m) >= n and m.header.type == "STATUS", "NOT_FOUND"
            )
        finally:
            await c.close()
            await server.stop()
        code, _, name, text = wire.unpack_status_content(st.content)
        assert (code, name, st.header.device_name) == (4, "NOT_FOUND", "NoSuchTool")
        assert "RobotToImage" in text
        ras = wire.unpack_transform_content(got[0].content)
        assert_transform_close(ras, RAS_FROM_LPS @ IMAGE_FROM_ROBOT)

    asyncio.run(main())


def test_get_status_and_get_capabil_are_answered() -> None:
    holder = Holder(RegistrationState(None))

    async def main() -> None:
        server = await started(holder, period_s=60.0)
        c = await RawClient.connect(server.port, v2=False)
        try:
            c.send(query("GET_STATUS"))
            not_ready = await c.wait(is_msg("STATUS", "oarmreg"), "STATUS without registration")
            holder.reg = RegistrationState(REG)
            holder.joints = JointView((0.1, 0.0), time.monotonic() + 3600, "connected")  # fresh for an hour
            n = len(c.messages)
            c.send(query("GET_STATUS", "Svc"))
            ok = await c.wait(is_msg("STATUS", "Svc"), "OK", after=n)
            c.send(query("GET_CAPABIL"))
            cap = await c.wait(lambda m: m.header.type == "CAPABILITY", "CAPABILITY")
        finally:
            await c.close()
            await server.stop()
        code, _, _, text = wire.unpack_status_content(not_ready.content)
        assert code == wire.STATUS_NOT_READY and "no current registration" in text
        code, _, _, text = wire.unpack_status_content(ok.content)
        assert code == wire.STATUS_OK and "reg-0007" in text, text
        types = [cap.content[i : i + 12].rstrip(b"\0").decode() for i in range(0, len(cap.content), 12)]
        assert {
            "TRANSFORM",
            "POINT",
            "STATUS",
            "GET_TRANS",
            "GET_TRANSFOR",
            "GET_STATUS",
            "GET_CAPABIL",
        } <= set(types)

    asyncio.run(main())


def test_a_client_switching_to_version_2_gets_the_metadata_at_once() -> None:
    """Issue #31 item 4: the on-connect push goes out in version 1 before the client's version-2
    STATUS is read; the first message with metadata used to wait for the next periodic push (20 s
    in the report, 60 s here)."""

    async def main() -> None:
        server = await started(Holder(RegistrationState(REG)), period_s=60.0)
        c = await RawClient.connect(server.port, v2=False)
        try:
            await c.wait(
                lambda m: m.header.device_name == "RobotToImage" and m.header.version == 1, "v1 push"
            )
            c.send(wire.pack_status("Hello", timestamp_s=time.time()))  # what Slicer sends at connect
            msg = await c.wait(
                lambda m: m.header.version == 2 and m.header.device_name == "RobotToImage", "v2"
            )
        finally:
            await c.close()
            await server.stop()
        assert msg.metadata["TransformStatus"] == "OK" and msg.metadata["RegistrationId"] == "reg-0007"

    asyncio.run(main())


def _doc_keys() -> dict[str, str]:
    """docs/slicer.md §3: metadata key → the "in" column."""
    text = (Path(__file__).resolve().parents[2] / "docs" / "slicer.md").read_text(encoding="utf-8")
    section = text.split("## 3. Metadata", 1)[1].split("\n## ", 1)[0]
    rows = [ln.split("|") for ln in section.splitlines() if ln.startswith("| `")]
    return {r[1].strip().strip("`"): r[2].strip() for r in rows}


def test_documented_metadata_keys_are_what_is_sent_both_ways() -> None:
    """docs/slicer.md §3 lists every key a message carries and nothing that is never sent (it
    listed ``SroSopInstanceUid``, never sent).  The union over the states: a current registration
    with every figure, a refusal, no registration, the robot link down."""
    full = RegistrationView(
        IMAGE_FROM_ROBOT, "reg-0007", fre_mm=0.41, tre_pred_mm=0.6, chain_error_mm=1.02,
        chain_error_source="nominal model prior (no active calibration)",
        evidence="unverified",
        spheres=(SpherePoint("+x-r1c1", (1.0, 2.0, 3.0), 0.02),), sphere_diameter_mm=4.0,
    )  # fmt: skip
    holder = Holder(RegistrationState(full, Refusal("reg-0008", "moved")))
    sent: set[str] = set()

    async def collect(c: RawClient) -> None:
        await wait_until(lambda: {m.header.device_name for m in c.messages if m.header.version == 2}
                         >= {"RobotToImage", "ToolToImage", "PhantomSpheres"}, "every device")  # fmt: skip
        sent.update(k for m in c.messages for k in m.metadata)

    async def main() -> None:
        server = await started(holder, send_invalid_transforms_v2=True)
        try:
            for reg, joints in (
                (holder.reg, JointView((0.1, 0.0), time.monotonic() + 3600, "connected")),
                (holder.reg, JointView((0.1, 0.0), time.monotonic(), "down", "cable")),
                (RegistrationState(None), None),
            ):
                holder.reg, holder.joints = reg, joints
                c = await RawClient.connect(server.port, v2=True)
                try:
                    await collect(c)
                finally:
                    await c.close()
        finally:
            await server.stop()

    asyncio.run(main())
    documented = _doc_keys()
    assert sent - set(documented) == set(), "sent but not in docs/slicer.md §3"
    assert set(documented) - sent == set(), "in docs/slicer.md §3 but never sent"
    first = list(registration_messages(RegistrationState(full), IgtlSettings())[0].metadata)
    assert first[:3] == ["Evidence", "ChainError_pred_mm", "ChainErrorSource"], (
        first
    )  # what backs it, then the figure


def test_a_non_finite_matrix_or_tcp_is_a_status_and_the_server_keeps_serving() -> None:
    """Issue #31 item 8: a NaN in ``tool0_from_tcp`` (or in a stored matrix) used to cut every
    client off; now that device is a STATUS and the others keep flowing."""
    bad = IMAGE_FROM_ROBOT.copy()
    bad[0, 3] = np.nan
    holder = Holder(RegistrationState(RegistrationView(bad, "reg-nan", fre_mm=0.1)))

    async def main() -> None:
        tcp = np.eye(4)
        tcp[2, 3] = np.inf
        src = holder.source(tcp=tcp)
        holder.joints = JointView((0.1, 0.0), time.monotonic() + 3600, "connected")
        server = IgtlServer(IgtlSettings(port=0, period_s=0.1), src)
        await server.start()
        c = await RawClient.connect(server.port, v2=True)
        try:
            for dev in ("RobotToImage", "ToolToImage"):
                await c.wait(is_msg("STATUS", dev, TransformStatus="INVALID"), f"{dev} STATUS")
            holder.reg = RegistrationState(REG)
            await c.wait(is_msg("TRANSFORM", "RobotToImage", TransformStatus="OK"), "served again")
        finally:
            await c.close()
            await server.stop()

    asyncio.run(main())


def test_the_server_refuses_to_start_when_crcmod_runs_without_its_c_extension(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """crcmod falls back to pure Python silently (issue #32): its own flag says so, and then the
    server does not start (the CRC of a message would hold the event loop)."""
    import sys

    monkeypatch.setattr(sys.modules["crcmod.crcmod"], "_usingExtension", False)

    async def main() -> None:
        server = IgtlServer(IgtlSettings(port=0), Holder(RegistrationState(REG)).source())
        with pytest.raises(IgtlConfigError, match="C extension"):
            await server.start()

    asyncio.run(main())
