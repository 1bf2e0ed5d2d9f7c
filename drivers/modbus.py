"""Joint angles over Modbus TCP (pymodbus), with a fully configurable register map.

No public document fixes how a CS8/CS9 maps VAL3 ``aio`` words to Modbus
registers: not the function code, the base address, the float word order, nor
the units (research/staubli-link.md §2.1).  So everything is configuration
(:class:`RegisterMap`), from the URL query or from keyword options::

    modbus://192.168.0.254:502?unit=1&fc=3&address=100&type=float32&word_order=big&units=deg&poll_hz=50

=================  ==========================================================
``unit``           Modbus unit / device id (default 1)
``fc``             3 = read holding registers, 4 = read input registers
``address``        register address of J1 (0-based, as on the wire)
``type``           ``float32`` (2 registers / joint), ``int32`` (2), ``int16`` (1)
``word_order``     ``big`` (first register = high word) or ``little``
``units``          ``deg`` or ``rad``: what the controller writes
``scale``          value in ``units`` = raw register value × ``scale``
                   (e.g. int16 hundredths of a degree: ``type=int16&scale=0.01``)
``n_joints``       joints in the block (default 6)
``poll_hz``        poll rate (default 50, the simple_message rate)
``timeout_s``      per-request timeout (default 0.5 s)
=================  ==========================================================

The joints must be consecutive registers (one read per poll).  The encode
function :func:`joints_to_registers` is shared with the mock server.  The link
only *reads*: it sends read requests (FC 3 or 4) and never a write function code.
"""

from __future__ import annotations

import asyncio
import logging
import math
import time
from collections.abc import Sequence
from dataclasses import dataclass, fields, replace
from typing import Any
from urllib.parse import urlsplit

from drivers.base import BaseLink, base_options, float32_half_spacing, parse_query
from drivers.errors import LinkConfigError, ProtocolError

log = logging.getLogger(__name__)

DEFAULT_PORT = 502
"""Modbus TCP; also the CS8C ``modbus.xml`` default ``TCP_Port="502"``."""

DATA_TYPES = {"float32": 2, "int32": 2, "int16": 1}
"""Register data type → registers per joint."""

_ALIASES = {
    "unit": "unit_id", "device_id": "unit_id", "fc": "function_code", "address": "start_address",
    "type": "data_type",
}  # fmt: skip


@dataclass(frozen=True)
class RegisterMap:
    """Where and how the controller publishes J1…Jn (see the module table)."""

    unit_id: int = 1
    function_code: int = 3
    start_address: int = 0
    data_type: str = "float32"
    word_order: str = "big"
    units: str = "deg"  # VAL3 herej() is in degrees; a program copying it unchanged writes degrees
    scale: float = 1.0
    n_joints: int = 6
    poll_hz: float = 50.0
    timeout_s: float = 0.5

    def __post_init__(self) -> None:
        problems = []
        if not 0 <= self.unit_id <= 255:
            problems.append(f"unit id {self.unit_id} not in 0..255")
        if self.function_code not in (3, 4):
            problems.append(f"function code {self.function_code} (use 3 = holding or 4 = input registers)")
        if not 0 <= self.start_address <= 0xFFFF:
            problems.append(f"start address {self.start_address} not in 0..65535")
        if self.data_type not in DATA_TYPES:
            problems.append(f"data type {self.data_type!r} (use one of {sorted(DATA_TYPES)})")
        if self.word_order not in ("big", "little"):
            problems.append(f"word order {self.word_order!r} (use big or little)")
        if self.units not in ("deg", "rad"):
            problems.append(f"units {self.units!r} (use deg or rad)")
        if not (math.isfinite(self.scale) and self.scale != 0):
            problems.append(f"scale {self.scale} (must be finite and non-zero)")
        if not 1 <= self.n_joints <= 10:
            problems.append(f"n_joints {self.n_joints} not in 1..10")
        if not 0 < self.poll_hz <= 1000:
            problems.append(f"poll_hz {self.poll_hz} not in (0, 1000]")
        if not self.timeout_s > 0:
            problems.append(f"timeout_s {self.timeout_s} must be > 0")
        if self.data_type in DATA_TYPES and self.start_address + self.register_count > 0x10000:
            problems.append("the joint block runs past register 65535")
        if problems:
            raise LinkConfigError("invalid Modbus register map: " + "; ".join(problems))

    @property
    def registers_per_joint(self) -> int:
        return DATA_TYPES[self.data_type]

    @property
    def register_count(self) -> int:
        return self.registers_per_joint * self.n_joints

    @classmethod
    def from_options(cls, opts: dict[str, Any], base: RegisterMap | None = None) -> RegisterMap:
        """Build from URL-query style options (strings allowed, aliases ``unit``, ``fc``, ``address``,
        ``type``); keys that are not register-map fields are left in ``opts``."""
        types = {f.name: f.type for f in fields(cls)}
        changes: dict[str, Any] = {}
        for key in list(opts):
            name = _ALIASES.get(key, key)
            if name not in types:
                continue
            raw = opts.pop(key)
            conv = {"int": int, "float": float, "str": str}[str(types[name])]
            try:
                changes[name] = conv(raw)
            except (TypeError, ValueError):
                raise LinkConfigError(f"Modbus option {key}={raw!r} is not a valid {conv.__name__}") from None
        return replace(base or cls(), **changes)


def _datatype(rmap: RegisterMap) -> Any:
    from pymodbus.client import AsyncModbusTcpClient

    dt = AsyncModbusTcpClient.DATATYPE
    return {"float32": dt.FLOAT32, "int32": dt.INT32, "int16": dt.INT16}[rmap.data_type]


def joints_to_registers(joints_rad: Any, rmap: RegisterMap) -> list[int]:
    """Encode joint angles (rad) as the controller would write them (used by the mock).

    Raises ``ValueError`` if a scaled integer does not fit the register type.
    """
    from pymodbus.client import AsyncModbusTcpClient

    out: list[int] = []
    dtype = _datatype(rmap)
    for q in joints_rad:
        v = math.degrees(q) if rmap.units == "deg" else float(q)
        raw: float | int = v / rmap.scale
        if rmap.data_type != "float32":
            if not math.isfinite(raw):
                raise ValueError(f"cannot encode {q} as {rmap.data_type}")
            raw = round(raw)
            bits = 16 if rmap.data_type == "int16" else 32
            if not -(2 ** (bits - 1)) <= raw < 2 ** (bits - 1):
                raise ValueError(f"{v} {rmap.units} / scale {rmap.scale} does not fit {rmap.data_type}")
        out += AsyncModbusTcpClient.convert_to_registers(raw, dtype, word_order=rmap.word_order)  # type: ignore[arg-type]
    return out


def registers_to_joints(registers: list[int], rmap: RegisterMap) -> list[float]:
    """Decode a block of ``rmap.register_count`` registers to joint angles in radians."""
    from pymodbus.client import AsyncModbusTcpClient

    if len(registers) != rmap.register_count:
        raise ProtocolError(f"expected {rmap.register_count} registers, got {len(registers)}")
    dtype = _datatype(rmap)
    k = rmap.registers_per_joint
    out = []
    for i in range(rmap.n_joints):
        raw = AsyncModbusTcpClient.convert_from_registers(
            registers[i * k : (i + 1) * k],
            dtype,
            word_order=rmap.word_order,  # type: ignore[arg-type]
        )
        v = float(raw) * rmap.scale  # type: ignore[arg-type]
        out.append(math.radians(v) if rmap.units == "deg" else v)
    return out


def register_rounding_rad(value_rad: float, rmap: RegisterMap) -> float:
    """The most the register type moves a joint of ``value_rad`` (rad): half a float32 spacing of the
    register value, or half an integer step (× ``scale``), converted from ``rmap.units``."""
    v = math.degrees(value_rad) if rmap.units == "deg" else value_rad
    raw = v / rmap.scale
    step = float32_half_spacing(raw) if rmap.data_type == "float32" else 0.5
    half = step * abs(rmap.scale)
    return math.radians(half) if rmap.units == "deg" else half


class ModbusLink(BaseLink):
    """Polling Modbus TCP client (``modbus://HOST[:502]?…``).

    Parameters
    ----------
    register_map : RegisterMap, optional
        Base map; URL query options override its fields.
    """

    scheme = "modbus"
    streamed = False  # polled: a sample exists only when the poller ran (stillness judges receive gaps)

    def __init__(self, url: str, *, register_map: RegisterMap | None = None, **options: Any) -> None:
        parts = urlsplit(url)
        if parts.scheme != self.scheme or not parts.hostname:
            raise LinkConfigError(f"expected modbus://HOST[:PORT]?..., got {url!r}")
        try:
            self.port = parts.port or DEFAULT_PORT
        except ValueError as e:
            raise LinkConfigError(f"{url}: bad port ({e})") from None
        self.host = parts.hostname
        opts: dict[str, Any] = {**parse_query(url), **options}
        self.register_map = RegisterMap.from_options(opts, register_map)
        rm = self.register_map
        opts.setdefault("frame_period_s", 1.0 / rm.poll_hz)
        opts.setdefault("stale_after_s", 3.0 / rm.poll_hz)
        opts.setdefault("n_joints", rm.n_joints)
        super().__init__(url, **base_options(opts, url))
        self._client: Any = None

    def joint_resolution_rad(self, joints_rad: Sequence[float]) -> tuple[float, ...]:
        """As the register map encodes them (:func:`register_rounding_rad`): int16 hundredths of a degree
        round by 0.005° (8.7e-5 rad), float32 degrees by half a float32 spacing."""
        return tuple(register_rounding_rad(q, self.register_map) for q in joints_rad)

    async def _session(self) -> None:
        from pymodbus.client import AsyncModbusTcpClient
        from pymodbus.exceptions import ModbusException

        rm = self.register_map
        # retries=0, reconnect_delay=0: pymodbus's own retry and reconnect are off, so the
        # back-off in BaseLink is the only reconnect policy.
        client = AsyncModbusTcpClient(
            self.host, port=self.port, timeout=rm.timeout_s, retries=0, reconnect_delay=0
        )
        self._client = client
        if not await client.connect():
            raise ConnectionRefusedError(f"cannot open Modbus TCP connection to {self.host}:{self.port}")
        self._mark_up()
        read = client.read_holding_registers if rm.function_code == 3 else client.read_input_registers
        period = 1.0 / rm.poll_hz
        loop = asyncio.get_running_loop()
        next_t = loop.time()
        started = time.monotonic()
        while not self._closing.is_set():
            try:
                rr = await read(rm.start_address, count=rm.register_count, device_id=rm.unit_id)
            except ModbusException as e:
                raise ConnectionError(f"Modbus request failed: {e}") from None
            t_s = time.monotonic()
            if rr.isError():
                raise ProtocolError(
                    f"{self.url}: the controller answered FC{rm.function_code} for {rm.register_count} "
                    f"registers at {rm.start_address} (unit {rm.unit_id}) with a Modbus exception ({rr}); "
                    "check the register map against the controller's modbus.xml"
                )
            self._publish_joints(registers_to_joints(list(rr.registers), rm), t_s)
            if self._silence_exceeded(started):
                raise TimeoutError(f"no valid joint read for more than {self.silence_reconnect_s:g} s")
            next_t += period
            delay = next_t - loop.time()
            if delay < -period:
                next_t = loop.time()
                delay = 0.0
            await asyncio.sleep(max(0.0, delay))

    async def _cleanup(self) -> None:
        c, self._client = self._client, None
        if c is not None:
            c.close()
