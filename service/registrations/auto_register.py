"""Auto-register (``service.registrations.auto_register = true``): each scan recorded complete is registered.

It listens to :class:`~service.events.ScanArrived` (bound by :mod:`service.runtime.assembly`) and runs
:meth:`service.registrations.orchestrator.Orchestrator.register` on its own worker thread, one scan after the
other; the orchestrator stores and publishes the result (``registration_done`` /
``registration_refused``), which the IGTL publisher and the PACS export pick up like any other.
"""

from __future__ import annotations

import asyncio
import logging
from concurrent.futures import ThreadPoolExecutor
from typing import TYPE_CHECKING

from service.events import ScanArrived
from service.records import RegistrationRefusal
from service.workers import started_executor

if TYPE_CHECKING:
    from service.registrations.orchestrator import Orchestrator

log = logging.getLogger(__name__)


class AutoRegister:
    """Registers each scan recorded complete, on one worker thread (see the module docstring)."""

    def __init__(self, orchestrator: Orchestrator) -> None:
        self.orchestrator = orchestrator
        self._registrar: ThreadPoolExecutor | None = None

    async def start(self) -> None:
        self._registrar = started_executor(1, "oarmreg-autoreg")

    async def stop(self) -> None:
        """Drop the scans still queued; wait for the registration in progress."""
        if self._registrar is not None:
            await asyncio.to_thread(self._registrar.shutdown, True, cancel_futures=True)

    def on_scan_arrived(self, event: ScanArrived) -> None:
        """Queue the scan (the publishing thread returns at once)."""
        if self._registrar is not None:
            self._registrar.submit(self._register, event.scan_id)

    def _register(self, scan_id: int) -> None:
        try:
            rec = self.orchestrator.register(scan_id)
        except Exception as e:  # nothing to register (the scan went away meanwhile)
            log.warning("auto-register: scan %d not registered: %s", scan_id, e)
            return
        if isinstance(rec, RegistrationRefusal):  # stored and published by the orchestrator
            log.warning("auto-register: scan %d refused (registration %s): %s", scan_id,
                        rec.registration_id, rec.error)  # fmt: skip
        else:
            log.info(
                "auto-register: scan %d → registration %d (FRE %.3f mm)", scan_id, rec.id, rec.fre_mm or 0
            )
