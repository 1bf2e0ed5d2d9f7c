"""A small asyncio OpenIGTLink server: the registration and the live tool pose, to any
number of clients (3D Slicer OpenIGTLinkIF, PLUS-style consumers).

Devices (PLUS / SlicerIGT naming ``<From>To<To>``, research §3.2; one TRANSFORM each):

``RobotToImage``
    ``ras_from_robot = RAS_FROM_LPS @ image_from_robot``: maps a point in the robot base
    frame (mm) to the scan's patient coordinates **in RAS** (mm), which is what Slicer's
    scene uses; ``image_from_robot`` itself is DICOM LPS (design §3) and the TRANSFORM
    message carries no coordinate field, so the flip ``diag(-1, -1, 1, 1)`` is applied here
    on the image side only (the robot frame is not a patient frame and is not flipped).
``ToolToImage``
    ``RAS_FROM_LPS @ image_from_robot @ robot_from_tool0(q) @ tool0_from_tcp``: the TCP pose
    in image RAS from the latest joints, sent whenever a new joint sample arrives (the link
    rate), on connect, and at least every ``period_s``.

Header version, per client: every client is sent header version 1 (bare content, no
metadata: what the reference library reads by default, OpenIGTLink ticket 200) until it has sent
a well-formed message with header version 2 (SlicerOpenIGTLink sends a dummy version-2 STATUS at
connect for exactly this, PR #65); from then on it gets version 2 with the metadata below, the
PLUS rule (answer in the highest version received from that client).  A client that never writes
keeps version 1.  Client messages are read in either version; a client whose version-2 extended
header or metadata is malformed, or who sends a header version other than 1 or 2, is closed (the
others are not affected); a message with a bad CRC is ignored (logged, counted, no switch).

Version 2 carries the metadata ``TransformStatus`` (``OK`` / ``INVALID``; the matrix
of an INVALID transform is the identity and must not be used), ``RegistrationId``,
``FRE_mm``, ``TRE_pred_mm``, ``ImageFrame=RAS``, ``SourceFrame`` and, when the newest
registration was refused while an older one stays current, ``LastRefusal``; INVALID ones
give ``Reason``.

Pushes: on every change of the registration (id or refusal), to every client on connect,
and periodically (``period_s``, 1 Hz by default).  Each client has a bounded queue: when it
is full the oldest message is dropped; a client whose socket stays blocked for longer than
``slow_client_timeout_s`` is disconnected.  Nothing here ever blocks the caller or the
other clients.  OpenIGTLink has no authentication: binding anything but loopback requires
an explicit ``allowed_peer_addresses`` list, and peers not on the list are closed at once.
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

import numpy as np
import numpy.typing as npt

from registration.errors import ConfigError
from service.igtl import wire
from service.netaddr import Network, in_networks, is_loopback, parse_networks

log = logging.getLogger(__name__)

F64 = npt.NDArray[np.float64]

RAS_FROM_LPS: F64 = np.diag([-1.0, -1.0, 1.0, 1.0])
"""DICOM patient LPS → Slicer RAS (its own inverse)."""

DEFAULT_PORT = 18944
"""The OpenIGTLink / PLUS convention (research §3.3)."""


class IgtlConfigError(ConfigError):
    """The OpenIGTLink server configuration is unsafe or invalid."""

    title = "Invalid OpenIGTLink server configuration"


# --------------------------------------------------------------------------- state source


@dataclass(frozen=True)
class RegistrationView:
    """The current registration as the server needs it.

    ``image_from_robot`` : (4, 4) float64, robot mm → image (DICOM LPS) mm.
    """

    image_from_robot: F64
    registration_id: str
    fre_mm: float
    tre_pred_mm: float | None = None
    sro_sop_instance_uid: str | None = None
    chain_error_mm: float | None = None
    """The registration's ``predicted_chain_error_mm`` (metadata ``ChainError_pred_mm``)."""


@dataclass(frozen=True)
class Refusal:
    """The newest refused registration (the previous current one stays current)."""

    registration_id: str
    reason: str


@dataclass(frozen=True)
class RegistrationState:
    current: RegistrationView | None
    last_refusal: Refusal | None = None


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


@dataclass(frozen=True)
class IgtlServerConfig:
    host: str = "127.0.0.1"
    port: int = DEFAULT_PORT
    allowed_peer_addresses: tuple[str, ...] = ()
    """IP addresses or networks (CIDR) allowed to connect; required off loopback."""
    period_s: float = 1.0
    """Periodic re-send of both devices (research §3.3: late joiners get nothing otherwise)."""
    poll_period_s: float = 0.01
    """How often new joint samples are looked for: 100 Hz, twice the 50 Hz VAL3 rate."""
    joint_max_age_s: float = 0.25
    """A joint sample older than this makes ToolToImage INVALID even if the link says OK."""
    client_queue_max: int = 64
    client_buffer_bytes: int = 64 * 1024
    """Transport write-buffer high-water mark per client."""
    socket_send_buffer_bytes: int = 64 * 1024
    """SO_SNDBUF of each accepted socket: bounds what a stalled client can pile up in the
    kernel (and so how fast it is detected) instead of Linux's autotuning up to 4 MiB."""
    slow_client_timeout_s: float = 2.0
    """A client whose socket accepts nothing for this long is disconnected."""
    registration_device: str = "RobotToImage"
    tool_device: str = "ToolToImage"

    def __post_init__(self) -> None:
        for name in ("period_s", "poll_period_s", "joint_max_age_s", "slow_client_timeout_s"):
            v = getattr(self, name)
            if not (math.isfinite(v) and v > 0):
                raise IgtlConfigError(f"igtl.{name} must be > 0 s, got {v}")
        if self.client_queue_max < 1 or min(self.client_buffer_bytes, self.socket_send_buffer_bytes) < 1024:
            raise IgtlConfigError(
                "igtl.client_queue_max must be >= 1, client_buffer_bytes and socket_send_buffer_bytes >= 1024"
            )
        for dev in (self.registration_device, self.tool_device):
            if not dev.isascii() or not 0 < len(dev) <= wire.DEVICE_NAME_SIZE:
                raise IgtlConfigError(f"device name {dev!r} must be 1–20 ASCII bytes")
        self.allowed_networks()  # validates the entries
        if not is_loopback(self.host) and not self.allowed_peer_addresses:
            raise IgtlConfigError(
                f"refusing to serve OpenIGTLink on {self.host!r} without an allow-list: the protocol "
                "has no authentication; set igtl.allowed_peer_addresses (e.g. ['10.0.0.12']) "
                "or bind 127.0.0.1"
            )

    def allowed_networks(self) -> tuple[Network, ...]:
        try:
            return parse_networks(self.allowed_peer_addresses, "igtl.allowed_peer_addresses")
        except ValueError as e:
            raise IgtlConfigError(str(e)) from None


# --------------------------------------------------------------------------- messages


@dataclass(frozen=True)
class _Out:
    """A message to send, packed per client (each client numbers its own MSG_IDs)."""

    device: str
    matrix: F64
    metadata: dict[str, str]
    timestamp_s: float


def _fmt(v: float) -> str:
    return f"{v:.6g}"


def registration_message(state: RegistrationState, device: str) -> _Out:
    """The ``RobotToImage`` message for ``state`` (see the module docstring)."""
    meta: dict[str, str] = {"ImageFrame": "RAS", "SourceFrame": "robot"}
    cur = state.current
    if state.last_refusal is not None:
        meta["LastRefusal"] = f"{state.last_refusal.registration_id}: {state.last_refusal.reason}"[:500]
    if cur is None:
        meta["TransformStatus"] = "INVALID"
        meta["Reason"] = "no current registration"
        return _Out(device, np.eye(4), meta, time.time())
    meta["TransformStatus"] = "OK"
    meta["RegistrationId"] = cur.registration_id
    meta["FRE_mm"] = _fmt(cur.fre_mm)
    if cur.tre_pred_mm is not None:
        meta["TRE_pred_mm"] = _fmt(cur.tre_pred_mm)
    if cur.sro_sop_instance_uid:
        meta["SroSopInstanceUid"] = cur.sro_sop_instance_uid
    if cur.chain_error_mm is not None:
        meta["ChainError_pred_mm"] = _fmt(cur.chain_error_mm)
    return _Out(device, RAS_FROM_LPS @ cur.image_from_robot, meta, time.time())


def tool_message(
    state: RegistrationState,
    joints: JointView | None,
    source: IgtlStateSource,
    cfg: IgtlServerConfig,
    now_t_s: float,
) -> _Out:
    """The ``ToolToImage`` message (INVALID without registration, or with a down/stale link)."""
    meta: dict[str, str] = {"ImageFrame": "RAS", "SourceFrame": "tcp"}
    reason = ""
    if state.current is None:
        reason = "no current registration"
    elif joints is None:
        reason = "no joint sample received"
    elif joints.health != "connected":
        reason = f"robot link {joints.health}: {joints.reason}"
    elif now_t_s - joints.t_s > cfg.joint_max_age_s:
        reason = f"joint sample is {now_t_s - joints.t_s:.3f} s old (> {cfg.joint_max_age_s:g} s)"
    if state.current is not None:
        meta["RegistrationId"] = state.current.registration_id
    if not reason:
        assert joints is not None and state.current is not None
        try:
            robot_from_tcp = source.robot_from_tool0(joints.joints_rad) @ source.tool0_from_tcp
        except Exception as e:  # KinematicsError or a bug in the callback: say INVALID, keep serving
            reason = f"forward kinematics failed: {e}"
        else:
            meta["TransformStatus"] = "OK"
            m = RAS_FROM_LPS @ state.current.image_from_robot @ robot_from_tcp
            return _Out(cfg.tool_device, m, meta, time.time())
    meta["TransformStatus"] = "INVALID"
    meta["Reason"] = reason[:500]
    return _Out(cfg.tool_device, np.eye(4), meta, time.time())


# --------------------------------------------------------------------------- clients


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
        self.queue: asyncio.Queue[_Out | None] = asyncio.Queue(maxsize=server.config.client_queue_max)
        self.seq = 0
        self.dropped = 0
        self.header_version = 1
        """1 until this client has sent a well-formed version-2 message (module docstring)."""
        self.tasks: list[asyncio.Task[None]] = []

    def offer(self, out: _Out) -> None:
        """Enqueue without blocking; drop the oldest message when full."""
        if self.queue.full():
            with contextlib.suppress(asyncio.QueueEmpty):
                self.queue.get_nowait()
                self.dropped += 1
                self.server.counters["dropped"] += 1
        self.queue.put_nowait(out)

    async def write_loop(self) -> None:
        timeout = self.server.config.slow_client_timeout_s
        try:
            while (out := await self.queue.get()) is not None:
                self.seq += 1
                v2 = self.header_version >= 2
                raw = wire.pack_transform(
                    out.matrix, out.device, timestamp_s=out.timestamp_s,
                    metadata=out.metadata if v2 else None, message_id=self.seq if v2 else 0,
                    header_version=2 if v2 else 1,
                )  # fmt: skip
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

    async def read_loop(self) -> None:
        """Read what the client sends (header version 1 or 2), switch it to version 2 after its
        first well-formed version-2 message, answer GET_TRANSFORM; end on EOF or a bad header."""
        try:
            while True:
                head = wire.unpack_header(await self.reader.readexactly(wire.HEADER_SIZE))
                if head.version not in (1, 2):
                    raise wire.IgtlWireError(f"header version {head.version} (this server reads 1 and 2)")
                body = await self.reader.readexactly(head.body_size)
                try:
                    wire.unpack_body(head, body)
                except wire.IgtlCrcError as e:
                    self.server.counters["bad_crc"] += 1
                    log.warning("OpenIGTLink client %s: %s; message ignored", self.peer, e)
                    continue
                if head.version == 2 and self.header_version < 2:
                    self.header_version = 2
                    log.info("OpenIGTLink client %s sent header version 2; answering in version 2", self.peer)
                    self.server._report("header_version", self)
                if head.type.startswith("GET_TRANSFOR"):
                    self.server.push_current(self)
        except (asyncio.IncompleteReadError, ConnectionError, OSError):
            pass
        except wire.IgtlWireError as e:
            self.server.counters["bad_headers"] += 1
            log.warning("OpenIGTLink client %s sent a bad header (%s); closing", self.peer, e)

    def info(self) -> dict[str, object]:
        """For ``/status``: who, which header version, how much was sent / dropped."""
        return {"peer": self.peer, "header_version": self.header_version, "sent": self.seq,
                "dropped": self.dropped}  # fmt: skip


# --------------------------------------------------------------------------- server


class IgtlServer:
    """Serve ``RobotToImage`` and ``ToolToImage`` (see the module docstring).

    Construct, then ``await start()`` on the event loop that should own it; ``await stop()``.
    :meth:`notify` (thread-safe) asks for an immediate push after a registration change; the
    server also notices changes by itself at ``poll_period_s``.
    """

    def __init__(
        self,
        config: IgtlServerConfig,
        source: IgtlStateSource,
        *,
        on_client: Callable[[str, str, int, int], None] | None = None,
    ) -> None:
        self.config = config
        self.source = source
        self.on_client = on_client
        """``on_client(event, peer, n_clients, header_version)`` on the loop; event ``connected`` /
        ``header_version`` (the client switched to version 2) / ``disconnected``."""
        self._networks = config.allowed_networks()
        self._server: asyncio.Server | None = None
        self._loop: asyncio.AbstractEventLoop | None = None
        self._clients: set[_Client] = set()
        self._handlers: set[asyncio.Task[object]] = set()
        self._wake: asyncio.Event | None = None
        self._tick_task: asyncio.Task[None] | None = None
        self.counters: dict[str, int] = {
            "connects": 0, "refused_peers": 0, "sent": 0, "dropped": 0, "slow_disconnects": 0,
            "bad_headers": 0, "bad_crc": 0,
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
        """Each connected client's peer address and header version (``/status``)."""
        return sorted((c.info() for c in self._clients), key=lambda d: str(d["peer"]))

    async def start(self) -> None:
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

    def push_current(self, client: _Client | None = None) -> None:
        """Send both devices' current state to one client (or all)."""
        reg = self._registration()
        outs = [registration_message(reg, self.config.registration_device), self._tool(reg)]
        for c in [client] if client is not None else list(self._clients):
            for out in outs:
                c.offer(out)

    # ---- internals ------------------------------------------------------------

    def _peer_allowed(self, host: str) -> bool:
        if not self._networks:
            return is_loopback(host)
        return in_networks(host, self._networks)

    async def _on_connect(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        peer = writer.get_extra_info("peername")
        host = str(peer[0]) if isinstance(peer, tuple) else ""
        if not self._peer_allowed(host):
            self.counters["refused_peers"] += 1
            log.warning("OpenIGTLink: peer %s is not in allowed_peer_addresses; closed", host)
            writer.transport.abort()
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
        self.push_current(client)
        client.tasks = [asyncio.create_task(client.write_loop()), asyncio.create_task(client.read_loop())]
        try:
            await asyncio.wait(client.tasks, return_when=asyncio.FIRST_COMPLETED)
        finally:
            for t in client.tasks:
                t.cancel()
            await asyncio.gather(*client.tasks, return_exceptions=True)
            writer.transport.abort()
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
            return RegistrationState(None)

    def _joints(self) -> JointView | None:
        try:
            return self.source.joints()
        except Exception:
            log.exception("OpenIGTLink: the joints callback failed; ToolToImage INVALID")
            return None

    def _tool(self, reg: RegistrationState, joints: JointView | None = None) -> _Out:
        j = self._joints() if joints is None else joints
        return tool_message(reg, j, self.source, self.config, time.monotonic())

    def _broadcast(self, out: _Out) -> None:
        for c in list(self._clients):
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
                self._broadcast(registration_message(reg, cfg.registration_device))
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
    )
