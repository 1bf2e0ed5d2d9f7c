"""The watcher's intake: a series arrived → snapshot the joints, record the scan, cache its volume,
publish the event."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import replace
from typing import Any, Protocol

import numpy as np

from service.records import JointSnapshot, NewScan, ScanGeometry, matrix4
from service.store import Database
from service.volume_cache import VolumeCache
from service.watcher import SeriesArrival


class SnapshotSource(Protocol):
    """What the intake needs of :class:`service.capture.Capture`."""

    def snapshot(
        self, first_seen_t_s: float, last_change_t_s: float, *, preexisting: bool = False
    ) -> dict[str, Any]: ...


def new_scan(arrival: SeriesArrival, snapshot: JointSnapshot) -> NewScan:
    """The scan record of a (non-duplicate) arrival: status, joint snapshot, slice counts and geometry."""
    base = NewScan(
        series_uid=arrival.series_uid,
        folder=str(arrival.folder),
        status="invalid" if arrival.error else "complete",
        reason=arrival.error,
        n_files=arrival.n_files,
        snapshot=snapshot,
        arrived_at=arrival.first_seen_at.isoformat(),
    )
    vol = arrival.volume
    if vol is None:
        return base
    n_slices, rows, columns = (int(v) for v in vol.shape)
    return replace(
        base,
        frame_of_reference_uid=str(vol.frame_of_reference_uid or ""),
        n_slices=n_slices,
        rows=rows,
        columns=columns,
        geometry=ScanGeometry(
            image_from_voxel=matrix4(np.asarray(vol.image_from_voxel, dtype=float).tolist()),
            spacing_mm=tuple(float(v) for v in vol.spacing_mm),
            shape_kji=(n_slices, rows, columns),
        ),
    )


class Intake:
    """``SeriesWatcher``'s ``on_series`` callback (runs on the watcher thread)."""

    def __init__(
        self,
        db: Database,
        capture: SnapshotSource,
        volumes: VolumeCache,
        publish: Callable[[str, dict[str, Any]], None],
        withdraw: Callable[[int, str], object] | None = None,
    ) -> None:
        self.db = db
        self.capture = capture
        self.volumes = volumes
        self.publish = publish
        self.withdraw = withdraw
        """``withdraw(scan_id, reason)``: :meth:`service.orchestrator.Orchestrator.withdraw_scan`."""

    def __call__(self, arrival: SeriesArrival) -> None:
        uid = arrival.series_uid
        if arrival.duplicate:
            self.db.scans.upsert(NewScan(series_uid=uid, folder=str(arrival.folder), status="complete"))
            return
        snap = JointSnapshot.from_capture(
            self.capture.snapshot(
                arrival.first_seen_t_s, arrival.last_change_t_s, preexisting=arrival.preexisting
            )
        )
        scan = new_scan(arrival, snap)
        if arrival.reopened:
            self._reopen(arrival, scan)
            return
        scan_id, created = self.db.scans.upsert(scan)
        if not created:
            return
        if arrival.volume is not None:
            self.volumes.put(uid, arrival.volume)
        data: dict[str, Any] = {
            "scan_id": scan_id,
            "series_uid": uid,
            "folder": str(arrival.folder),
            "still": snap.still,
            "link_state": snap.link_state,
        }
        if arrival.error:
            self.publish("scan_invalid", {**data, "reason": arrival.error})
        else:
            self.publish("scan_arrived", {**data, "n_slices": scan.n_slices})

    def _reopen(self, arrival: SeriesArrival, scan: NewScan) -> None:
        """Late slices of a recorded series: replace its record and volume, withdraw what was made of it."""
        uid = arrival.series_uid
        self.volumes.discard(uid)
        scan_id, before = self.db.scans.reopen(scan)
        if arrival.volume is not None:
            self.volumes.put(uid, arrival.volume)
        now = f"{scan.n_slices} slices" if not arrival.error else f"now invalid: {arrival.error}"
        reason = (
            f"scan {scan_id} (series {uid}) was recorded with {before} slices, then more slices arrived in "
            f"{arrival.folder} ({now}): the earlier record was incomplete. Register the completed scan again."
        )
        self.publish(
            "scan_reopened",
            {
                "scan_id": scan_id,
                "series_uid": uid,
                "folder": str(arrival.folder),
                "previous_slices": before,
                "n_slices": scan.n_slices,
                "status": scan.status,
                "reason": reason,
            },
        )
        if self.withdraw is not None:
            self.withdraw(scan_id, reason)
