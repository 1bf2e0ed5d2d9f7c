"""Both intakes' verdict: a series arrived → snapshot the joints, record the scan (its state, its
instances' hashes), cache its volume, publish the event (:mod:`service.intake.scan_lifecycle`), store the
instance UIDs its Spatial Registration object will reference."""

from __future__ import annotations

import logging
from collections.abc import Sequence
from dataclasses import dataclass, replace
from datetime import datetime
from pathlib import Path
from typing import Any, Protocol

import numpy as np

from registration.errors import OarmRegError
from registration.imaging.volume import Volume
from service.events import Publish, Reopening, ScanArrived, ScanInvalid
from service.intake.scan_lifecycle import ContentChange, Hashes, ScanLifecycle, diff, hash_files
from service.intake.volume_cache import VolumeCache
from service.records import JointSnapshot, NewScan, ScanGeometry, matrix4
from service.store import Database
from service.store.scan_instances import SRO_PATIENT_STUDY_KEYS, ScanInstances

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class SeriesArrival:
    """A series found complete (or found unusable) in the watch folder.

    ``first_seen_t_s`` / ``last_change_t_s`` are ``time.monotonic()`` values: when the
    watcher first saw the folder's current content appear and when it last changed.
    ``volume`` is the loaded :class:`registration.imaging.volume.Volume` (None when ``error`` is set
    or when ``duplicate``).
    """

    series_uid: str
    folder: Path
    first_seen_t_s: float
    last_change_t_s: float
    first_seen_at: datetime
    n_files: int
    volume: Volume | None = None
    error: str = ""
    duplicate: bool = False
    preexisting: bool = False
    reopened: bool = False
    """Late slices of a series recorded before: the earlier record was incomplete."""
    previous_slices: int = 0
    """Slices of the earlier record when ``reopened``."""
    change: Any = None
    """:class:`service.intake.scan_lifecycle.ContentChange` from the recorded content, when known."""
    files: dict[str, tuple[str, int]] | None = None
    """The instances' hashes when the deliverer computed them (else the intake hashes the volume's files)."""
    source: str = "folder"
    """``folder`` or ``dicom``."""


class SnapshotSource(Protocol):
    """What the intake needs of :class:`service.intake.capture.Capture`."""

    def snapshot(
        self, first_seen_t_s: float, last_change_t_s: float, *, preexisting: bool = False
    ) -> JointSnapshot: ...


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
    """The verdict on a delivered series, for both intakes: ``SeriesWatcher``'s ``on_series`` callback
    (watcher thread) and the C-STORE path's release (a worker thread).  One rule set
    (:mod:`service.intake.scan_lifecycle`): the arrival's ``error`` is the failed completeness rule (the
    loader's, or the C-STORE offer tally's); a series recorded before whose content changed is first
    moved to ``reopened`` / ``replaced`` (withdrawing what was made from it), then recorded
    ``complete`` or ``invalid`` with its instances' hashes."""

    def __init__(
        self,
        db: Database,
        capture: SnapshotSource,
        volumes: VolumeCache,
        publish: Publish,
        lifecycle: ScanLifecycle,
    ) -> None:
        self.db = db
        self.capture = capture
        self.volumes = volumes
        self.publish = publish
        self.lifecycle = lifecycle
        """Moves a changed series to ``reopened`` / ``replaced`` and withdraws what was made from it
        (its ``withdraw`` is :meth:`service.registrations.orchestrator.Orchestrator.withdraw_scan`)."""

    def __call__(self, arrival: SeriesArrival) -> None:
        """Record the arrival; a readable, valid series also has its instance UIDs stored (what its
        Spatial Registration object references, :func:`store_instances`)."""
        self._record(arrival)
        if arrival.volume is not None and not arrival.error and not arrival.duplicate:
            meta = arrival.volume.meta
            files = [Path(f) for f in meta.get("files", ())]
            store_instances(self.db, arrival.series_uid, files, sop_uids=meta.get("sop_uids"))

    def _record(self, arrival: SeriesArrival) -> None:
        uid = arrival.series_uid
        if arrival.duplicate:
            self.db.scans.upsert(NewScan(series_uid=uid, folder=str(arrival.folder), status="complete"))
            return
        snap = self.capture.snapshot(
            arrival.first_seen_t_s, arrival.last_change_t_s, preexisting=arrival.preexisting
        )
        scan = new_scan(arrival, snap)
        files = arrival.files
        if files is None:
            files = (
                hash_files(Path(f) for f in arrival.volume.meta.get("files", ())) if arrival.volume else {}
            )
        prev = self.db.scans.by_series_uid(uid)
        source = "dicom" if arrival.source == "dicom" else "folder"
        previous_slices = 0 if prev is None else prev.n_slices
        if prev is not None and prev.status in ("complete", "invalid"):
            # a series judged before: what differs (the folder path sees a change only now)
            change = arrival.change or content_change(prev.status, self.db.scans.files(prev.id), files)
            if prev.status == "complete" and not change.changed and not arrival.error:
                self.db.scans.upsert(NewScan(series_uid=uid, folder=str(arrival.folder), status="complete"))
                return
            if prev.status == "invalid" and not change.changed and arrival.error == prev.reason:
                # the same bytes and the same verdict (the watcher's first pass at every start-up):
                # nothing changed, nothing is withdrawn, nothing is said
                log.debug("scan %d (%s) still invalid, unchanged: %s", prev.id, uid, prev.reason)
                return
            if not change.changed:  # a re-check without a named change (a refusal, an unreadable file)
                change = (
                    ContentChange(replaced=("(unreadable or refused instances)",))
                    if arrival.error
                    else change
                )
            self.lifecycle.changing(
                prev, change, f"{source}: {arrival.folder}", n_slices=None if arrival.error else scan.n_slices
            )
        scan_id, before = self.db.scans.record(scan, files=files)
        self.volumes.discard(uid)
        if arrival.volume is not None and not arrival.error:
            self.volumes.put(uid, arrival.volume)
        reopening = Reopening(before, previous_slices) if before in ("reopened", "replaced") else None
        folder = str(arrival.folder)
        if arrival.error:
            self.publish(ScanInvalid(scan_id=scan_id, series_uid=uid, folder=folder, still=snap.still,
                                     link_state=snap.link_state, source=source, reopening=reopening,
                                     reason=arrival.error))  # fmt: skip
        else:
            self.publish(ScanArrived(scan_id=scan_id, series_uid=uid, folder=folder, still=snap.still,
                                     link_state=snap.link_state, source=source, reopening=reopening,
                                     n_slices=scan.n_slices))  # fmt: skip


def content_change(status: str, recorded: Hashes, now: Hashes) -> ContentChange:
    """What differs between a judged scan's recorded instance hashes and its files now.  An
    ``invalid`` scan recorded without hashes (a version that did not hash invalid folders) cannot be
    compared: no change is claimed, and its verdict is compared instead."""
    if status == "invalid" and not recorded:
        return ContentChange()
    return diff(recorded, now)


def store_instances(
    db: Database, series_uid: str, files: list[Path], *, sop_uids: Sequence[tuple[str, str]] | None = None
) -> None:
    """Record what an SRO references of the series (logged, never raised: the scan is stored).

    ``sop_uids``: (SOP Instance UID, SOP Class UID) per slice when the C-STORE header pass read them
    (:mod:`service.intake.series_accumulator`), so only one file is read again.
    """
    try:
        db.scan_instances.put(scan_instances_from_files(series_uid, files, sop_uids=sop_uids))
    except Exception:
        log.exception("series %s: could not store its instance UIDs; its SRO will be unavailable", series_uid)


def scan_instances_from_files(
    series_uid: str, files: list[Path], *, sop_uids: Sequence[tuple[str, str]] | None = None
) -> ScanInstances:
    """Read the headers an SRO needs from the series' files (slice order kept, multi-frame deduplicated).

    ``sop_uids``: the (SOP Instance UID, SOP Class UID) of each slice in slice order when the header
    pass already read them (:mod:`service.intake.series_accumulator`); then only the first file is read, for
    the patient / study attributes (a 192-slice series: 1 file read instead of 192).
    """
    from pydicom import dcmread

    tags = [
        "SOPClassUID",
        "SOPInstanceUID",
        "StudyInstanceUID",
        "FrameOfReferenceUID",
        *SRO_PATIENT_STUDY_KEYS,
    ]
    seen: dict[str, str] = {}
    first: Any = None
    if sop_uids is not None:
        for inst, cls in sop_uids:
            seen.setdefault(inst, cls)
        files = files[:1]
    for f in dict.fromkeys(files):
        ds = dcmread(f, stop_before_pixels=True, specific_tags=tags)
        first = first if first is not None else ds
        if sop_uids is None:
            seen.setdefault(str(ds.SOPInstanceUID), str(ds.SOPClassUID))
    if first is None:
        raise OarmRegError(f"series {series_uid}: no files to read the instance UIDs from")
    attrs = {k: str(first.get(k, "")) for k in SRO_PATIENT_STUDY_KEYS if k in first}
    return ScanInstances(
        series_uid=series_uid,
        study_uid=str(first.get("StudyInstanceUID", "")),
        frame_of_reference_uid=str(first.get("FrameOfReferenceUID", "")),
        sop_class_uids=tuple(seen.values()),
        sop_instance_uids=tuple(seen),
        attributes=attrs,
    )
