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
from typing import Any

import numpy as np
import pyigtl
import pytest
from polling import wait_until

from drivers.factory import open_link
from mocks.robot.robot import ScriptedRobot
from mocks.robot.runner import run_mock_controller
from registration.model.kinematics import RobotModel
from service.igtl import wire
from service.igtl.server import (
    RAS_FROM_LPS,
    IgtlConfigError,
    IgtlServer,
    IgtlServerConfig,
    IgtlStateSource,
    JointView,
    Refusal,
    RegistrationState,
    RegistrationView,
)

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

    async def wait(self, pred: Callable[[wire.Message], bool], what: str) -> wire.Message:
        found: list[wire.Message] = []

        def hit() -> bool:
            found[:] = [m for m in self.messages if pred(m)]
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
    server = IgtlServer(IgtlServerConfig(port=0, **cfg), holder.source())
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
        server = await started(Holder(RegistrationState(None)), send_invalid_transforms_v2=True)
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
                server = IgtlServer(IgtlServerConfig(port=0, send_invalid_transforms_v2=True), src)
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
    cfg = IgtlServerConfig(
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
    with pytest.raises(IgtlConfigError, match="allowed_peer_addresses"):
        IgtlServerConfig(host=host)
    IgtlServerConfig(host=host, allowed_peer_addresses=("10.0.0.0/24",))  # explicit list: fine


def test_bad_allow_list_entry_and_long_device_name_refused() -> None:
    with pytest.raises(IgtlConfigError, match="allowed_peer_addresses"):
        IgtlServerConfig(allowed_peer_addresses=("not-an-ip",))
    with pytest.raises(IgtlConfigError, match="20"):
        IgtlServerConfig(tool_device="StylusTipToImageRASFrame")


def test_failing_callbacks_give_invalid_not_a_dead_server() -> None:
    def boom() -> RegistrationState:
        raise RuntimeError("database is locked")

    async def main() -> None:
        src = IgtlStateSource(boom, lambda: None, lambda q: np.eye(4))
        server = IgtlServer(IgtlServerConfig(port=0), src)
        await server.start()
        client = await RawClient.connect(server.port, v2=True)
        try:
            msg = await client.wait(is_msg("STATUS", "RobotToImage", TransformStatus="INVALID"), "INVALID")
        finally:
            await client.close()
            await server.stop()
        assert "could not be read" in wire.unpack_status_content(msg.content)[3]

    asyncio.run(main())
