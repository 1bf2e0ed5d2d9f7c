"""OpenIGTLink header-version negotiation per client (issue #23), over loopback sockets.

The rule (service/navigation/igtl/server.py): version 1 headers without metadata until a client has sent a
well-formed version-2 message, then version 2 with metadata; a client that never writes keeps
version 1; a malformed version-2 header drops only that client; a bad CRC is ignored.
"""

from __future__ import annotations

import asyncio
import math
import struct
import time
from typing import Any

import numpy as np
import pyigtl
import pytest
from polling import wait_until

from service.navigation.igtl import wire
from service.navigation.igtl.server import (
    RAS_FROM_LPS,
    IgtlServer,
    IgtlStateSource,
    JointView,
    RegistrationState,
    RegistrationView,
)
from service.settings import IgtlSettings

RX_TIMEOUT_S = 5.0
IMAGE_FROM_ROBOT = np.array(
    [[0.0, -1.0, 0.0, 120.5], [1.0, 0.0, 0.0, -33.25], [0.0, 0.0, 1.0, 410.0], [0.0, 0.0, 0.0, 1.0]]
)
REG = RegistrationView(IMAGE_FROM_ROBOT, "reg-0042", fre_mm=0.25, tre_pred_mm=0.5)


class Events:
    """``on_client`` recorder."""

    def __init__(self) -> None:
        self.items: list[tuple[str, str, int]] = []

    def __call__(self, event: str, peer: str, n_clients: int, header_version: int) -> None:
        self.items.append((event, peer, header_version))


async def started(events: Events | None = None, **cfg: Any) -> IgtlServer:
    def joints() -> JointView:  # a fresh sample at every look: ToolToImage valid (a TRANSFORM)
        return JointView((0.0,), time.monotonic(), "connected")

    src = IgtlStateSource(lambda: RegistrationState(REG), joints, lambda q: np.eye(4))
    server = IgtlServer(IgtlSettings(port=0, period_s=0.05, **cfg), src, on_client=events)
    await server.start()
    return server


async def read_one(reader: asyncio.StreamReader) -> wire.Message:
    """The next TRANSFORM, its CRC checked (unpack_body raises on a mismatch); the PhantomSpheres
    POINT (on connect and on the version-2 switch) is read past, its CRC checked too."""
    async with asyncio.timeout(RX_TIMEOUT_S):
        while True:
            head = wire.unpack_header(await reader.readexactly(wire.HEADER_SIZE))
            msg = wire.unpack_body(head, await reader.readexactly(head.body_size))
            if head.type != "POINT":
                return msg


async def until_v2(reader: asyncio.StreamReader) -> wire.Message:
    """Read until the first version-2 message (deadline)."""
    deadline = time.monotonic() + RX_TIMEOUT_S
    while time.monotonic() < deadline:
        msg = await read_one(reader)
        if msg.header.version == 2:
            return msg
    raise AssertionError("no version-2 message in time")


def peer_versions(server: IgtlServer) -> list[int]:
    return [int(str(c["header_version"])) for c in server.client_info()]


def assert_v1_transform(msg: wire.Message) -> None:
    assert msg.header.version == 1
    assert msg.header.type == "TRANSFORM"
    assert msg.header.body_size == wire.TRANSFORM_CONTENT_SIZE  # bare content: no extended header
    assert msg.metadata == {}
    if msg.header.device_name == "RobotToImage":
        m = wire.unpack_transform_content(msg.content)
        np.testing.assert_allclose(m, RAS_FROM_LPS @ IMAGE_FROM_ROBOT, atol=1e-4)


def test_client_that_never_writes_gets_version_1_without_metadata() -> None:
    events = Events()

    async def main() -> None:
        server = await started(events)
        reader, writer = await asyncio.open_connection("127.0.0.1", server.port)
        try:
            msgs = [await read_one(reader) for _ in range(8)]  # the connect push + periodic re-sends
            versions = peer_versions(server)
        finally:
            writer.close()
            await server.stop()
        for msg in msgs:
            assert_v1_transform(msg)
        assert {m.header.device_name for m in msgs} == {"RobotToImage", "ToolToImage"}
        assert versions == [1]
        assert events.items[0][0] == "connected" and events.items[0][2] == 1

    asyncio.run(main())


def test_pyigtl_client_that_sends_nothing_reads_version_1() -> None:
    """pyigtl's client sends nothing unasked: it must still get the matrix (without metadata)."""

    async def main() -> None:
        server = await started()
        client = pyigtl.OpenIGTLinkClient(host="127.0.0.1", port=server.port)
        try:
            deadline = time.monotonic() + RX_TIMEOUT_S
            msg = None
            while msg is None and time.monotonic() < deadline:
                msg = await asyncio.to_thread(client.wait_for_message, "RobotToImage", 0.5)
        finally:
            client.stop()
            await server.stop()
        assert msg is not None
        assert msg.header_version == 1 and not msg.metadata
        np.testing.assert_allclose(np.asarray(msg.matrix), RAS_FROM_LPS @ IMAGE_FROM_ROBOT, atol=1e-4)

    asyncio.run(main())


def test_v2_status_switches_that_client_only_and_v1_messages_do_not() -> None:
    events = Events()

    async def main() -> None:
        server = await started(events)
        ra, wa = await asyncio.open_connection("127.0.0.1", server.port)
        rb, wb = await asyncio.open_connection("127.0.0.1", server.port)
        try:
            await wait_until(lambda: server.client_count == 2, "two clients")
            # a version-1 message (GET_TRANSFORM) is read and answered, in version 1
            wa.write(wire.pack_message("GET_TRANSFOR", "RobotToImage", b"", timestamp_s=time.time(),
                                       header_version=1))  # fmt: skip
            for _ in range(6):
                assert_v1_transform(await read_one(ra))
            assert peer_versions(server) == [1, 1]
            wa.write(wire.pack_status("SlicerHello", timestamp_s=time.time()))
            first = await until_v2(ra)
            later = [await read_one(ra) for _ in range(6)]
            b_msgs = [await read_one(rb) for _ in range(12)]
            versions = sorted(peer_versions(server))
        finally:
            wa.close()
            wb.close()
            await server.stop()
        for msg in [first, *later]:
            assert msg.header.version == 2
            assert msg.metadata["RegistrationId"] == "reg-0042"
            assert msg.metadata["TransformStatus"] in ("OK", "INVALID")  # ToolToImage: no joints here
        robot = [m for m in [first, *later] if m.header.device_name == "RobotToImage"]
        assert (
            robot
            and robot[0].metadata["TransformStatus"] == "OK"
            and float(robot[0].metadata["FRE_mm"]) == pytest.approx(0.25)
        )
        np.testing.assert_allclose(
            wire.unpack_transform_content(robot[0].content), RAS_FROM_LPS @ IMAGE_FROM_ROBOT, atol=1e-4
        )
        for msg in b_msgs:  # the other client never wrote: still version 1
            assert_v1_transform(msg)
        assert versions == [1, 2]
        switched = [e for e in events.items if e[0] == "header_version"]
        assert len(switched) == 1 and switched[0][2] == 2

    asyncio.run(main())


def _v2_body(ext_size: int, mhead_size: int, mbody_size: int, content: bytes) -> bytes:
    return struct.pack(">HHII", ext_size, mhead_size, mbody_size, 1) + content


def _raw(version: int, body: bytes) -> bytes:
    """A message with a valid CRC whose header says ``version`` (the structure is what is wrong)."""
    raw = bytearray(wire.pack_header("STATUS", "Bad", time.time(), body, version=2) + body)
    struct.pack_into(">H", raw, 0, version)
    return bytes(raw)


STATUS_CONTENT = struct.pack(">Hq20s", 1, 0, b"") + b"\0"
MALFORMED = {
    "extended header size below 12": _raw(2, _v2_body(4, 0, 0, STATUS_CONTENT)),
    "metadata larger than the body": _raw(2, _v2_body(12, 10, 5000, STATUS_CONTENT)),
    "body shorter than an extended header": _raw(2, b"\0\x0c\0\0"),
    "metadata header count disagrees": _raw(2, _v2_body(12, 2, 0, STATUS_CONTENT) + b"\0\x05"),
    "header version 7": _raw(7, STATUS_CONTENT),
}


@pytest.mark.parametrize("bad", list(MALFORMED.values()), ids=list(MALFORMED))
def test_malformed_v2_header_drops_only_that_client(bad: bytes) -> None:
    async def main() -> None:
        server = await started()
        rg, wg = await asyncio.open_connection("127.0.0.1", server.port)
        rb, wb = await asyncio.open_connection("127.0.0.1", server.port)
        try:
            wg.write(wire.pack_status("Hello", timestamp_s=time.time()))
            await until_v2(rg)
            wb.write(bad)
            async with asyncio.timeout(RX_TIMEOUT_S):  # the bad client is closed: EOF after what was queued
                while await rb.read(65536):
                    pass
            await wait_until(lambda: server.counters["bad_headers"] == 1, "the bad header counted")
            after = [await read_one(rg) for _ in range(6)]  # the good client is still served, in v2
            versions = peer_versions(server)
        finally:
            wg.close()
            wb.close()
            await server.stop()
        assert all(m.header.version == 2 and m.metadata["RegistrationId"] == "reg-0042" for m in after)
        assert versions == [2]

    asyncio.run(main())


def test_bad_crc_is_ignored_without_switching_then_a_good_v2_switches() -> None:
    async def main() -> None:
        server = await started()
        reader, writer = await asyncio.open_connection("127.0.0.1", server.port)
        try:
            good = wire.pack_status("Hello", timestamp_s=time.time())
            bad = bytearray(good)
            bad[-1] ^= 0x01  # the body changed, the header's CRC did not
            writer.write(bytes(bad))
            await wait_until(lambda: server.counters["bad_crc"] == 1, "the bad CRC counted")
            for _ in range(4):
                assert_v1_transform(await read_one(reader))
            still_v1 = peer_versions(server)
            writer.write(good)
            msg = await until_v2(reader)
        finally:
            writer.close()
            await server.stop()
        assert still_v1 == [1]
        assert msg.metadata["RegistrationId"] == "reg-0042"
        assert server.counters["bad_headers"] == 0

    asyncio.run(main())


def test_status_message_layout() -> None:
    """pack_status follows status.md: C uint16, S int64, E char[20], M null-terminated."""
    raw = wire.pack_status("Dev", timestamp_s=1.5, code=13, subcode=-2, error_name="NOT_READY",
                           status_string="warming up", header_version=1)  # fmt: skip
    msg = wire.unpack_message(raw)
    assert msg.header.type == "STATUS" and msg.header.version == 1
    code, sub, name = struct.unpack_from(">Hq20s", msg.content)
    assert (code, sub, name.rstrip(b"\0")) == (13, -2, b"NOT_READY")
    assert msg.content[30:] == b"warming up\0"
    assert math.isclose(msg.header.timestamp_s, 1.5, abs_tol=1e-6)
