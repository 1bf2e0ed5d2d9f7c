"""A mock controller publishing joints over Modbus TCP (a real pymodbus server).

It plays the part of a CS8C ``ModbusSrv-0`` with a VAL3 task copying
``herej()`` into ``aio`` words (research/staubli-link.md §2.1): one block of
registers at ``register_map.start_address`` holds J1…Jn encoded by
:func:`drivers.modbus.joints_to_registers` (the client's own codec, so the map
is exercised both ways).  The block is refreshed on every read from the
scripted robot; reading outside it gets a Modbus ILLEGAL_ADDRESS exception,
as from real hardware.

Faults: :meth:`stall` (requests go unanswered until :meth:`resume`),
:meth:`disconnect` (server down for ``down_s``, then back on the same port),
:meth:`inject_nan`, :meth:`inject_raw` (the next response is replaced by these
bytes).
"""

from __future__ import annotations

import asyncio
import logging
import math
import time
from typing import Any

from drivers.modbus import RegisterMap, joints_to_registers
from mocks.robot.faults import QueuedFaults
from mocks.robot.robot import ScriptedRobot

log = logging.getLogger(__name__)


class ModbusMockServer:
    """Serve ``robot`` on ``host:port`` (0: any free port) with ``register_map``."""

    def __init__(
        self,
        robot: ScriptedRobot,
        host: str = "127.0.0.1",
        port: int = 0,
        *,
        register_map: RegisterMap | None = None,
    ) -> None:
        self.robot = robot
        self.host = host
        self.port = port
        self.register_map = register_map or RegisterMap()
        self._server: Any = None
        self._resumed = asyncio.Event()
        self._resumed.set()
        self.faults = QueuedFaults()
        self.joint_frames_sent = 0
        self.bytes_from_clients = 0  # Modbus clients must send requests; counted for symmetry only
        self.write_requests = 0
        self.returned_t_s: float | None = None

    @property
    def url(self) -> str:
        rm = self.register_map
        return (
            f"modbus://{self.host}:{self.port}?unit={rm.unit_id}&fc={rm.function_code}"
            f"&address={rm.start_address}&type={rm.data_type}&word_order={rm.word_order}"
            f"&units={rm.units}&scale={rm.scale:g}&n_joints={rm.n_joints}&poll_hz={rm.poll_hz:g}"
        )

    async def start(self) -> None:
        from pymodbus.server import ModbusTcpServer
        from pymodbus.simulator import DataType, SimData, SimDevice

        rm = self.register_map
        device = SimDevice(
            id=rm.unit_id,
            simdata=[
                SimData(rm.start_address, count=rm.register_count, values=0, datatype=DataType.REGISTERS)
            ],
            action=self._action,
        )
        self._server = ModbusTcpServer(device, address=(self.host, self.port), trace_packet=self._trace)
        await self._server.serve_forever(background=True)
        self.port = self._server.transport.sockets[0].getsockname()[1]
        log.info("mock Modbus controller on %s", self.url)

    async def stop(self) -> None:
        if self._server is not None:
            await self._server.shutdown()
            self._server = None

    async def _action(
        self, function_code: int, start_address: int, address: int, count: int,
        registers: list[int], set_values: Any,
    ) -> Any:  # fmt: skip
        if set_values is not None:
            self.write_requests += 1
            return None
        await self._resumed.wait()
        q = self.faults.joints(self.robot.joints_rad_at())
        rm = self.register_map
        if rm.data_type == "float32" or all(math.isfinite(v) for v in q):
            regs = joints_to_registers(q, rm)
        else:  # integers cannot carry NaN: send an all-ones pattern instead
            regs = [0xFFFF] * rm.register_count
        off = rm.start_address - start_address
        registers[off : off + len(regs)] = regs
        self.joint_frames_sent += 1
        return None

    def _trace(self, sending: bool, data: bytes) -> bytes:
        if not sending:
            self.bytes_from_clients += len(data)
            return data
        raw = self.faults.next_raw()
        return data if raw is None else raw

    # ---- faults ---------------------------------------------------------------

    def stall(self) -> None:
        self._resumed.clear()

    def resume(self) -> None:
        self._resumed.set()

    def inject_nan(self, n_frames: int = 1, joint: int = 0) -> None:
        self.faults.inject_nan(n_frames, joint)

    def inject_raw(self, data: bytes) -> None:
        self.faults.inject_raw(data)

    async def disconnect(self, down_s: float) -> None:
        port = self.port
        await self.stop()
        await asyncio.sleep(down_s)
        self.port = port
        await self.start()
        self.returned_t_s = time.monotonic()
