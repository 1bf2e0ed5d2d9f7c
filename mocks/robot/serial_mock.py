"""A mock controller speaking the project's serial line protocol on a pty pair.

``os.openpty()`` gives a master / slave pair: the mock holds the master (the
controller's end of the cable) and keeps the slave open in raw mode so the
line settings survive; the link opens the slave *path*
(``serial:///dev/pts/N?baudrate=115200``).  ``$J`` lines go out at 50 Hz and
``$S`` lines every 5th cycle, like the simple_message mock, encoded with
:mod:`drivers.serial_link` (the link's own codec).

A serial cable has no connection to drop: :meth:`disconnect` means silence for
``down_s`` (the line is dead, then comes back).  Other faults:
:meth:`stall` / :meth:`resume`, :meth:`inject_raw` (garbage),
:meth:`inject_nan`, :meth:`inject_bad_checksum`, :meth:`set_split_frames`.
POSIX only.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import os
import time
import tty

from drivers.serial_link import encode_joint_line, encode_status_line
from mocks.robot.faults import QueuedFaults
from mocks.robot.robot import ScriptedRobot

log = logging.getLogger(__name__)

FRAME_PERIOD_S = 0.02
STATUS_EVERY = 5
MAX_PENDING_BYTES = 4096
"""Output queued beyond this (nobody reading) is dropped, as bytes on a cable nobody listens to."""
SPLIT_WRITE_PAUSE_S = 0.0005


class SerialMock:
    """Serve ``robot`` on a fresh pty; :attr:`url` names the slave side."""

    def __init__(
        self,
        robot: ScriptedRobot,
        *,
        period_s: float = FRAME_PERIOD_S,
        status_every: int = STATUS_EVERY,
        baudrate: int = 115200,
    ) -> None:
        self.robot = robot
        self.period_s = period_s
        self.status_every = status_every
        self.baudrate = baudrate
        self._master: int | None = None
        self._slave: int | None = None
        self.slave_path = ""
        self._task: asyncio.Task[None] | None = None
        self._stalled = False
        self._split = False
        self.faults = QueuedFaults()
        self._bad_checksum_frames = 0
        self._seq = 0
        self.joint_frames_sent = 0
        self.frames_dropped = 0
        self.bytes_from_clients = 0
        self.returned_t_s: float | None = None

    @property
    def url(self) -> str:
        return f"serial://{self.slave_path}?baudrate={self.baudrate}"

    async def start(self) -> None:
        master, slave = os.openpty()
        tty.setraw(slave)
        os.set_blocking(master, False)
        self._master, self._slave = master, slave
        self.slave_path = os.ttyname(slave)
        loop = asyncio.get_running_loop()
        loop.add_reader(master, self._on_readable)
        self._task = asyncio.create_task(self._stream())
        log.info("mock serial controller on %s", self.url)

    async def stop(self) -> None:
        if self._task is not None:
            self._task.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await self._task
            self._task = None
        if self._master is not None:
            asyncio.get_running_loop().remove_reader(self._master)
            os.close(self._master)
            self._master = None
        if self._slave is not None:
            os.close(self._slave)
            self._slave = None

    def _on_readable(self) -> None:
        assert self._master is not None
        try:
            data = os.read(self._master, 4096)
        except OSError:  # EIO while no one has the slave open
            return
        self.bytes_from_clients += len(data)

    # ---- faults ---------------------------------------------------------------

    def stall(self) -> None:
        self._stalled = True

    def resume(self) -> None:
        self._stalled = False

    async def disconnect(self, down_s: float) -> None:
        self._stalled = True
        await asyncio.sleep(down_s)
        self._stalled = False
        self.returned_t_s = time.monotonic()

    def inject_raw(self, data: bytes) -> None:
        self.faults.inject_raw(data)

    def inject_nan(self, n_frames: int = 1, joint: int = 0) -> None:
        self.faults.inject_nan(n_frames, joint)

    def inject_bad_checksum(self, n_frames: int = 1) -> None:
        self._bad_checksum_frames = n_frames

    def set_split_frames(self, enabled: bool) -> None:
        self._split = enabled

    # ---- streaming --------------------------------------------------------------

    async def _stream(self) -> None:
        loop = asyncio.get_running_loop()
        next_t = loop.time()
        cycle = 0
        while True:
            if not self._stalled:
                for raw in self.faults.take_raw():
                    await self._write(raw)
                q = self.faults.joints(self.robot.joints_rad_at())
                line = encode_joint_line(self._seq, q)
                if self._bad_checksum_frames > 0:
                    line = line[:-4] + (b"00" if line[-4:-2] != b"00" else b"FF") + b"\r\n"
                    self._bad_checksum_frames -= 1
                if await self._write(line):
                    self.joint_frames_sent += 1
                self._seq += 1
                if cycle % self.status_every == 0:
                    st = self.robot.controller_status
                    from drivers.serial_link import StatusLine

                    s = StatusLine(cycle // self.status_every, st.drives_powered, st.e_stopped,
                                   st.error_code, st.in_error, self.robot.reported_in_motion(), st.mode,
                                   st.motion_possible)  # fmt: skip
                    await self._write(encode_status_line(s.seq, s))
                cycle += 1
            next_t += self.period_s
            delay = next_t - loop.time()
            if delay < -self.period_s:
                next_t = loop.time()
                delay = 0.0
            await asyncio.sleep(max(0.0, delay))

    async def _write(self, data: bytes) -> bool:
        """Write all of ``data`` (or drop it if the pty buffer is full); True if written."""
        assert self._master is not None
        chunks = [data[i : i + 1] for i in range(len(data))] if self._split else [data]
        for i, chunk in enumerate(chunks):
            if self._split and i:
                await asyncio.sleep(SPLIT_WRITE_PAUSE_S)
            view = memoryview(chunk)
            deadline = time.monotonic() + self.period_s
            while view:
                try:
                    n = os.write(self._master, view)
                except BlockingIOError:
                    n = 0
                view = view[n:]
                if view:
                    if time.monotonic() > deadline:
                        self.frames_dropped += 1
                        return False
                    await asyncio.sleep(0.001)
        return True
