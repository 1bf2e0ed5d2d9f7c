"""A mock Stäubli controller streaming simple_message like the ROS-I VAL3 driver.

Behaviour copied from ros-industrial/staubli_val3_driver (research/staubli-link.md
§1.1, §1.6): a TCP server (the ``Feedback`` socket); once a client connects it
sends JOINT_POSITION (10) every 20 ms (50 Hz) and STATUS (13) every 5th cycle
(10 Hz); each message goes out as three separate writes (prefix, header, body,
``sendRosMsg.pgx``), with Nagle off (TCP_NODELAY).  The sequence number is 0,
as in the driver.  Everything the client sends is read and counted (a
read-only client must send nothing) but otherwise ignored.

Fault injection (call from the server's event loop; :mod:`mocks.robot.runner`
wraps these for other threads): :meth:`stall`, :meth:`resume`,
:meth:`disconnect`, :meth:`inject_raw` (garbage bytes, an oversized length
prefix), :meth:`inject_nan`, :meth:`set_split_frames`.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import socket
import struct
import time
from collections import deque

from drivers.simple_message import (
    HEADER,
    MSG_JOINT_FEEDBACK,
    MSG_JOINT_POSITION,
    PREFIX,
    JointFeedback,
    Status,
    encode_joint_feedback,
    encode_joint_position,
    encode_status,
)
from mocks.robot.faults import QueuedFaults
from mocks.robot.robot import ScriptedRobot

log = logging.getLogger(__name__)

FRAME_PERIOD_S = 0.02
"""VAL3 driver feedback task period (``start.pgx``: ``l_nFbkPeriod = 0.02``)."""
CATCH_UP_MAX_S = 2.0
"""Frames missed while this mock process was starved are sent late, up to this much backlog."""
STATUS_EVERY = 5
"""STATUS goes out every 5th cycle (``dataStreamer.pgx``: ``l_nThrottle == 5``) → 10 Hz."""
SPLIT_WRITE_PAUSE_S = 0.0005
"""Pause between single-byte writes when frames are split, so they travel in separate segments."""


class SimpleMessageServer:
    """Serve ``robot`` over simple_message on ``host:port`` (port 0: any free port).

    Parameters
    ----------
    msg_type : int
        10 (JOINT_POSITION, the VAL3 driver) or 15 (JOINT_FEEDBACK, PR #36 fork).
    start_delay_s : float
        Wait after a client connects before streaming (the real driver waits 1 s,
        ``recvHeartbeat.pgx``; tests use 0).
    """

    def __init__(
        self,
        robot: ScriptedRobot,
        host: str = "127.0.0.1",
        port: int = 0,
        *,
        period_s: float = FRAME_PERIOD_S,
        status_every: int = STATUS_EVERY,
        msg_type: int = MSG_JOINT_POSITION,
        start_delay_s: float = 0.0,
        send_log_size: int = 4096,
    ) -> None:
        if msg_type not in (MSG_JOINT_POSITION, MSG_JOINT_FEEDBACK):
            raise ValueError(f"msg_type must be {MSG_JOINT_POSITION} or {MSG_JOINT_FEEDBACK}")
        self.robot = robot
        self.host = host
        self.port = port
        self.period_s = period_s
        self.status_every = status_every
        self.msg_type = msg_type
        self.start_delay_s = start_delay_s
        self._server: asyncio.Server | None = None
        self._conns: set[asyncio.Task[None]] = set()
        self._writers: set[asyncio.StreamWriter] = set()
        self._stalled = False
        self._split = False
        self.faults = QueuedFaults()
        self.joint_frames_sent = 0
        self.status_frames_sent = 0
        self.bytes_from_clients = 0
        self.connections_accepted = 0
        self.send_log: deque[tuple[tuple[float, ...], float]] = deque(maxlen=send_log_size)
        """(joints as float32-rounded tuple, time.monotonic() just after the body write)."""
        self.returned_t_s: float | None = None
        self.client_connected = asyncio.Event()

    @property
    def url(self) -> str:
        return f"simple-message://{self.host}:{self.port}"

    async def start(self) -> None:
        self._server = await asyncio.start_server(self._handle, self.host, self.port, reuse_address=True)
        self.port = self._server.sockets[0].getsockname()[1]
        log.info("mock simple_message controller on %s", self.url)

    async def stop(self) -> None:
        if self._server is not None:
            self._server.close()
            self._server = None
        for w in list(self._writers):
            w.transport.abort()
        tasks = list(self._conns)
        for t in tasks:
            t.cancel()
        for t in tasks:
            with contextlib.suppress(asyncio.CancelledError, Exception):
                await t

    # ---- faults -------------------------------------------------------------

    def stall(self) -> None:
        """Keep connections open but send nothing until :meth:`resume`."""
        self._stalled = True

    def resume(self) -> None:
        self._stalled = False

    async def disconnect(self, down_s: float) -> None:
        """Close every connection and the listening socket; listen again on the same port
        after ``down_s`` (sets :attr:`returned_t_s`)."""
        port = self.port
        await self.stop()
        self.client_connected.clear()
        await asyncio.sleep(down_s)
        self.port = port
        await self.start()
        self.returned_t_s = time.monotonic()

    def inject_raw(self, data: bytes) -> None:
        """Send ``data`` verbatim before the next frame (garbage, an oversized prefix…)."""
        self.faults.inject_raw(data)

    def inject_nan(self, n_frames: int = 1, joint: int = 0) -> None:
        """Replace joint ``joint`` by NaN in the next ``n_frames`` joint frames."""
        self.faults.inject_nan(n_frames, joint)

    def set_split_frames(self, enabled: bool) -> None:
        """Write every byte separately (with a short pause) instead of three writes per frame."""
        self._split = enabled

    # ---- serving -------------------------------------------------------------

    async def _handle(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        task = asyncio.current_task()
        assert task is not None
        self._conns.add(task)
        self._writers.add(writer)
        self.connections_accepted += 1
        sock = writer.get_extra_info("socket")
        if sock is not None:
            sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        drain_task = asyncio.create_task(self._count_incoming(reader))
        self.client_connected.set()
        try:
            if self.start_delay_s:
                await asyncio.sleep(self.start_delay_s)
            await self._stream(writer)
        except (ConnectionError, OSError, asyncio.CancelledError):
            pass  # client gone, or stop(): end this handler quietly (start_server logs a cancelled task)
        finally:
            drain_task.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await drain_task
            writer.transport.abort()
            self._writers.discard(writer)
            self._conns.discard(task)

    async def _count_incoming(self, reader: asyncio.StreamReader) -> None:
        while True:
            try:
                data = await reader.read(4096)
            except (ConnectionError, OSError):
                return  # the client aborted (as the link does on close): nothing more to count
            if not data:
                return
            self.bytes_from_clients += len(data)
            log.warning("mock controller received %d bytes from a client (should be read-only)", len(data))

    async def _stream(self, writer: asyncio.StreamWriter) -> None:
        loop = asyncio.get_running_loop()
        next_t = loop.time()
        cycle = 0
        while True:
            if writer.transport.is_closing():
                return
            if not self._stalled:
                for raw in self.faults.take_raw():
                    await self._write(writer, [raw])
                await self._send_joints(writer)
                if cycle % self.status_every == 0:
                    st = self.robot.controller_status
                    msg = Status(
                        st.drives_powered, st.e_stopped, st.error_code, st.in_error,
                        self.robot.reported_in_motion(), st.mode, st.motion_possible,
                    )  # fmt: skip
                    await self._write_frame(writer, encode_status(msg))
                    self.status_frames_sent += 1
                cycle += 1
            next_t += self.period_s
            delay = next_t - loop.time()
            # A real controller's feedback task runs on its own real-time clock: our host's load
            # must not cost frames.  Late (this process starved), send the missed frames at once,
            # as TCP would deliver them from a controller that kept sending; only a backlog over
            # CATCH_UP_MAX_S (a suspended process, not load) re-anchors the schedule.
            if delay < -CATCH_UP_MAX_S:
                next_t = loop.time()
                delay = 0.0
            await asyncio.sleep(max(0.0, delay))

    async def _send_joints(self, writer: asyncio.StreamWriter) -> None:
        q = self.faults.joints(self.robot.joints_rad_at())
        if self.msg_type == MSG_JOINT_POSITION:
            frame = encode_joint_position(q)
        else:
            frame = encode_joint_feedback(
                JointFeedback(0, 0x2, time.monotonic(), tuple(q), (0.0,) * 6, (0.0,) * 6)
            )
        t = await self._write_frame(writer, frame)
        self.joint_frames_sent += 1
        self.send_log.append((tuple(struct.unpack("<6f", struct.pack("<6f", *q))), t))

    async def _write_frame(self, writer: asyncio.StreamWriter, frame: bytes) -> float:
        cut = PREFIX.size + HEADER.size
        return await self._write(writer, [frame[: PREFIX.size], frame[PREFIX.size : cut], frame[cut:]])

    async def _write(self, writer: asyncio.StreamWriter, parts: list[bytes]) -> float:
        """Write ``parts`` as separate writes (drain between); returns the time of the last write."""
        t = time.monotonic()
        if self._split:
            parts = [bytes([b]) for p in parts for b in p]
        for i, p in enumerate(parts):
            if self._split and i:
                await asyncio.sleep(SPLIT_WRITE_PAUSE_S)
            writer.write(p)
            t = time.monotonic()
            await writer.drain()
        return t
