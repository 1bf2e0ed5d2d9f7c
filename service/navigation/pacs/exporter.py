"""The PACS archive queue's worker: each accepted registration's Spatial Registration object, by
C-STORE, retried with back-off across link failures and restarts.

* :meth:`PacsExporter.enqueue` (any thread; :meth:`PacsExporter.on_registration_done` calls it on
  each ``registration_done``) inserts a ``pending``
  row (:mod:`service.store.pacs_exports`) and wakes the worker.  At start the worker also queues
  accepted registrations newer than the newest queued one (the service stopped between accepting
  and queueing) and resumes every ``pending`` row, including one whose send was cut by a crash.
* One worker thread sends the due rows oldest first.  The object is built at send time from the
  stored record (:func:`service.navigation.sro_export.sro_dataset`, status ``accepted``: what the archive
  keeps is the accepted registration, not whether it is current; its UIDs are derived from the
  registration, so a re-send is the same instance and the PACS overwrites or ignores it).
* Outcomes (:mod:`service.navigation.pacs.scu`): ``sent`` → ``sent``; ``refused`` (a permanent status such
  as 0xA9xx or 0xCxxx) → ``failed`` with the PACS's status (no automatic retry:
  ``POST /registrations/{id}/pacs-export``); ``transient`` (0xA7xx out of resources, 0x0213)
  and ``unreachable`` → ``pending`` again after ``retry_initial_s · 2^(attempts-1)`` capped at
  ``retry_max_s``, until
  ``give_up_after_s`` after queueing → ``failed``.  A registration withdrawn before it was sent
  is not sent (``failed``, reason says so).  Every ``sent`` / ``failed`` is published
  (``pacs_export_sent`` / ``pacs_export_failed``) and written to the audit log.
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable
from dataclasses import replace
from datetime import datetime
from pathlib import Path

from registration.errors import OarmRegError
from service.events import PacsExportFailed, PacsExportSent, Publish, RegistrationDone
from service.navigation.pacs.scu import RETRIED, StoreOutcome, c_store, destination
from service.settings import PacsSettings
from service.store import Database
from service.store.pacs_exports import PacsExport

log = logging.getLogger(__name__)

PRINCIPAL = "service:pacs-export"
"""Audit principal of the worker's own entries."""
IDLE_WAKE_S = 60.0
"""Longest wait of the idle worker (it is woken at once by enqueue / retry / stop)."""


class PacsExporter:
    def __init__(
        self,
        db: Database,
        cfg: PacsSettings,
        data_dir: Path,
        publish: Publish,
        *,
        send: Callable[[bytes, PacsSettings], StoreOutcome] = c_store,
    ) -> None:
        self.db = db
        self.cfg = cfg
        self.data_dir = data_dir
        self.publish = publish
        self._send = send
        self._wake = threading.Event()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None

    @property
    def destination(self) -> str:
        return destination(self.cfg)

    def start(self) -> None:
        for rid in self.db.pacs_exports.missed():
            log.warning("PACS export: registration %d was accepted but never queued; queueing it now", rid)
            self.db.pacs_exports.enqueue(rid, self.destination, time.time())
        self._thread = threading.Thread(target=self._run, name="oarmreg-pacs-export", daemon=True)
        self._thread.start()

    def stop(self) -> None:
        """Stop after the attempt in progress (at most ``timeout_s``); its row stays ``pending``."""
        self._stop.set()
        self._wake.set()
        if self._thread is not None:
            self._thread.join()
            self._thread = None

    def enqueue(self, registration_id: int) -> None:
        if self.db.pacs_exports.enqueue(registration_id, self.destination, time.time()):
            log.info("PACS export: registration %d queued for %s", registration_id, self.destination)
        self._wake.set()

    def on_registration_done(self, event: RegistrationDone) -> None:
        """Bus listener (bound by :mod:`service.runtime.assembly`): queue the new registration's SRO."""
        try:
            self.enqueue(event.registration_id)
        except Exception:  # the registration stands; the worker's start-up sweep queues it later
            log.exception("PACS export: could not queue registration %d", event.registration_id)

    def retry(self, registration_id: int) -> None:
        """Queue again now (the row exists)."""
        self.db.pacs_exports.requeue(registration_id, self.destination, time.time())
        self._wake.set()

    # ---- worker ---------------------------------------------------------------------------

    def _run(self) -> None:
        while not self._stop.is_set():
            self._wake.clear()
            try:
                for row in self.db.pacs_exports.due(time.time()):
                    if self._stop.is_set():
                        return
                    self._attempt(row)
                nxt = self.db.pacs_exports.next_due_unix_s()
            except Exception:  # the database went away or a bug: log, keep the thread alive
                log.exception("PACS export: the queue could not be processed; trying again later")
                nxt = None
            wait_s = IDLE_WAKE_S if nxt is None else min(max(nxt - time.time(), 0.0), IDLE_WAKE_S)
            if wait_s > 0:
                self._wake.wait(wait_s)

    def _attempt(self, row: PacsExport) -> None:
        from service.navigation.sro_export import sro_dataset, to_bytes
        from service.registrations.robot_frame import robot_frame_uid

        rid = row.registration_id
        attempts = row.attempts + 1
        rec = self.db.registrations.get(rid)
        if rec is None or rec.status == "withdrawn" or rec.image_from_robot is None:
            why = "it was withdrawn before it was archived" if rec is not None else "it no longer exists"
            self._finish(row, attempts, "failed", None, f"registration {rid} not sent: {why}", "")
            return
        try:
            inst = self.db.scan_instances.get(rec.series_uid) if rec.series_uid else None
            accepted = (
                rec if rec.status == "accepted" else replace(rec, status="accepted")
            )  # retired: was accepted
            ds = sro_dataset(accepted, inst, robot_frame_uid=robot_frame_uid(self.data_dir), is_current=False)
            raw = to_bytes(ds)
        except (
            OarmRegError
        ) as e:  # e.g. its scan's instance UIDs not stored (yet): retried like a link failure
            self._again(row, attempts, str(e), "")
            return
        sop = str(ds.SOPInstanceUID)
        outcome = self._send(raw, self.cfg)
        if outcome.kind in RETRIED:
            self._again(row, attempts, outcome.reason, sop, outcome.dimse_status)
        else:
            state = "sent" if outcome.kind == "sent" else "failed"
            self._finish(row, attempts, state, outcome.dimse_status, outcome.reason, sop)

    def _again(
        self, row: PacsExport, attempts: int, reason: str, sop: str, status: int | None = None
    ) -> None:
        now = time.time()
        queued = datetime.fromisoformat(row.queued_at).timestamp()
        if now - queued > self.cfg.give_up_after_s:
            self._finish(
                row,
                attempts,
                "failed",
                status,
                f"gave up after {now - queued:.0f} s and {attempts} "
                f"attempts (pacs.give_up_after_s); last: {reason}",
                sop,
            )
            return
        delay = min(self.cfg.retry_initial_s * 2.0 ** (attempts - 1), self.cfg.retry_max_s)
        log.warning(
            "PACS export of registration %d: attempt %d failed (%s); next in %.1f s",
            row.registration_id,
            attempts,
            reason,
            delay,
        )
        self.db.pacs_exports.update(
            row.registration_id,
            state="pending",
            attempts=attempts,
            dimse_status=status,
            reason=reason,
            sop_instance_uid=sop,
            next_attempt_unix_s=now + delay,
        )

    def _finish(
        self, row: PacsExport, attempts: int, state: str, status: int | None, reason: str, sop: str
    ) -> None:
        rid = row.registration_id
        self.db.pacs_exports.update(
            rid,
            state="sent" if state == "sent" else "failed",
            attempts=attempts,
            dimse_status=status,
            reason=reason,
            sop_instance_uid=sop,
            next_attempt_unix_s=time.time(),
        )
        (log.info if state == "sent" else log.error)("PACS export of registration %d: %s", rid, reason)
        detail = f"{state} to {row.destination}" + (f", status 0x{status:04X}" if status is not None else "")
        try:
            self.db.audit.record(PRINCIPAL, "pacs_export", "registration", rid, state, f"{detail}: {reason}")
        except Exception:
            log.exception("PACS export: could not write the audit entry of registration %d", rid)
        kind = PacsExportSent if state == "sent" else PacsExportFailed
        self.publish(
            kind(registration_id=rid, destination=row.destination, dimse_status=status, reason=reason,
                 sop_instance_uid=sop, attempts=attempts)
        )  # fmt: skip
