"""ROS-Industrial simple_message, as sent by the Stäubli VAL3 driver, and its read-only link.

Wire format (research/staubli-link.md §1.2-1.5; ros-industrial/industrial_core
``simple_message.h``; ros-industrial/staubli_val3_driver ``encPrefixHeader.pgx``):
every integer is an int32 and every real a float32, **little-endian**; a message is

    PREFIX  int32 length of HEADER + BODY (does not count itself)
    HEADER  int32 msg_type, int32 comm_type, int32 reply_code
    BODY    depends on msg_type

=================  ====  =====================================================
JOINT_POSITION     10    seq int32, joints float32[10] (rad)    length 56
STATUS             13    7 × int32 (TriState / mode)            length 40
JOINT_FEEDBACK     15    robot_id, valid_fields int32, time f32,
                         positions, velocities, accelerations f32[10]   length 144
=================  ====  =====================================================

The controller writes each message as three ``sioSet`` calls (prefix, header,
body), so TCP may split or merge frames anywhere: :class:`FrameReassembler`
cuts the byte stream by the length prefix.  A prefix outside
[:data:`MIN_LENGTH`, :data:`MAX_LENGTH`] means the stream is corrupt: it raises
:class:`~drivers.errors.ProtocolError` *before* buffering anything of that size,
and the link drops the connection and reconnects.

The link is read-only: it opens a TCP client to the controller's ``Feedback``
socket (port 11002) and never writes a byte (there is no write call in this
module).  Port 11000 is the motion socket and is never touched.
"""

from __future__ import annotations

import asyncio
import logging
import socket
import struct
import time
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any
from urllib.parse import urlsplit

from drivers.base import BaseLink, RobotStatus, base_options, float32_half_spacing, option_float, parse_query
from drivers.errors import LinkConfigError, ProtocolError

log = logging.getLogger(__name__)

DEFAULT_PORT = 11002
"""simple_message STATE port, the VAL3 driver's ``Feedback`` socket (industrial_core
``simple_socket.h`` ``StandardSocketPorts.STATE``)."""

MOTION_PORT = 11000
"""The motion socket.  This package must never connect to it."""

# message types (industrial_core simple_message.h l.58-86)
MSG_PING = 1
MSG_JOINT_POSITION = 10
MSG_JOINT_TRAJ_PT = 11
MSG_STATUS = 13
MSG_JOINT_TRAJ_PT_FULL = 14
MSG_JOINT_FEEDBACK = 15

COMM_TOPIC = 1
REPLY_INVALID = 0

MAX_NUM_JOINTS = 10
"""industrial_core ``joint_data.h`` MAX_NUM_JOINTS."""

PREFIX = struct.Struct("<i")
HEADER = struct.Struct("<3i")
JOINT_POSITION_BODY = struct.Struct("<i10f")
STATUS_BODY = struct.Struct("<7i")
JOINT_FEEDBACK_BODY = struct.Struct("<2if10f10f10f")

JOINT_POSITION_LENGTH = HEADER.size + JOINT_POSITION_BODY.size  # 56, VAL3 setupRosMsgs.pgx "12 + 44"
STATUS_LENGTH = HEADER.size + STATUS_BODY.size  # 40, "12 + 28"
JOINT_FEEDBACK_LENGTH = HEADER.size + JOINT_FEEDBACK_BODY.size  # 144, "12 + 132"

MIN_LENGTH = HEADER.size
"""Smallest legal prefix value: a header with an empty body (e.g. PING)."""

MAX_LENGTH = 4096
"""Largest prefix value accepted.  The biggest standard message, JOINT_TRAJ_PT_FULL, is 148 bytes
and JOINT_TRAJ (12) at most ~1.4 kB; anything larger is a corrupt or misaligned stream, and
must not make the client allocate (a garbage prefix can claim up to 2 GiB)."""

JOINT_FEEDBACK_POSITION_VALID = 0x2
"""industrial_core ``ValidFieldTypes::POSITION`` (joint_traj_pt_full.h)."""


# --------------------------------------------------------------------------- messages


@dataclass(frozen=True)
class Header:
    msg_type: int
    comm_type: int
    reply_code: int


@dataclass(frozen=True)
class JointPosition:
    """JOINT_POSITION (10): ``joints_rad`` holds all 10 slots (the VAL3 driver fills 6)."""

    sequence: int
    joints_rad: tuple[float, ...]
    header: Header = Header(MSG_JOINT_POSITION, COMM_TOPIC, REPLY_INVALID)


@dataclass(frozen=True)
class JointFeedback:
    """JOINT_FEEDBACK (15), as in industrial_core ``joint_feedback.h``."""

    robot_id: int
    valid_fields: int
    time_s: float
    positions_rad: tuple[float, ...]
    velocities_rad_s: tuple[float, ...]
    accelerations_rad_s2: tuple[float, ...]
    header: Header = Header(MSG_JOINT_FEEDBACK, COMM_TOPIC, REPLY_INVALID)


@dataclass(frozen=True)
class Status:
    """STATUS (13), industrial_core ``robot_status.h`` field order.  TriState: −1/0/1."""

    drives_powered: int
    e_stopped: int
    error_code: int
    in_error: int
    in_motion: int
    mode: int
    motion_possible: int
    header: Header = Header(MSG_STATUS, COMM_TOPIC, REPLY_INVALID)

    def to_robot_status(self, t_s: float) -> RobotStatus:
        return RobotStatus(
            self.drives_powered, self.e_stopped, self.error_code, self.in_error,
            self.in_motion, self.mode, self.motion_possible, t_s,
        )  # fmt: skip


@dataclass(frozen=True)
class Unknown:
    """A message of a type this client does not interpret (skipped by its length)."""

    header: Header
    body: bytes


Message = JointPosition | JointFeedback | Status | Unknown


# --------------------------------------------------------------------------- codec


def _pad10(values: tuple[float, ...] | list[float]) -> list[float]:
    v = [float(x) for x in values]
    if len(v) > MAX_NUM_JOINTS:
        raise ValueError(f"at most {MAX_NUM_JOINTS} joints, got {len(v)}")
    return v + [0.0] * (MAX_NUM_JOINTS - len(v))


def _frame(header: Header, body: bytes) -> bytes:
    return PREFIX.pack(HEADER.size + len(body)) + HEADER.pack(*_hdr(header)) + body


def _hdr(h: Header) -> tuple[int, int, int]:
    return (h.msg_type, h.comm_type, h.reply_code)


def encode_joint_position(joints_rad: Any, sequence: int = 0, header: Header | None = None) -> bytes:
    """Full wire bytes (prefix included) of a JOINT_POSITION message (60 bytes)."""
    h = header or Header(MSG_JOINT_POSITION, COMM_TOPIC, REPLY_INVALID)
    return _frame(h, JOINT_POSITION_BODY.pack(sequence, *_pad10(tuple(joints_rad))))


def encode_status(status: Status) -> bytes:
    """Full wire bytes of a STATUS message (44 bytes)."""
    body = STATUS_BODY.pack(
        status.drives_powered, status.e_stopped, status.error_code, status.in_error,
        status.in_motion, status.mode, status.motion_possible,
    )  # fmt: skip
    return _frame(status.header, body)


def encode_joint_feedback(msg: JointFeedback) -> bytes:
    """Full wire bytes of a JOINT_FEEDBACK message (148 bytes)."""
    body = JOINT_FEEDBACK_BODY.pack(
        msg.robot_id, msg.valid_fields, msg.time_s,
        *_pad10(msg.positions_rad), *_pad10(msg.velocities_rad_s), *_pad10(msg.accelerations_rad_s2),
    )  # fmt: skip
    return _frame(msg.header, body)


def encode(msg: Message) -> bytes:
    """Wire bytes of any :data:`Message`."""
    if isinstance(msg, JointPosition):
        return encode_joint_position(msg.joints_rad, msg.sequence, msg.header)
    if isinstance(msg, Status):
        return encode_status(msg)
    if isinstance(msg, JointFeedback):
        return encode_joint_feedback(msg)
    return _frame(msg.header, msg.body)


def check_length(length: int) -> None:
    """Raise :class:`ProtocolError` if a prefix value is outside the sane range."""
    if not MIN_LENGTH <= length <= MAX_LENGTH:
        raise ProtocolError(
            f"simple_message length prefix {length} outside [{MIN_LENGTH}, {MAX_LENGTH}] bytes: "
            "the stream is corrupt or not simple_message (is this the controller's port 11002?)"
        )


def decode_message(frame: bytes | bytearray | memoryview) -> Message:
    """Decode HEADER + BODY (the bytes after the length prefix).

    Raises
    ------
    ProtocolError
        Shorter than a header, or a known type whose body has the wrong size.
    """
    n = len(frame)
    if n < HEADER.size:
        raise ProtocolError(f"simple_message frame of {n} bytes is shorter than the 12-byte header")
    header = Header(*HEADER.unpack_from(frame, 0))
    body_len = n - HEADER.size
    t = header.msg_type
    if t == MSG_JOINT_POSITION:
        _expect(t, "JOINT_POSITION", JOINT_POSITION_BODY.size, body_len)
        seq, *joints = JOINT_POSITION_BODY.unpack_from(frame, HEADER.size)
        return JointPosition(seq, tuple(joints), header)
    if t == MSG_STATUS:
        _expect(t, "STATUS", STATUS_BODY.size, body_len)
        s = STATUS_BODY.unpack_from(frame, HEADER.size)
        return Status(s[0], s[1], s[2], s[3], s[4], s[5], s[6], header)
    if t == MSG_JOINT_FEEDBACK:
        _expect(t, "JOINT_FEEDBACK", JOINT_FEEDBACK_BODY.size, body_len)
        v = JOINT_FEEDBACK_BODY.unpack_from(frame, HEADER.size)
        return JointFeedback(
            int(v[0]), int(v[1]), float(v[2]), tuple(v[3:13]), tuple(v[13:23]), tuple(v[23:33]), header
        )
    return Unknown(header, bytes(frame[HEADER.size :]))


def _expect(msg_type: int, name: str, expected: int, found: int) -> None:
    if expected != found:
        raise ProtocolError(
            f"simple_message {name} ({msg_type}) body must be {expected} bytes, found {found} "
            "(a controller built with FLOAT64 reals, or a misaligned stream)"
        )


class FrameReassembler:
    """Cut a byte stream into simple_message frames by the length prefix.

    ``feed(data)`` returns the complete frames (HEADER + BODY, without the
    prefix) now available.  A prefix outside [MIN_LENGTH, MAX_LENGTH] raises
    :class:`ProtocolError` as soon as its 4 bytes are seen; the buffer never
    holds more than one partial frame plus the bytes of one ``feed`` call.
    """

    def __init__(self) -> None:
        self._buf = bytearray()
        self._need: int | None = None  # length of the frame being collected, once its prefix is read

    def feed(self, data: bytes | bytearray | memoryview) -> list[bytes]:
        self._buf += data
        out: list[bytes] = []
        buf = self._buf
        pos = 0
        try:
            while True:
                if self._need is None:
                    if len(buf) - pos < PREFIX.size:
                        break
                    (length,) = PREFIX.unpack_from(buf, pos)
                    check_length(length)
                    self._need = length
                    pos += PREFIX.size
                if len(buf) - pos < self._need:
                    break
                out.append(bytes(buf[pos : pos + self._need]))
                pos += self._need
                self._need = None
        except ProtocolError:
            self.reset()
            raise
        if pos:
            del buf[:pos]
        return out

    def reset(self) -> None:
        self._buf.clear()
        self._need = None

    @property
    def buffered(self) -> int:
        """Bytes held (a partial frame)."""
        return len(self._buf)


# --------------------------------------------------------------------------- link


class _Receiver(asyncio.Protocol):
    """asyncio protocol: reassemble, decode, hand to the link.  Never writes."""

    def __init__(self, link: SimpleMessageLink) -> None:
        self.link = link
        self.reasm = FrameReassembler()
        self.closed: asyncio.Future[BaseException | None] = asyncio.get_running_loop().create_future()
        self.transport: asyncio.Transport | None = None

    def connection_made(self, transport: asyncio.BaseTransport) -> None:
        # uvloop's transports are not asyncio.Transport subclasses; only close() is ever used.
        self.transport = transport  # type: ignore[assignment]

    def data_received(self, data: bytes) -> None:
        t_s = time.monotonic()
        try:
            frames = self.reasm.feed(data)
        except ProtocolError as e:
            self._finish(e)
            return
        for f in frames:
            self.link._on_frame(f, t_s)

    def eof_received(self) -> bool:
        self._finish(EOFError("controller closed the connection"))
        return False

    def connection_lost(self, exc: Exception | None) -> None:
        self._finish(exc or EOFError("connection lost"))

    def _finish(self, exc: BaseException) -> None:
        if not self.closed.done():
            self.closed.set_result(exc)
        if self.transport is not None:
            self.transport.abort()


class SimpleMessageLink(BaseLink):
    """Read-only simple_message client (``simple-message://HOST[:11002]``).

    URL options (query or keyword): ``connect_timeout_s`` (per attempt,
    default 2 s), plus those of :class:`~drivers.base.BaseLink`.
    """

    scheme = "simple-message"

    def __init__(self, url: str, *, connect_timeout_s: float = 2.0, **options: Any) -> None:
        opts: dict[str, Any] = {**parse_query(url), **options}
        parts = urlsplit(url)
        if parts.scheme != self.scheme or not parts.hostname:
            raise LinkConfigError(f"expected simple-message://HOST[:PORT], got {url!r}")
        try:
            self.port = parts.port or DEFAULT_PORT
        except ValueError as e:
            raise LinkConfigError(f"{url}: bad port ({e})") from None
        if self.port == MOTION_PORT:
            raise LinkConfigError(
                f"{url}: port {MOTION_PORT} is the controller's motion socket; joint feedback is "
                f"on {DEFAULT_PORT} (this service must never connect to the motion port)"
            )
        self.host = parts.hostname
        self.connect_timeout_s = option_float(opts, "connect_timeout_s", connect_timeout_s, url)
        super().__init__(url, **base_options(opts, url))
        self._transport: asyncio.Transport | None = None

    def joint_resolution_rad(self, joints_rad: Sequence[float]) -> tuple[float, ...]:
        """Every joint is a float32 on the wire: half its spacing (2.4e-7 rad at ±270°)."""
        return tuple(float32_half_spacing(q) for q in joints_rad)

    def _on_frame(self, frame: bytes, t_s: float) -> None:
        try:
            msg = decode_message(frame)
        except ProtocolError as e:
            self._count("frames_rejected")
            log.warning("robot link %s: %s; frame skipped", self.url, e)
            return
        if isinstance(msg, JointPosition):
            self._publish_joints(msg.joints_rad, t_s)
        elif isinstance(msg, JointFeedback):
            if not msg.valid_fields & JOINT_FEEDBACK_POSITION_VALID:
                self._count("frames_rejected")
                log.warning("robot link %s: JOINT_FEEDBACK without valid positions; skipped", self.url)
                return
            self._publish_joints(msg.positions_rad, t_s)
        elif isinstance(msg, Status):
            self._publish_status(msg.to_robot_status(t_s))
        else:
            self._count("unknown_frames")
            log.debug("robot link %s: skipped message type %d (%d bytes)", self.url,
                      msg.header.msg_type, len(frame))  # fmt: skip

    async def _session(self) -> None:
        loop = asyncio.get_running_loop()
        transport, proto = await asyncio.wait_for(
            loop.create_connection(lambda: _Receiver(self), self.host, self.port),
            self.connect_timeout_s,
        )
        self._transport = transport
        sock = transport.get_extra_info("socket")
        if sock is not None:
            sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        self._mark_up()
        started = time.monotonic()
        check_s = min(0.5, self.silence_reconnect_s / 4)
        while not self._closing.is_set():
            done, _ = await asyncio.wait({proto.closed}, timeout=check_s)
            if done:
                exc = proto.closed.result()
                if exc is not None:
                    raise exc
                return
            if self._silence_exceeded(started):
                raise TimeoutError(f"no valid frame for more than {self.silence_reconnect_s:g} s")

    async def _cleanup(self) -> None:
        t, self._transport = self._transport, None
        if t is not None:
            t.abort()
