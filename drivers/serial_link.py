"""Joint angles over RS-232/RS-422 (pyserial): the project's own line protocol.

Stäubli defines no serial joint protocol (research/staubli-link.md §2.2), so
this one is ours; the VAL3 program that speaks it is in ``docs/robot-link.md``
and ``docs/val3/``.  ASCII lines, NMEA-0183 style::

    $J,<seq>,<j1>,<j2>,<j3>,<j4>,<j5>,<j6>*<CS>\\r\\n        joints, 50 Hz
    $S,<seq>,<pow>,<estop>,<err>,<in_err>,<in_motion>,<mode>,<possible>*<CS>\\r\\n   status, 10 Hz

* ``seq``: decimal integer 0…65535, +1 per ``$J`` line, wrapping to 0 (the
  receiver counts gaps as lost lines); ``$S`` lines carry their own counter.
* ``j1…j6``: joint angles in **radians** (the project's wire unit; the VAL3
  program multiplies ``herej()`` degrees by π/180 as the ROS-I driver does),
  decimal text with at most 9 significant digits (enough to round-trip a
  float32 exactly), optional sign and exponent, no spaces.
* status fields: integers, the simple_message STATUS meanings (TriState −1/0/1,
  mode −1 unknown / 1 manual / 2 auto).
* ``CS``: XOR of every byte strictly between ``$`` and ``*``, two hex digits
  (upper or lower case accepted).
* A line is at most :data:`MAX_LINE_BYTES` bytes including ``\\r\\n``; CR, LF or CR LF
  all end a line (a VAL3 ``sio`` write ends with CR).  Lines
  that do not start with ``$``, overflow, fail the checksum, have the wrong
  field count, or carry a non-finite joint are rejected (logged, counted), never
  published.  Unknown sentence letters are skipped.

URL: ``serial:///dev/ttyS0?baudrate=115200&parity=N&stopbits=1``.  At 50 Hz a
``$J`` line is ≤ 100 bytes, i.e. ≤ 50 kbit/s: use ≥ 57600 baud (115200
recommended).  The link never writes to the port.  POSIX only (it watches the
port's file descriptor on the event loop).
"""

from __future__ import annotations

import asyncio
import logging
import math
import time
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any
from urllib.parse import unquote, urlsplit

from drivers.base import BaseLink, RobotStatus, base_options, parse_query
from drivers.errors import LinkConfigError, ProtocolError

log = logging.getLogger(__name__)

MAX_LINE_BYTES = 160
"""Longest legal line: '$J,65535,' + 6 × '-1.23456789e+00,' + '*XX\\r\\n' ≈ 112 bytes, with margin."""
SEQ_MODULO = 65536
N_JOINTS = 6
N_STATUS_FIELDS = 7
DEFAULT_BAUDRATE = 115200


@dataclass(frozen=True)
class JointLine:
    seq: int
    joints_rad: tuple[float, ...]


@dataclass(frozen=True)
class StatusLine:
    seq: int
    drives_powered: int
    e_stopped: int
    error_code: int
    in_error: int
    in_motion: int
    mode: int
    motion_possible: int

    def to_robot_status(self, t_s: float) -> RobotStatus:
        return RobotStatus(
            self.drives_powered, self.e_stopped, self.error_code, self.in_error,
            self.in_motion, self.mode, self.motion_possible, t_s,
        )  # fmt: skip


def checksum(payload: bytes) -> int:
    """XOR of all bytes of ``payload`` (the text between ``$`` and ``*``)."""
    c = 0
    for b in payload:
        c ^= b
    return c


def _sentence(payload: str) -> bytes:
    p = payload.encode("ascii")
    return b"$" + p + b"*" + f"{checksum(p):02X}".encode() + b"\r\n"


SIGNIFICANT_DIGITS = 9
"""Significant digits of a joint value on the wire (:func:`format_joint`)."""


def format_joint(value_rad: float) -> str:
    """Decimal text of a joint value: 9 significant digits (round-trips float32 exactly)."""
    return f"{value_rad:.{SIGNIFICANT_DIGITS}g}"


VAL3_DECIMALS = 8
"""Decimals the project's VAL3 program writes (``toString(".8", …)``, docs/val3/publishSerial.pgx)."""


def text_rounding_rad(value_rad: float) -> float:
    """The most the text encoding moves ``value_rad``: half a unit in its last digit, for the coarser of
    :data:`SIGNIFICANT_DIGITS` significant digits (:func:`format_joint`) and :data:`VAL3_DECIMALS`
    decimals (the VAL3 program): 5e-9 rad for |value| < 10 rad (127.5° = 2.22529480 on the wire)."""
    if not math.isfinite(value_rad):
        return 0.0
    by_decimals = 0.5 * 10.0**-VAL3_DECIMALS
    if value_rad == 0:
        return by_decimals
    by_digits = 0.5 * 10.0 ** (math.floor(math.log10(abs(value_rad))) - (SIGNIFICANT_DIGITS - 1))
    return max(by_decimals, by_digits)


def encode_joint_line(seq: int, joints_rad: Any) -> bytes:
    """``$J`` sentence bytes (CR LF included)."""
    q = [format_joint(float(v)) for v in joints_rad]
    return _sentence(f"J,{seq % SEQ_MODULO}," + ",".join(q))


def encode_status_line(seq: int, status: StatusLine | RobotStatus) -> bytes:
    """``$S`` sentence bytes (CR LF included)."""
    v = (status.drives_powered, status.e_stopped, status.error_code, status.in_error,
         status.in_motion, status.mode, status.motion_possible)  # fmt: skip
    return _sentence(f"S,{seq % SEQ_MODULO}," + ",".join(str(int(x)) for x in v))


def decode_line(line: bytes) -> JointLine | StatusLine | None:
    """Decode one line (with or without CR LF).  Returns None for an unknown sentence letter.

    Raises
    ------
    ProtocolError
        Not ``$…*CS``, bad checksum, wrong field count, unparsable or non-finite numbers.
    """
    text = line.rstrip(b"\r\n")
    if len(text) + 2 > MAX_LINE_BYTES:
        raise ProtocolError(f"serial line of {len(text)} bytes exceeds {MAX_LINE_BYTES}")
    if not text.startswith(b"$") or len(text) < 4 or text[-3:-2] != b"*":
        raise ProtocolError(f"serial line {text[:40]!r} is not '$<payload>*<2 hex digits>'")
    payload, cs_text = text[1:-3], text[-2:]
    try:
        cs = int(cs_text, 16)
    except ValueError:
        raise ProtocolError(f"serial line checksum {cs_text!r} is not 2 hex digits") from None
    if cs != checksum(payload):
        raise ProtocolError(
            f"serial line checksum mismatch: line says {cs:02X}, payload gives {checksum(payload):02X} "
            f"({text[:40]!r}); check baud rate / parity / cable"
        )
    try:
        fields = payload.decode("ascii").split(",")
    except UnicodeDecodeError:
        raise ProtocolError(f"serial line {text[:40]!r} is not ASCII") from None
    kind = fields[0]
    try:
        if kind == "J":
            if len(fields) != 2 + N_JOINTS:
                raise ProtocolError(f"$J line has {len(fields) - 2} joint fields, expected {N_JOINTS}")
            q = tuple(float(f) for f in fields[2:])
            if not all(math.isfinite(v) for v in q):
                raise ProtocolError(f"$J line carries a non-finite joint value: {fields[2:]}")
            return JointLine(int(fields[1]), q)
        if kind == "S":
            if len(fields) != 2 + N_STATUS_FIELDS:
                raise ProtocolError(f"$S line has {len(fields) - 2} fields, expected {N_STATUS_FIELDS}")
            return StatusLine(*(int(f) for f in fields[1:]))
    except ValueError as e:
        raise ProtocolError(f"serial line {text[:40]!r}: bad number ({e})") from None
    return None


class LineSplitter:
    """Cut a byte stream into lines ended by CR, LF or CR LF; drop overlong garbage.

    A VAL3 ``sio`` string write ends with the port's end-of-string character
    (CR, 13), so CR alone must terminate a line too.  Empty lines are ignored.
    """

    def __init__(self, max_line_bytes: int = MAX_LINE_BYTES) -> None:
        self._buf = bytearray()
        self.max_line_bytes = max_line_bytes
        self.overflows = 0

    def feed(self, data: bytes) -> list[bytes]:
        self._buf += data
        out: list[bytes] = []
        while True:
            cr, lf = self._buf.find(b"\r"), self._buf.find(b"\n")
            ends = [i for i in (cr, lf) if i >= 0]
            if not ends:
                if len(self._buf) > self.max_line_bytes:
                    self._buf.clear()  # no terminator in sight: garbage
                    self.overflows += 1
                break
            i = min(ends)
            line = bytes(self._buf[:i])
            del self._buf[: i + 1]
            if not line:
                continue
            if len(line) + 2 > self.max_line_bytes:
                self.overflows += 1
                continue
            out.append(line + b"\r\n")
        return out


class SerialLink(BaseLink):
    """Read-only serial client (``serial:///dev/ttyS0?baudrate=115200``).

    Options: ``baudrate`` (115200), ``parity`` (N/E/O), ``stopbits`` (1/2),
    ``bytesize`` (8), plus those of :class:`~drivers.base.BaseLink`.
    """

    scheme = "serial"

    def __init__(self, url: str, **options: Any) -> None:
        parts = urlsplit(url)
        path = unquote(parts.path)
        if parts.scheme != self.scheme or not path:
            raise LinkConfigError(f"expected serial:///dev/ttyXXX?baudrate=115200, got {url!r}")
        self.path = path
        opts: dict[str, Any] = {**parse_query(url), **options}
        try:
            self.baudrate = int(opts.pop("baudrate", DEFAULT_BAUDRATE))
            self.bytesize = int(opts.pop("bytesize", 8))
            self.stopbits = float(opts.pop("stopbits", 1))
        except ValueError as e:
            raise LinkConfigError(f"{url}: bad serial option ({e})") from None
        self.parity = str(opts.pop("parity", "N")).upper()[:1]
        if self.parity not in "NEO" or self.bytesize not in (7, 8) or self.stopbits not in (1, 1.5, 2):
            raise LinkConfigError(f"{url}: parity must be N/E/O, bytesize 7/8, stopbits 1/1.5/2")
        super().__init__(url, **base_options(opts, url))
        self._serial: Any = None
        self._fd: int | None = None
        self._splitter = LineSplitter()
        self._last_seq: int | None = None

    def joint_resolution_rad(self, joints_rad: Sequence[float]) -> tuple[float, ...]:
        """Joints are decimal text (9 significant digits, 8 decimals from the VAL3 program): half a unit in
        the last digit (5e-9 rad at 127.5°, :func:`text_rounding_rad`)."""
        return tuple(text_rounding_rad(q) for q in joints_rad)

    async def _session(self) -> None:
        import serial

        loop = asyncio.get_running_loop()
        try:
            ser = serial.Serial(
                self.path, baudrate=self.baudrate, bytesize=self.bytesize, parity=self.parity,
                stopbits=self.stopbits, timeout=0, exclusive=True,
            )  # fmt: skip
        except serial.SerialException as e:
            raise OSError(f"cannot open serial port {self.path}: {e}") from None
        self._serial = ser
        ser.reset_input_buffer()  # lines queued while nobody listened are stale
        self._splitter = LineSplitter()
        self._last_seq = None
        closed: asyncio.Future[BaseException] = loop.create_future()
        fd = ser.fileno()
        self._fd = fd

        def on_readable() -> None:
            try:
                data = ser.read(ser.in_waiting or 1)
            except Exception as e:  # pyserial raises SerialException on EIO / hang-up
                if not closed.done():
                    closed.set_result(OSError(f"serial read failed: {e}"))
                loop.remove_reader(fd)
                return
            if data:
                self._on_bytes(data, time.monotonic())

        loop.add_reader(fd, on_readable)
        self._mark_up()
        started = time.monotonic()
        check_s = min(0.5, self.silence_reconnect_s / 4)
        while not self._closing.is_set():
            done, _ = await asyncio.wait({closed}, timeout=check_s)
            if done:
                raise closed.result()
            if self._silence_exceeded(started):
                raise TimeoutError(f"no valid line for more than {self.silence_reconnect_s:g} s")

    def _on_bytes(self, data: bytes, t_s: float) -> None:
        before = self._splitter.overflows
        lines = self._splitter.feed(data)
        if self._splitter.overflows != before:
            self._count("frames_rejected", self._splitter.overflows - before)
            log.warning("robot link %s: discarded an overlong line (garbage on the wire?)", self.url)
        for line in lines:
            try:
                msg = decode_line(line)
            except ProtocolError as e:
                self._count("frames_rejected")
                log.warning("robot link %s: %s; line skipped", self.url, e)
                continue
            if isinstance(msg, JointLine):
                if self._last_seq is not None:
                    gap = (msg.seq - self._last_seq - 1) % SEQ_MODULO
                    if gap:
                        self._count("frames_lost", gap)
                self._last_seq = msg.seq
                self._publish_joints(msg.joints_rad, t_s)
            elif isinstance(msg, StatusLine):
                self._publish_status(msg.to_robot_status(t_s))
            else:
                self._count("unknown_frames")

    async def _cleanup(self) -> None:
        ser, self._serial = self._serial, None
        fd, self._fd = self._fd, None
        if fd is not None:
            asyncio.get_running_loop().remove_reader(fd)
        if ser is not None:
            ser.close()
