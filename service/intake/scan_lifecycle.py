"""One scan lifecycle for both intakes, the folder watcher and the C-STORE SCP.

States (``scans.status``, docs/safety.md "Scan lifecycle"):

``receiving``  instances of a series the service has not judged yet are arriving (C-STORE: from the
               first instance of an unknown series until its association ends)
``complete``   every completeness rule holds (:func:`completeness_rules` names them); the only state
               that can be registered, verified or calibrated with
``reopened``   instances were *added* to a series after it was judged (a later association, late
               files in the folder)
``replaced``   an instance of a judged series was replaced with different bytes, or removed
``invalid``    a rule fails; the reason names which and what to do

Every stored instance carries a SHA-256 of its file (``scan_files``).  An identical re-send changes
nothing.  Any change of content after the series was judged moves it to ``reopened`` / ``replaced``
and **withdraws everything made from it** (registrations — the current one included, so
``/registration/current`` answers 409 naming the scan and the change and every OpenIGTLink client
gets INVALID —, verifications, calibrations), recording why (``scan_changes``); then the changed
series is judged again (``complete`` or ``invalid``).  On the C-STORE path the withdrawal is
committed *before* the changed file is renamed into place (:meth:`ScanLifecycle.changing` is the
SCP's ``before_replace`` hook); at start-up :meth:`ScanLifecycle.recover` re-hashes the current
registration's scan and ends every interrupted change, so a kill -9 between the two steps leaves
nothing stale current.
"""

from __future__ import annotations

import hashlib
import logging
from collections import Counter
from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass, field
from pathlib import Path

from service.events import Publish, ScanReopened, ScanReplaced
from service.intake.volume_cache import VolumeCache
from service.records import ScanRecord, ScanStatus
from service.store import Database

log = logging.getLogger(__name__)

USABLE: ScanStatus = "complete"
CHANGING: tuple[ScanStatus, ...] = ("receiving", "reopened", "replaced")
"""States a series is in only while a delivery is under way; found at start-up they were interrupted."""

HASH_CHUNK_BYTES = 1 << 20

Hashes = dict[str, tuple[str, int]]
"""``file name → (sha256 hex, bytes)`` of a scan's instances (names inside the scan's folder)."""


def completeness_rules() -> tuple[str, ...]:
    """The rules a series must meet to be ``complete`` (the same for both intakes; docs/safety.md)."""
    return (
        "every instance the sender offered for the series was stored (C-STORE: one refused or failed "
        "instance in an association leaves the series incomplete, naming how many and why)",
        "as many slices as the headers announce (ImagesInAcquisition) where they announce a count",
        "contiguous, uniformly spaced slice positions, one Frame of Reference, one image size",
        "every instance of the series loads",
    )


def sha256_file(path: Path) -> tuple[str, int]:
    """SHA-256 (hex) and size of one regular file, read in 1 MiB chunks."""
    h = hashlib.sha256()
    n = 0
    with open(path, "rb") as f:
        while chunk := f.read(HASH_CHUNK_BYTES):
            h.update(chunk)
            n += len(chunk)
    return h.hexdigest(), n


def hash_files(paths: Iterable[Path]) -> Hashes:
    """:func:`sha256_file` of each file, by name (a multi-frame file listed once)."""
    return {p.name: sha256_file(p) for p in dict.fromkeys(Path(p) for p in paths)}


@dataclass(frozen=True)
class ContentChange:
    """How a series' instances differ from what was recorded."""

    added: tuple[str, ...] = ()
    replaced: tuple[str, ...] = ()
    removed: tuple[str, ...] = ()

    @property
    def changed(self) -> bool:
        return bool(self.added or self.replaced or self.removed)

    @property
    def state(self) -> ScanStatus:
        """``replaced`` when recorded bytes changed or vanished, ``reopened`` when only added to."""
        return "replaced" if self.replaced or self.removed else "reopened"

    def describe(self) -> str:
        parts = []
        for what, names in (("added", self.added), ("replaced with different bytes", self.replaced),
                            ("removed", self.removed)):  # fmt: skip
            if names:
                shown = ", ".join(names[:3]) + (f" and {len(names) - 3} more" if len(names) > 3 else "")
                parts.append(f"{len(names)} instance(s) {what} ({shown})")
        return "; ".join(parts) or "no change"


def diff(before: Mapping[str, tuple[str, int]], after: Mapping[str, tuple[str, int]]) -> ContentChange:
    """The change from ``before`` to ``after`` (both :data:`Hashes`)."""
    return ContentChange(
        added=tuple(sorted(set(after) - set(before))),
        replaced=tuple(sorted(n for n in set(after) & set(before) if after[n][0] != before[n][0])),
        removed=tuple(sorted(set(before) - set(after))),
    )


def rehash(folder: Path, recorded: Mapping[str, tuple[str, int]]) -> ContentChange:
    """Re-hash the recorded instances in ``folder``: which were replaced or removed (never raises)."""
    replaced, removed = [], []
    for name, (sha, _n) in recorded.items():
        p = folder / name
        try:
            if not p.is_file() or p.is_symlink():
                removed.append(name)
            elif sha256_file(p)[0] != sha:
                replaced.append(name)
        except OSError:
            removed.append(name)
    return ContentChange(replaced=tuple(sorted(replaced)), removed=tuple(sorted(removed)))


@dataclass
class OfferTally:
    """What one association offered for one series: instances stored and instances not stored, by why."""

    offered: int = 0
    stored: int = 0
    failed: Counter[str] = field(default_factory=Counter)

    def add_stored(self) -> None:
        self.offered += 1
        self.stored += 1

    def add_failed(self, why: str) -> None:
        self.offered += 1
        self.failed[why] += 1

    def problem(self, series_uid: str) -> str:
        """``""`` when every offered instance was stored; else the completeness rule's refusal."""
        n_failed = sum(self.failed.values())
        if not n_failed:
            return ""
        reasons = "; ".join(f"{n} × {why}" for why, n in self.failed.most_common(4))
        more = f" (+{len(self.failed) - 4} other reasons)" if len(self.failed) > 4 else ""
        return (
            f"series {series_uid}: {n_failed} of the {self.offered} instance(s) the sender offered in one "
            f"association were not stored ({reasons}{more}); the series is incomplete. Fix the cause "
            "(GET /events lists each dicom_refused) and send the whole series again"
        )


Withdraw = Callable[[int, str], object]


class ScanLifecycle:
    """The transitions of the state machine that are not a plain verdict (those are
    :meth:`service.store.scans.ScanStore.record` calls made by :class:`service.intake.recording.Intake`).

    ``withdraw(scan_id, reason)`` is :meth:`service.registrations.orchestrator.Orchestrator.withdraw_scan`.
    Thread-safe (the database serialises; the SCP's association threads and the watcher call it).
    """

    def __init__(
        self, db: Database, volumes: VolumeCache, publish: Publish, withdraw: Withdraw | None
    ) -> None:
        self.db = db
        self.volumes = volumes
        self.publish = publish
        self.withdraw = withdraw

    def changing(
        self, scan: ScanRecord, change: ContentChange, source: str, *, n_slices: int | None = None
    ) -> ScanStatus:
        """The content of a judged series is about to change (C-STORE: before the file is renamed into
        place) or has changed (folder: seen after the quiet period).  Marks it ``reopened`` /
        ``replaced`` (committed first: a registration starting now is refused), forgets its cached
        volume, publishes ``scan_reopened`` / ``scan_replaced`` (``n_slices``: the new count when the
        deliverer knows it), then withdraws what was made from it.  A series already ``reopened`` /
        ``replaced`` / ``receiving`` only has its state updated."""
        to: ScanStatus = change.state
        if scan.status == "replaced":
            to = "replaced"
        if scan.status == to:
            return to
        earlier = (
            "the earlier record was incomplete"
            if to == "reopened"
            else "the content it was made from is gone"
        )
        reason = (
            f"scan {scan.id} (series {scan.series_uid}) changed after it was recorded {scan.status} "
            f"({source}): {change.describe()}; {earlier}, so everything made from it is withdrawn. "
            "Register the scan again once it is complete"
        )
        self.db.scans.set_status(scan.id, to, reason)
        self.volumes.discard(scan.series_uid)
        if scan.status != "receiving":
            log.warning("%s", reason)
            kind = ScanReopened if to == "reopened" else ScanReplaced
            self.publish(
                kind(
                    scan_id=scan.id, series_uid=scan.series_uid, folder=scan.folder, source=source,
                    previous_status=scan.status, previous_slices=scan.n_slices, added=tuple(change.added),
                    replaced=tuple(change.replaced), removed=tuple(change.removed), reason=reason,
                    n_slices=n_slices,
                )
            )  # fmt: skip
        if scan.status in ("complete", "invalid") and self.withdraw is not None:
            self.withdraw(scan.id, reason)
        return to

    def recover(self, *, cstore_root: Path | None) -> list[str]:
        """At start-up: end interrupted changes and re-hash the current registration's scan.

        * a current registration whose scan is not ``complete`` is withdrawn;
        * a C-STORE series (under ``cstore_root``) left ``receiving`` / ``reopened`` / ``replaced`` is
          recorded ``invalid`` (its association is gone: send it again); a folder series in those
          states is judged again by the watcher's first pass;
        * the current registration's scan is re-hashed against its recorded instances: any instance
          replaced or missing withdraws it (``invalid``, with the change).

        Returns what was done (logged too)."""
        done: list[str] = []
        for scan in self.db.scans.in_status(*CHANGING):
            if cstore_root is not None and Path(scan.folder).is_relative_to(cstore_root):
                why = (
                    f"the service stopped while scan {scan.id} (series {scan.series_uid}) was {scan.status}; "
                    "its association is gone and it may be incomplete: send the series again"
                )
                self.db.scans.set_status(scan.id, "invalid", why)
                self._withdraw(scan.id, why)
                done.append(why)
        cur = self.db.registrations.current()
        if cur is None or cur.scan_id is None:
            return done
        found = self.db.scans.get(cur.scan_id)
        if found is None:
            return done
        scan = found
        if scan.status != USABLE:
            why = (
                f"registration {cur.id} was current at start-up but its scan {scan.id} (series "
                f"{scan.series_uid}) is {scan.status}: {scan.reason}"
            )
            self._withdraw(scan.id, why)
            done.append(why)
            return done
        recorded = self.db.scans.files(scan.id)
        if not recorded:
            log.warning("scan %d has no recorded instance hashes (an older version); not re-hashed",
                        scan.id)  # fmt: skip
            return done
        change = rehash(Path(scan.folder), recorded)
        if change.changed:
            why = (
                f"scan {scan.id} (series {scan.series_uid}) changed while the service was stopped: "
                f"{change.describe()} in {scan.folder}; registration {cur.id} made from its earlier content "
                "is withdrawn. Send or export the scan again and register it"
            )
            self.db.scans.set_status(scan.id, "invalid", why)
            self.volumes.discard(scan.series_uid)
            self._withdraw(scan.id, why)
            done.append(why)
        else:
            log.info("start-up: scan %d of the current registration %d re-hashed: %d instance(s) unchanged",
                     scan.id, cur.id, len(recorded))  # fmt: skip
        return done

    def _withdraw(self, scan_id: int, why: str) -> None:
        log.warning("start-up: %s", why)
        if self.withdraw is not None:
            self.withdraw(scan_id, why)
