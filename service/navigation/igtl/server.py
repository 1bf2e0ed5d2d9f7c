"""A small asyncio OpenIGTLink server: the registration and the live tool pose, to any
number of clients (3D Slicer OpenIGTLinkIF, PLUS-style consumers).

Devices (PLUS / SlicerIGT naming ``<From>To<To>``, research §3.2):

``RobotToImage`` (TRANSFORM)
    ``ras_from_robot = RAS_FROM_LPS @ image_from_robot``: maps a point in the robot base
    frame (mm) to the scan's patient coordinates **in RAS** (mm), which is what Slicer's
    scene uses; ``image_from_robot`` itself is DICOM LPS (design §3) and the TRANSFORM
    message carries no coordinate field, so the flip ``diag(-1, -1, 1, 1)`` is applied here
    on the image side only (the robot frame is not a patient frame and is not flipped).
``ToolToImage`` (TRANSFORM)
    ``RAS_FROM_LPS @ image_from_robot @ robot_from_tool0(q) @ tool0_from_tcp``: the TCP pose
    in image RAS from the latest joints, sent whenever a new joint sample arrives (the link
    rate), on connect, and at least every ``period_s``.
``PhantomSpheres`` (POINT)
    The registration's matched spheres in image RAS (mm): each phantom sphere centre as the
    registration maps it (``image_from_robot`` applied to its robot-frame centre), named
    ``<hole id> <residual> mm`` (the residual: distance to its detected centre).  Sent on connect,
    on every change of the registration and on ``GET_POINT``, not periodically (a POINT list
    would reset a Slicer user's markup edits every second).

Never an invalid transform (PLUS's ``SendValidTransformsOnly``): a device that has no valid
value (no current registration, robot link down or stale, kinematics failed) is sent as a
STATUS message under the device's own name instead, to every client whatever its header
version: code ``NOT_READY`` (13, no registration), ``TIME_OUT`` (7, robot link) or
``UNKNOWN_ERROR`` (2), error name ``INVALID``, the reason as status string.  With
``send_invalid_transforms_v2`` a version-2 client also gets the TRANSFORM with the metadata
``TransformStatus=INVALID`` (an identity matrix that must not be used); a version-1 client, which
cannot see metadata, never gets a matrix for an invalid device.

Queries answered: ``GET_TRANS`` (the reference library's spelling) and ``GET_TRANSFOR`` (the
12-byte cut of ``GET_TRANSFORM``) with the named device only, or every device when the name is
empty; ``GET_POINT`` the same for POINT devices; ``GET_STATUS`` with a STATUS of the service
(``OK`` when a registration is current and the robot link delivers, else the reasons);
``GET_CAPABIL`` with a CAPABILITY listing :data:`CAPABILITY_TYPES`.  An unknown device name gets
a STATUS ``NOT_FOUND`` (4) naming the devices.

Header version, per client: every client is sent header version 1 (bare content, no
metadata: what the reference library reads by default, OpenIGTLink ticket 200) until it has sent
a well-formed message with header version 2 (SlicerOpenIGTLink sends a dummy version-2 STATUS at
connect for exactly this, PR #65); from then on it gets version 2 with the metadata below, the
PLUS rule (answer in the highest version received from that client), and every device is sent
again at once with its metadata.  A client that never writes keeps version 1.

Version 2 carries the metadata (the honest figure first) ``ChainError_pred_mm`` and
``ChainErrorSource`` (whether a calibration backs it), ``TransformStatus`` (``OK`` /
``INVALID``), ``RegistrationId``, ``FRE_mm``, ``TRE_pred_mm`` (the one-scan figure),
``ImageFrame=RAS``, ``SourceFrame`` and, when the newest registration was refused while an older
one stays current, ``LastRefusal``; INVALID ones give ``Reason``.

Listener limits (``docs/security.md``, OpenIGTLink listener limits): at most ``max_clients``
connections (more are closed at once, counted ``refused_full``), at most ``max_clients_per_address``
of them from one peer address (more from it are closed at once, counted ``refused_per_address``; a
full listener and these refusals are health problems, :meth:`IgtlServer.slot_report`); each message
type class has a maximum body size (STATUS, queries, anything else): a larger BODY_SIZE closes the
connection before a byte of the body is read; once a message has started (its first byte), the rest
must arrive within ``stall_timeout_s`` or the connection is closed (a client that only receives, as
Slicer does, is never timed out); a malformed header closes the connection.  The body CRC is
crcmod's C code (a 64 KiB body in about 0.2 ms); the server refuses to start without it.  Each
client has a bounded queue: when it is full the oldest message is dropped; a client whose socket
stays blocked for longer than ``slow_client_timeout_s`` is disconnected.  Queries are read one
message at a time, yielding to the event loop between messages, and answered at most
``max_query_answers_per_s`` per client (a faster client is read no faster); an answer waiting to be
sent is replaced by a newer one of the same type and device (the latest state, not a backlog); a
client that sends a query while more than ``client_buffer_bytes`` wait for it to read is dropped
(``slow_reader_drops``).  Nothing here ever blocks the caller or the other clients.  OpenIGTLink has
no authentication: binding anything but loopback requires an explicit ``allowed_peer_addresses``
list, and peers not on the list are closed at once.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import math
import socket
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import numpy as np

from registration.arrays import F64
from service.errors import IgtlConfigError, IgtlCrcError, IgtlPeerError, IgtlWireError
from service.navigation.igtl import wire
from service.netaddr import in_networks, is_loopback, parse_networks, printable
from service.settings import as_enabled

if TYPE_CHECKING:
    from service.settings import IgtlSettings

log = logging.getLogger(__name__)

RAS_FROM_LPS: F64 = np.diag([-1.0, -1.0, 1.0, 1.0])
"""DICOM patient LPS → Slicer RAS (its own inverse)."""

DEFAULT_PORT = 18944
"""The OpenIGTLink / PLUS convention (research §3.3)."""


# --------------------------------------------------------------------------- state source


@dataclass(frozen=True)
class SpherePoint:
    """One matched sphere for the POINT device: its centre in the image (DICOM LPS, mm) as the
    registration maps it, its phantom hole id and its residual (mm)."""

    sphere: str
    image_lps_mm: tuple[float, float, float]
    residual_mm: float


@dataclass(frozen=True)
class RegistrationView:
    """The current registration as the server needs it.

    ``image_from_robot`` : (4, 4) float64, robot mm → image (DICOM LPS) mm.
    """

    image_from_robot: F64
    registration_id: str
    fre_mm: float
    tre_pred_mm: float | None = None
    chain_error_mm: float | None = None
    """The registration's ``predicted_chain_error_mm`` (metadata ``ChainError_pred_mm``)."""
    chain_error_source: str = ""
    """Whether a calibration backs ``chain_error_mm`` (metadata ``ChainErrorSource``)."""
    evidence: str = ""
    """What backs the robot side: calibrated, verified or unverified (metadata ``Evidence``, first;
    service.registrations.evidence)."""
    spheres: tuple[SpherePoint, ...] = ()
    sphere_diameter_mm: float = 0.0


@dataclass(frozen=True)
class Refusal:
    """The newest refused registration (the previous current one stays current)."""

    registration_id: str
    reason: str


@dataclass(frozen=True)
class RegistrationState:
    current: RegistrationView | None
    last_refusal: Refusal | None = None
    no_current_reason: str = ""
    """Why nothing is current (e.g. ``registration 4 was withdrawn: …``); "" = none accepted yet."""


@dataclass(frozen=True)
class JointView:
    """Latest joints and link health.  ``t_s`` is ``time.monotonic()`` at receipt;
    ``health`` is ``"connected"``, ``"stale"`` or ``"down"`` (drivers.base.LinkHealth)."""

    joints_rad: tuple[float, ...]
    t_s: float
    health: str
    reason: str = ""


@dataclass(frozen=True)
class IgtlStateSource:
    """What the server reads, through callbacks (called on the server's event loop; they
    must be quick and thread-safe).  ``joints`` returns None when no sample exists yet."""

    registration: Callable[[], RegistrationState]
    joints: Callable[[], JointView | None]
    robot_from_tool0: Callable[[Sequence[float]], F64]
    tool0_from_tcp: F64 = field(default_factory=lambda: np.eye(4))


# --------------------------------------------------------------------------- config
# Every limit and period is an ``[igtl]`` setting (:class:`service.settings.IgtlSettings`: the
# defaults and their origin are there).

CAPABILITY_TYPES: tuple[str, ...] = (
    "TRANSFORM", "POINT", "STATUS", "CAPABILITY",
    "GET_TRANS", "GET_TRANSFOR", "GET_POINT", "GET_STATUS", "GET_CAPABIL",
)  # fmt: skip
"""What the server sends (TRANSFORM, POINT, STATUS, CAPABILITY) and answers (the GET_ types)."""

_QUERY_PREFIXES = ("GET_", "STT_", "STP_", "RTS_")


REGISTRATION_DEVICE = "RobotToImage"
TOOL_DEVICE = "ToolToImage"
POINTS_DEVICE = "PhantomSpheres"
TRANSFORM_DEVICES: tuple[str, str] = (REGISTRATION_DEVICE, TOOL_DEVICE)


def max_body_bytes(settings: IgtlSettings, msg_type: str) -> int:
    """The largest body accepted for a message of ``msg_type`` (module docstring)."""
    if msg_type == "STATUS":
        return settings.status_max_body_bytes
    if msg_type.startswith(_QUERY_PREFIXES):
        return settings.query_max_body_bytes
    return settings.other_max_body_bytes


# --------------------------------------------------------------------------- messages


@dataclass(frozen=True)
class _Out:
    """A message to send, packed per client (each client numbers its own MSG_IDs and gets
    metadata only in header version 2)."""

    type: str
    device: str
    content: bytes
    metadata: dict[str, str]
    timestamp_s: float
    v2_only: bool = False
    """Sent to version-2 clients only (an INVALID transform: its matrix must not reach a version-1
    client, which cannot read the metadata that says so)."""


def _fmt(v: float) -> str:
    return f"{v:.6g}"


def _transform(device: str, matrix: F64, meta: dict[str, str]) -> _Out:
    return _Out("TRANSFORM", device, wire.pack_transform_content(matrix), meta, time.time())


def invalid_messages(
    device: str, reason: str, code: int, meta: dict[str, str], cfg: IgtlSettings
) -> list[_Out]:
    """What replaces the TRANSFORM of an invalid device: a STATUS to everyone (code, ``INVALID``,
    the reason), and with ``send_invalid_transforms_v2`` the INVALID TRANSFORM to version 2 only."""
    meta = {**meta, "TransformStatus": "INVALID", "Reason": reason[:500]}
    content = wire.status_content(code, error_name="INVALID", status_string=reason)
    out = [_Out("STATUS", device, content, meta, time.time())]
    if cfg.send_invalid_transforms_v2:
        out.append(_Out("TRANSFORM", device, wire.pack_transform_content(np.eye(4)), meta, time.time(), True))
    return out


def _no_registration(state: RegistrationState) -> str:
    return state.no_current_reason or "no current registration"


def _figures(cur: RegistrationView) -> dict[str, str]:
    """The registration's figures, the chain's expected error first (the honest figure)."""
    meta: dict[str, str] = {}
    if cur.evidence:
        meta["Evidence"] = cur.evidence
    if cur.chain_error_mm is not None:
        meta["ChainError_pred_mm"] = _fmt(cur.chain_error_mm)
        meta["ChainErrorSource"] = cur.chain_error_source[:200] or "unknown"
    meta["RegistrationId"] = cur.registration_id
    meta["FRE_mm"] = _fmt(cur.fre_mm)
    if cur.tre_pred_mm is not None:
        meta["TRE_pred_mm"] = _fmt(cur.tre_pred_mm)
    return meta


def registration_messages(state: RegistrationState, cfg: IgtlSettings) -> list[_Out]:
    """The ``RobotToImage`` device for ``state`` (see the module docstring)."""
    meta: dict[str, str] = {"ImageFrame": "RAS", "SourceFrame": "robot"}
    cur = state.current
    if state.last_refusal is not None:
        meta["LastRefusal"] = f"{state.last_refusal.registration_id}: {state.last_refusal.reason}"[:500]
    if cur is None:
        return invalid_messages(
            REGISTRATION_DEVICE, _no_registration(state), wire.STATUS_NOT_READY, meta, cfg
        )
    with np.errstate(all="ignore"):
        matrix = RAS_FROM_LPS @ cur.image_from_robot
    if not np.all(np.isfinite(matrix)):  # never a matrix the receiver cannot trust (nor a dead push loop)
        reason = f"registration {cur.registration_id} has a non-finite matrix"
        return invalid_messages(REGISTRATION_DEVICE, reason, wire.STATUS_UNKNOWN_ERROR, meta, cfg)
    meta = {**_figures(cur), "TransformStatus": "OK", **meta}
    return [_transform(REGISTRATION_DEVICE, matrix, meta)]


def points_messages(state: RegistrationState, cfg: IgtlSettings) -> list[_Out]:
    """The ``PhantomSpheres`` POINT list (image RAS), or its STATUS without a registration."""
    cur = state.current
    meta: dict[str, str] = {"ImageFrame": "RAS"}
    if cur is None:
        return invalid_messages(POINTS_DEVICE, _no_registration(state), wire.STATUS_NOT_READY, meta, cfg)[:1]
    points = []
    for sp in cur.spheres:
        ras = (RAS_FROM_LPS[:3, :3] @ np.asarray(sp.image_lps_mm, dtype=np.float64)).tolist()
        points.append(
            wire.Point(
                name=f"{sp.sphere} {sp.residual_mm:.3f} mm",
                position_mm=(ras[0], ras[1], ras[2]),
                diameter_mm=cur.sphere_diameter_mm,
                owner="",
            )
        )
    meta["RegistrationId"] = cur.registration_id
    meta["Spheres"] = ",".join(sp.sphere for sp in cur.spheres)[:2000]
    meta["Residuals_mm"] = ",".join(f"{sp.residual_mm:.4f}" for sp in cur.spheres)[:2000]
    return [_Out("POINT", POINTS_DEVICE, wire.point_content(points), meta, time.time())]


def tool_messages(
    state: RegistrationState,
    joints: JointView | None,
    source: IgtlStateSource,
    cfg: IgtlSettings,
    now_t_s: float,
) -> list[_Out]:
    """The ``ToolToImage`` device (a STATUS without registration, or with a down/stale link)."""
    meta: dict[str, str] = {"ImageFrame": "RAS", "SourceFrame": "tcp"}
    reason, code = "", wire.STATUS_TIME_OUT
    if state.current is None:
        reason, code = _no_registration(state), wire.STATUS_NOT_READY
    elif joints is None:
        reason = "no joint sample received"
    elif joints.health != "connected":
        reason = f"robot link {joints.health}: {joints.reason}"
    elif now_t_s - joints.t_s > cfg.joint_max_age_s:
        reason = f"joint sample is {now_t_s - joints.t_s:.3f} s old (> {cfg.joint_max_age_s:g} s)"
    if state.current is not None:
        meta["RegistrationId"] = state.current.registration_id
        if state.current.evidence:
            meta["Evidence"] = state.current.evidence
    if not reason:
        assert joints is not None and state.current is not None
        try:
            with np.errstate(all="ignore"):  # a non-finite result is refused just below
                robot_from_tcp = source.robot_from_tool0(joints.joints_rad) @ source.tool0_from_tcp
                m = RAS_FROM_LPS @ state.current.image_from_robot @ robot_from_tcp
            if not np.all(np.isfinite(m)):
                raise ValueError("the pose is not finite")
        except Exception as e:  # KinematicsError or a bug in the callback: never a matrix, keep serving
            reason, code = f"forward kinematics failed: {e}", wire.STATUS_UNKNOWN_ERROR
        else:
            return [_transform(TOOL_DEVICE, m, {"TransformStatus": "OK", **meta})]
    return invalid_messages(TOOL_DEVICE, reason, code, meta, cfg)


def service_status(state: RegistrationState, tool: list[_Out]) -> tuple[int, str]:
    """``(code, text)`` of the ``GET_STATUS`` answer: OK when every device is valid."""
    if state.current is None:
        return wire.STATUS_NOT_READY, _no_registration(state)
    cur = state.current
    text = f"registration {cur.registration_id} current"
    if cur.chain_error_mm is not None:
        text += f"; expected error at working poses {cur.chain_error_mm:.3g} mm ({cur.chain_error_source})"
    if tool[0].type != "TRANSFORM":
        return wire.STATUS_TIME_OUT, f"{text}; {tool[0].device}: {tool[0].metadata.get('Reason', '')}"
    return wire.STATUS_OK, text


# --------------------------------------------------------------------------- clients

_QUERY_BURST_S = 0.1
"""A client's queries may come in a burst worth this long at ``max_query_answers_per_s`` (24 at 240/s:
a poller's queries for every device at once) before its pace applies."""


@dataclass(frozen=True)
class _AnswerKey:
    """Stands in a client's queue for its pending answer of this type and device."""

    type: str
    device: str


class _Client:
    """One connected peer: a bounded queue drained by its own writer task."""

    def __init__(
        self, server: IgtlServer, reader: asyncio.StreamReader, writer: asyncio.StreamWriter
    ) -> None:
        self.server = server
        self.reader = reader
        self.writer = writer
        peer = writer.get_extra_info("peername")
        self.peer = f"{peer[0]}:{peer[1]}" if isinstance(peer, tuple) else str(peer)
        self.queue: asyncio.Queue[_Out | _AnswerKey | None] = asyncio.Queue(
            maxsize=server.config.client_queue_max
        )
        self.answers: dict[_AnswerKey, _Out] = {}
        """The one pending answer per (type, device); the queue holds its key in its place."""
        self.next_query_t = -math.inf
        """``time.monotonic()`` from which the next query may be answered (the per-client pace)."""
        self.seq = 0
        self.dropped = 0
        self.header_version = 1
        """1 until this client has sent a well-formed version-2 message (module docstring)."""
        self.tasks: list[asyncio.Task[None]] = []

    def offer(self, out: _Out) -> None:
        """Enqueue without blocking; drop the oldest message when full."""
        self._put(out)

    def offer_answer(self, out: _Out) -> None:
        """Enqueue a query's answer, replacing the one of the same type and device still waiting."""
        key = _AnswerKey(out.type, out.device)
        if key in self.answers:
            self.answers[key] = out
            self.server.counters["answers_coalesced"] += 1
            return
        self.answers[key] = out
        self._put(key)

    def _put(self, item: _Out | _AnswerKey) -> None:
        if self.queue.full():
            with contextlib.suppress(asyncio.QueueEmpty):
                old = self.queue.get_nowait()
                if isinstance(old, _AnswerKey):
                    self.answers.pop(old, None)
                self.dropped += 1
                self.server.counters["dropped"] += 1
        self.queue.put_nowait(item)

    def backlog_bytes(self) -> int:
        """Bytes written for this client and not yet taken by its socket."""
        return int(self.writer.transport.get_write_buffer_size())

    def _pack(self, out: _Out) -> bytes | None:
        v2 = self.header_version >= 2
        if out.v2_only and not v2:
            return None
        self.seq += 1
        return wire.pack_message(
            out.type, out.device, out.content, timestamp_s=out.timestamp_s,
            metadata=out.metadata if v2 else None, message_id=self.seq if v2 else 0,
            header_version=2 if v2 else 1,
        )  # fmt: skip

    async def write_loop(self) -> None:
        timeout = self.server.config.slow_client_timeout_s
        try:
            while (item := await self.queue.get()) is not None:
                out = self.answers.pop(item, None) if isinstance(item, _AnswerKey) else item
                if out is None:
                    continue
                raw = self._pack(out)
                if raw is None:
                    continue
                self.writer.write(raw)
                self.server.counters["sent"] += 1
                try:
                    await asyncio.wait_for(self.writer.drain(), timeout)
                except TimeoutError:
                    self.server.counters["slow_disconnects"] += 1
                    log.warning(
                        "OpenIGTLink client %s accepted nothing for %.1f s (dropped %d); disconnecting",
                        self.peer, timeout, self.dropped,
                    )  # fmt: skip
                    return
        except (ConnectionError, OSError) as e:
            log.info("OpenIGTLink client %s: %s", self.peer, e)
        finally:
            self.writer.transport.abort()

    async def _read_message(self) -> tuple[wire.Header, bytes]:
        """One message.  Waits without limit for its first byte (a client that only receives is
        fine); from then on the rest must come within ``stall_timeout_s``; a BODY_SIZE above the
        type's limit ends the connection before the body is read."""
        cfg = self.server.config
        first = await self.reader.readexactly(1)
        try:
            async with asyncio.timeout(cfg.stall_timeout_s):
                head = wire.unpack_header(first + await self.reader.readexactly(wire.HEADER_SIZE - 1))
                if head.version not in (1, 2):
                    raise IgtlWireError(f"header version {head.version} (this server reads 1 and 2)")
                limit = max_body_bytes(cfg, head.type)
                if head.body_size > limit:
                    raise IgtlPeerError(
                        "oversize",
                        f"announced a {head.body_size}-byte {head.type!r} body, over the {limit}-byte "
                        "limit for that type",
                    )
                return head, await self.reader.readexactly(head.body_size)
        except TimeoutError:
            raise IgtlPeerError(
                "stalled", f"sent part of a message and nothing more for {cfg.stall_timeout_s:g} s"
            ) from None
        except IgtlWireError as e:
            raise IgtlPeerError("bad_headers", f"sent a bad header ({e})") from None

    async def read_loop(self) -> None:
        """Read what the client sends (header version 1 or 2), switch it to version 2 after its
        first well-formed version-2 message, answer the queries (paced, see the module docstring); end on
        EOF or a broken limit."""
        cfg = self.server.config
        try:
            while True:
                head, body = await self._read_message()
                try:
                    msg = wire.unpack_body(head, body)
                except IgtlCrcError as e:
                    self.server.counters["bad_crc"] += 1
                    log.warning("OpenIGTLink client %s: %s; message ignored", self.peer, e)
                    continue
                except IgtlWireError as e:
                    raise IgtlPeerError("bad_headers", f"sent a malformed version-2 body ({e})") from None
                del msg
                if head.version == 2 and self.header_version < 2:
                    self.header_version = 2
                    log.info("OpenIGTLink client %s sent header version 2; answering in version 2", self.peer)
                    self.server._report("header_version", self)
                    self.server.push_current(self, points=True)  # the metadata now, not a period later
                if head.type.startswith("GET_"):
                    if self.backlog_bytes() > cfg.client_buffer_bytes:
                        self.server._drop_slow_reader(self)
                        return
                    await self._pace()
                self.server._answer(self, head.type, head.device_name)
                await asyncio.sleep(0)  # a yield, not a wait: the next buffered message after the others
        except (asyncio.IncompleteReadError, ConnectionError, OSError):
            pass
        except IgtlPeerError as e:
            self.server.counters[e.counter] += 1
            log.warning("OpenIGTLink client %s %s; closing the connection", self.peer, e)
        finally:
            self.writer.transport.abort()

    async def _pace(self) -> None:
        """Wait until this client's next query may be answered: at most ``max_query_answers_per_s``, in
        bursts of up to :data:`_QUERY_BURST_S` of that rate.  Its socket is not read meanwhile."""
        now = time.monotonic()
        interval = 1.0 / self.server.config.max_query_answers_per_s
        t = max(self.next_query_t, now - _QUERY_BURST_S)
        self.next_query_t = t + interval
        if t > now:
            self.server.counters["queries_paced"] += 1
            await asyncio.sleep(t - now)

    @property
    def host(self) -> str:
        peer = self.writer.get_extra_info("peername")
        return str(peer[0]) if isinstance(peer, tuple) else ""

    def info(self) -> dict[str, object]:
        """For ``/status``: who, which header version, how much was sent / dropped."""
        return {"peer": self.peer, "header_version": self.header_version, "sent": self.seq,
                "dropped": self.dropped}  # fmt: skip


# --------------------------------------------------------------------------- server

_REFUSAL_LOG_EVERY_S = 10.0
"""A flood of refused connections (or of dropped slow readers) is logged once per this period (with
the count), not per peer."""


@dataclass(frozen=True)
class SlotReport:
    """Who holds the listener's slots and who was refused one (``service.http.health``)."""

    clients: int
    max_clients: int
    address_share: int
    """``igtl.max_clients_per_address`` (capped at ``max_clients``)."""
    by_address: dict[str, int]
    """Connections held per peer address, the most first."""
    full_refused_s_ago: float | None
    """Seconds since a connection was last refused because the listener was full (None: never)."""
    full_refused_host: str
    address_refused_s_ago: float | None
    """Seconds since an address was last refused for holding its share (None: never)."""
    address_refused_host: str


class IgtlServer:
    """Serve ``RobotToImage``, ``ToolToImage`` and ``PhantomSpheres`` (see the module docstring).

    Construct, then ``await start()`` on the event loop that should own it; ``await stop()``.
    :meth:`notify` (thread-safe) asks for an immediate push after a registration change; the
    server also notices changes by itself at ``poll_period_s``.
    """

    def __init__(
        self,
        config: IgtlSettings,
        source: IgtlStateSource,
        *,
        on_client: Callable[[str, str, int, int], None] | None = None,
    ) -> None:
        self.config = as_enabled(config, IgtlConfigError)
        self.source = source
        self.on_client = on_client
        """``on_client(event, peer, n_clients, header_version)`` on the loop; event ``connected`` /
        ``header_version`` (the client switched to version 2) / ``disconnected``."""
        self._networks = parse_networks(config.allowed_peer_addresses, "igtl.allowed_peer_addresses")
        self._server: asyncio.Server | None = None
        self._loop: asyncio.AbstractEventLoop | None = None
        self._clients: set[_Client] = set()
        self._handlers: set[asyncio.Task[object]] = set()
        self._wake: asyncio.Event | None = None
        self._tick_task: asyncio.Task[None] | None = None
        self._refusals_logged_at = -math.inf
        self._refusals_unlogged = 0
        self._slow_logged_at = -math.inf
        self._slow_unlogged = 0
        self._full_refused: tuple[float, str] | None = None
        self._address_refused: tuple[float, str] | None = None
        self.counters: dict[str, int] = {
            "connects": 0, "refused_peers": 0, "refused_full": 0, "refused_per_address": 0, "sent": 0,
            "dropped": 0, "slow_disconnects": 0, "slow_reader_drops": 0, "bad_headers": 0, "bad_crc": 0,
            "oversize": 0, "stalled": 0, "queries": 0, "queries_paced": 0, "answers_coalesced": 0,
        }  # fmt: skip

    @property
    def port(self) -> int:
        """The bound port (useful with ``port=0``)."""
        if self._server is None or not self._server.sockets:
            raise RuntimeError("the OpenIGTLink server is not started")
        return int(self._server.sockets[0].getsockname()[1])

    @property
    def client_count(self) -> int:
        return len(self._clients)

    def client_info(self) -> list[dict[str, object]]:
        """Each connected client's peer address and header version (``/status``).  Read from any thread:
        a copy of the client set is taken at once (the event loop adds clients meanwhile)."""
        return sorted((c.info() for c in list(self._clients)), key=lambda d: str(d["peer"]))

    def slot_report(self) -> SlotReport:
        """The listener's slots: held per address, the latest refusals (for the health problems).  Read
        from any thread (a copy of the client set is taken at once)."""
        clients = list(self._clients)
        by_address: dict[str, int] = {}
        for c in clients:
            by_address[c.host] = by_address.get(c.host, 0) + 1
        now = time.monotonic()
        full, share = self._full_refused, self._address_refused
        return SlotReport(
            clients=len(clients),
            max_clients=self.config.max_clients,
            address_share=self.config.address_share,
            by_address=dict(sorted(by_address.items(), key=lambda kv: (-kv[1], kv[0]))),
            full_refused_s_ago=None if full is None else now - full[0],
            full_refused_host="" if full is None else full[1],
            address_refused_s_ago=None if share is None else now - share[0],
            address_refused_host="" if share is None else share[1],
        )

    async def start(self) -> None:
        if not wire.native_crc():
            raise IgtlConfigError(
                "crcmod runs without its C extension (pure Python, ~8 MB/s: a message's CRC would hold "
                "the service); reinstall it with a C compiler present: pip install --force-reinstall "
                "--no-binary crcmod crcmod (Debian: apt install python3-dev gcc)"
            )
        self._loop = asyncio.get_running_loop()
        self._wake = asyncio.Event()
        try:
            self._server = await asyncio.start_server(self._on_connect, self.config.host, self.config.port)
        except OSError as e:
            raise IgtlConfigError(
                f"cannot listen for OpenIGTLink on {self.config.host}:{self.config.port} ({e}); "
                "is another server (PLUS, Slicer) using the port?"
            ) from None
        self._tick_task = asyncio.create_task(self._tick(), name="igtl-tick")
        log.info("OpenIGTLink server on %s:%d", self.config.host, self.port)

    async def stop(self) -> None:
        if self._tick_task is not None:
            self._tick_task.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await self._tick_task
            self._tick_task = None
        if self._server is not None:
            self._server.close()
        tasks = [t for c in list(self._clients) for t in c.tasks]
        for c in list(self._clients):
            c.writer.transport.abort()
        for t in tasks:
            t.cancel()
        await asyncio.gather(*tasks, *self._handlers, return_exceptions=True)
        self._clients.clear()
        if self._server is not None:
            await self._server.wait_closed()
            self._server = None

    def notify(self) -> None:
        """Push now (thread-safe, never blocks): call after a registration changed."""
        if self._loop is not None and self._wake is not None:
            self._loop.call_soon_threadsafe(self._wake.set)

    def push_current(self, client: _Client | None = None, *, points: bool = False) -> None:
        """Send the devices' current state to one client (or all); the POINT list with ``points``."""
        reg = self._registration()
        outs = [*registration_messages(reg, self.config), *self._tool(reg)]
        if points:
            outs += points_messages(reg, self.config)
        for c in [client] if client is not None else list(self._clients):
            for out in outs:
                c.offer(out)

    # ---- internals ------------------------------------------------------------

    def _answer(self, client: _Client, msg_type: str, device: str) -> None:
        """Answer a query (module docstring); other messages are read and ignored."""
        cfg = self.config
        if not msg_type.startswith("GET_"):
            return
        self.counters["queries"] += 1
        if not (device.isascii() and device.isprintable()):  # refused with a STATUS, not dropped
            log.warning("OpenIGTLink: %s for device %s refused: not a printable ASCII name", msg_type,
                        printable(device))  # fmt: skip
            why = wire.status_content(
                4, error_name="NOT_FOUND", status_string="device names are printable ASCII"
            )
            client.offer_answer(_Out("STATUS", "oarmreg", why, {}, time.time()))
            return
        reg = self._registration()
        outs: list[_Out]
        if msg_type in ("GET_TRANS", "GET_TRANSFOR"):
            if device and device not in TRANSFORM_DEVICES:
                outs = [self._not_found(device, TRANSFORM_DEVICES)]
            else:
                outs = []
                if device in ("", REGISTRATION_DEVICE):
                    outs += registration_messages(reg, cfg)
                if device in ("", TOOL_DEVICE):
                    outs += self._tool(reg)
        elif msg_type == "GET_POINT":
            ok = device in ("", POINTS_DEVICE)
            outs = points_messages(reg, cfg) if ok else [self._not_found(device, (POINTS_DEVICE,))]
        elif msg_type == "GET_STATUS":
            code, text = service_status(reg, self._tool(reg))
            content = wire.status_content(code, error_name="" if code == wire.STATUS_OK else "NOT_READY",
                                          status_string=text)  # fmt: skip
            outs = [_Out("STATUS", device or "oarmreg", content, {}, time.time())]
        elif msg_type == "GET_CAPABIL":
            content = wire.capability_content(CAPABILITY_TYPES)
            outs = [_Out("CAPABILITY", device or "oarmreg", content, {}, time.time())]
        else:
            outs = [_Out("STATUS", device or "oarmreg", wire.status_content(
                12, error_name="UNKNOWN", status_string=f"{msg_type} is not answered here; GET_CAPABIL lists "
                "what is"), {}, time.time())]  # fmt: skip
        for out in outs:
            client.offer_answer(out)

    @staticmethod
    def _not_found(device: str, known: tuple[str, ...]) -> _Out:
        text = f"no device {device!r} here; devices: {', '.join(known)}"
        return _Out("STATUS", device, wire.status_content(4, error_name="NOT_FOUND", status_string=text), {},
                    time.time())  # fmt: skip

    def _peer_allowed(self, host: str) -> bool:
        if not self._networks:
            return is_loopback(host)
        return in_networks(host, self._networks)

    def _refuse(self, writer: asyncio.StreamWriter, host: str, *, full: bool) -> None:
        """Close a connection the listener has no slot for: full, or its address at its share."""
        writer.transport.abort()
        now = time.monotonic()
        if full:
            self.counters["refused_full"] += 1
            self._full_refused = (now, host)
            why = f"igtl.max_clients = {self.config.max_clients} reached"
        else:
            self.counters["refused_per_address"] += 1
            self._address_refused = (now, host)
            why = f"{host} holds igtl.max_clients_per_address = {self.config.address_share}"
        self._refusals_unlogged += 1
        if now - self._refusals_logged_at >= _REFUSAL_LOG_EVERY_S:
            log.warning(
                "OpenIGTLink: %d connection(s) refused (latest from %s): %s",
                self._refusals_unlogged, host, why,
            )  # fmt: skip
            self._refusals_logged_at, self._refusals_unlogged = now, 0

    def _drop_slow_reader(self, client: _Client) -> None:
        """A client asked while its unread output is over ``client_buffer_bytes``: the read loop ends
        (and with it the connection); logged at most once per :data:`_REFUSAL_LOG_EVERY_S`."""
        self.counters["slow_reader_drops"] += 1
        self._slow_unlogged += 1
        now = time.monotonic()
        if now - self._slow_logged_at >= _REFUSAL_LOG_EVERY_S:
            log.warning(
                "OpenIGTLink: %d client(s) dropped for asking faster than they read (latest %s: %d bytes "
                "unread, over igtl.client_buffer_bytes = %d)",
                self._slow_unlogged, client.peer, client.backlog_bytes(), self.config.client_buffer_bytes,
            )  # fmt: skip
            self._slow_logged_at, self._slow_unlogged = now, 0

    async def _on_connect(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        peer = writer.get_extra_info("peername")
        host = str(peer[0]) if isinstance(peer, tuple) else ""
        if not self._peer_allowed(host):
            self.counters["refused_peers"] += 1
            log.warning("OpenIGTLink: peer %s is not in allowed_peer_addresses; closed", host)
            writer.transport.abort()
            return
        if len(self._clients) >= self.config.max_clients:
            self._refuse(writer, host, full=True)
            return
        if sum(1 for c in self._clients if c.host == host) >= self.config.address_share:
            self._refuse(writer, host, full=False)
            return
        handler = asyncio.current_task()
        if handler is not None:
            self._handlers.add(handler)
            handler.add_done_callback(self._handlers.discard)
        writer.transport.set_write_buffer_limits(high=self.config.client_buffer_bytes)
        sock = writer.get_extra_info("socket")
        if sock is not None:
            sock.setsockopt(socket.SOL_SOCKET, socket.SO_SNDBUF, self.config.socket_send_buffer_bytes)
        client = _Client(self, reader, writer)
        self._clients.add(client)
        self.counters["connects"] += 1
        log.info("OpenIGTLink client %s connected (%d now)", client.peer, len(self._clients))
        self._report("connected", client)
        self.push_current(client, points=True)
        client.tasks = [asyncio.create_task(client.write_loop()), asyncio.create_task(client.read_loop())]
        try:
            await asyncio.wait(client.tasks, return_when=asyncio.FIRST_COMPLETED)
        finally:
            writer.transport.abort()
            for t in client.tasks:
                t.cancel()
            await asyncio.gather(*client.tasks, return_exceptions=True)
            self._clients.discard(client)
            log.info("OpenIGTLink client %s gone (%d left)", client.peer, len(self._clients))
            self._report("disconnected", client)

    def _report(self, event: str, client: _Client) -> None:
        if self.on_client is not None:
            try:
                self.on_client(event, client.peer, len(self._clients), client.header_version)
            except Exception:
                log.exception("OpenIGTLink: on_client callback failed")

    def _registration(self) -> RegistrationState:
        try:
            return self.source.registration()
        except Exception:
            log.exception("OpenIGTLink: the registration callback failed; sending INVALID")
            return RegistrationState(None, no_current_reason="the registration could not be read")

    def _joints(self) -> JointView | None:
        try:
            return self.source.joints()
        except Exception:
            log.exception("OpenIGTLink: the joints callback failed; ToolToImage INVALID")
            return None

    def _tool(self, reg: RegistrationState, joints: JointView | None = None) -> list[_Out]:
        j = self._joints() if joints is None else joints
        return tool_messages(reg, j, self.source, self.config, time.monotonic())

    def _broadcast(self, outs: list[_Out]) -> None:
        for c in list(self._clients):
            for out in outs:
                c.offer(out)

    async def _tick(self) -> None:
        cfg = self.config
        assert self._wake is not None
        last_reg: object = object()
        last_tool: object = object()
        next_reg = next_tool = 0.0
        while True:
            now = time.monotonic()
            reg = self._registration()
            key = _registration_key(reg)
            if key != last_reg or now >= next_reg:
                outs = registration_messages(reg, cfg)
                if key != last_reg:  # the POINT list on a change only (module docstring)
                    outs += points_messages(reg, cfg)
                self._broadcast(outs)
                last_reg, next_reg = key, now + cfg.period_s
            joints = self._joints()
            # A new sample, a health change or a sample going stale all change the key.
            tool_key = (
                key,
                None
                if joints is None
                else (joints.t_s, joints.health, now - joints.t_s > cfg.joint_max_age_s),
            )
            if tool_key != last_tool or now >= next_tool:
                self._broadcast(self._tool(reg, joints))
                last_tool, next_tool = tool_key, now + cfg.period_s
            self._wake.clear()
            # wake at the poll period or on notify(); call_later instead of wait_for, which would
            # start a new task for every wait (100 per second)
            timer = asyncio.get_running_loop().call_later(cfg.poll_period_s, self._wake.set)
            try:
                await self._wake.wait()
            finally:
                timer.cancel()


def _registration_key(reg: RegistrationState) -> object:
    cur = reg.current
    return (
        None if cur is None else (cur.registration_id, cur.image_from_robot.tobytes(), cur.fre_mm),
        None if reg.last_refusal is None else (reg.last_refusal.registration_id, reg.last_refusal.reason),
        reg.no_current_reason,
    )
