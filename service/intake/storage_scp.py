"""DICOM Storage SCP: the O-arm pushes its CT series here (design §10).

A pynetdicom AE that answers C-ECHO and accepts C-STORE of **CT Image Storage** and
**Enhanced CT Image Storage** only (no MR or other context is offered, so an MR series is
refused at association negotiation), in Implicit / Explicit VR Little Endian, JPEG Lossless
SV1, JPEG-LS lossless and JPEG 2000 lossless.

Each instance is received into a temp file (pynetdicom's ``STORE_RECV_CHUNKED_DATASET``: never
held in memory; larger than ``max_instance_mb`` → 0xA700), its header checked without loading the
pixels, and streamed as received (no decode / re-encode) and atomically (temp file in the same
directory + fsync + rename + directory fsync) to
``intake/<StudyInstanceUID>/<SeriesInstanceUID>/<SOPInstanceUID>.dcm``.  A re-sent identical
instance changes nothing; a re-sent *different* instance with the same SOP Instance UID
replaces the old file atomically and is logged.  ``before_replace`` runs between the fsync and
the rename (the service commits its withdrawal there).  Bounds:
ACSE / DIMSE / network timeouts, a per-connection socket timeout set at ``EVT_CONN_OPEN`` (a peer
stalled mid-PDU is dropped), ``maximum_associations``.

C-STORE statuses (PS3.4 Annex B.2.3):

``0x0000``  stored (or identical copy already stored)
``0xA700``  out of resources: the write failed (ENOSPC, EIO…); nothing half-written is left
``0xA900``  dataset does not match the SOP class: SOP Class / Instance UID differ from the
            request, Modality is not CT, a required attribute is missing, or a UID is malformed
``0xC210``  cannot understand: the dataset could not be decoded

Callbacks run on pynetdicom's association threads: keep them short and thread-safe.
``on_series_released(series_dir, instance_count, calling_ae)`` per series touched by an
association that was released normally (``instance_count`` = ``.dcm`` files now in the
folder); ``on_association_aborted(series_dirs, reason)`` when an association aborts
(its stored instances stay, but the series may be incomplete); ``on_refused(refusal)`` for
every refusal (peer address, calling AE title, rejected presentation context, dataset,
disk); ``on_instance_stored(path, outcome)`` after each instance is on disk;
``on_series_settled`` (used instead of ``on_series_released`` when set) adds the association's
:class:`~service.intake.scan_lifecycle.OfferTally` of the series (offered, stored, refused and why).

It listens through :func:`dicomnet.server.start_server` (pynetdicom's transport with ``poll`` instead
of ``select`` and failed ``accept`` calls reported): what is generic pynetdicom lives in
:mod:`dicomnet`, what the intake stores and refuses lives here.

Security: loopback by default.  A non-loopback bind needs at least one allow-list (calling
AE titles and/or peer addresses); DICOM has no authentication here (no TLS configured).  A calling
AE title may be tied to addresses (``OARM_01@10.0.0.21``); an unlisted caller gets A-ASSOCIATE-RJ
(permanent, calling AE title not recognised).  With the list empty the start-up log and ``/status``
say so.  No address holds more than ``max_associations_per_peer`` associations (A-ASSOCIATE-RJ
transient, local limit exceeded), and one that only echoes for ``network_timeout_s`` is aborted.
"""

from __future__ import annotations

import contextlib
import errno
import logging
import os
import threading
import time
import uuid
from collections import Counter
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any, cast

from pydicom.uid import (
    UID,
    CTImageStorage,
    EnhancedCTImageStorage,
    ExplicitVRLittleEndian,
    ImplicitVRLittleEndian,
    JPEG2000Lossless,
    JPEGLosslessSV1,
    JPEGLSLossless,
)
from pynetdicom import AE, evt
from pynetdicom import _config as _pn_config
from pynetdicom.dimse_primitives import C_STORE

from dicomnet.server import AssociationServer, start_server
from registration.dicom.uids import is_dicom_uid
from service.errors import DicomScpConfigError, InstanceNotStoredError
from service.intake.scan_lifecycle import OfferTally
from service.netaddr import in_networks, parse_networks, printable
from service.settings import as_enabled

if TYPE_CHECKING:
    from service.settings import DicomSettings

log = logging.getLogger(__name__)

TRANSFER_SYNTAXES: tuple[UID, ...] = (
    ImplicitVRLittleEndian,
    ExplicitVRLittleEndian,
    JPEGLosslessSV1,
    JPEGLSLossless,
    JPEG2000Lossless,
)
STORAGE_CLASSES: tuple[UID, ...] = (CTImageStorage, EnhancedCTImageStorage)
VERIFICATION = UID("1.2.840.10008.1.1")

STATUS_SUCCESS = 0x0000
STATUS_OUT_OF_RESOURCES = 0xA700
STATUS_DATASET_MISMATCH = 0xA900
STATUS_CANNOT_UNDERSTAND = 0xC210


_REQUIRED: dict[str, tuple[str, ...]] = {
    CTImageStorage: (
        "StudyInstanceUID", "SeriesInstanceUID", "FrameOfReferenceUID", "ImagePositionPatient",
        "ImageOrientationPatient", "PixelSpacing", "Rows", "Columns", "BitsAllocated", "PixelData",
    ),
    EnhancedCTImageStorage: (
        "StudyInstanceUID", "SeriesInstanceUID", "FrameOfReferenceUID", "NumberOfFrames", "Rows",
        "Columns", "SharedFunctionalGroupsSequence", "PerFrameFunctionalGroupsSequence", "PixelData",
    ),
}  # fmt: skip
"""Type-1 attributes of the CT Image / Enhanced CT Image IODs (PS3.3 A.3, A.38) that the
loader needs; a dataset lacking one does not match its SOP class."""


@dataclass(frozen=True)
class ScpRefusal:
    """Why something was refused.  ``kind``: ``peer``, ``calling_ae``, ``context``,
    ``dataset``, ``disk``."""

    kind: str
    reason: str
    calling_ae: str = ""
    peer: str = ""
    sop_instance_uid: str = ""
    status: int | None = None


@dataclass(frozen=True)
class ScpCallbacks:
    on_series_released: Callable[[Path, int, str], None] | None = None
    on_association_aborted: Callable[[list[Path], str], None] | None = None
    on_refused: Callable[[ScpRefusal], None] | None = None
    on_instance_stored: Callable[[Path, str], None] | None = None
    """``(path, outcome)`` after each instance is on disk; outcome ``stored``, ``duplicates`` or
    ``replaced`` (lets the service decode slices as they arrive)."""
    before_replace: Callable[[Path, str], None] | None = None
    """``(path, outcome)`` once a new (``stored``) or different (``replaced``) instance is written and
    fsynced beside its target, before it is renamed into place: the service commits the withdrawal of
    what was made from the series' earlier content here (the crash order of docs/safety.md, "Scan
    lifecycle").  If it raises the instance is not stored (0xA700)."""
    on_series_settled: Callable[[Path, int, str, OfferTally], None] | None = None
    """Like ``on_series_released`` plus the association's :class:`~service.intake.scan_lifecycle.OfferTally`
    for the series (instances offered, stored, refused and why); used instead when set.  Series whose
    every instance was refused are settled too."""


ALLOW_LIST_EMPTY = (
    "dicom.allowed_calling_ae_titles is empty: any calling AE title may store CT here (and a foreign "
    "instance in the current series withdraws its registration); list the O-arm's AE title"
)


def parse_allowed_callers(entries: tuple[str, ...]) -> dict[str, tuple[Any, ...]]:
    """``dicom.allowed_calling_ae_titles`` entries, ``TITLE`` or ``TITLE@ADDRESS[/PREFIX]`` (as Orthanc's
    ``DicomModalities`` pairs an AE title with its host), as {title: networks (empty = any address)}."""
    out: dict[str, list[Any]] = {}
    for entry in entries:
        title, at, where = entry.strip().partition("@")
        nets = out.setdefault(title.strip(), [])
        if at:
            nets.extend(parse_networks((where.strip(),), "dicom.allowed_calling_ae_titles"))
        else:
            nets.append(None)
    return {t: tuple(n) for t, n in out.items()}


def caller_allowed(allowed: dict[str, tuple[Any, ...]], calling: str, peer: str) -> bool:
    """Is ``calling`` listed, from anywhere or from a network holding ``peer``?"""
    nets = allowed.get(calling)
    if nets is None:
        return False
    return any(n is None for n in nets) or in_networks(peer, tuple(n for n in nets if n is not None))


# --------------------------------------------------------------------------- writing


Writer = Callable[[int, memoryview], int]


def atomic_write(path: Path, data: bytes, *, write: Writer = os.write) -> None:
    """Write ``data`` to ``path`` atomically: a temp file in the same directory, fsync,
    rename over ``path``, fsync the directory.  On any failure the temp file is removed and
    ``path`` is untouched.  ``write`` is ``os.write`` (injectable for fault tests)."""
    tmp = path.with_name(f".{path.name}.{uuid.uuid4().hex}.part")
    fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o644)
    try:
        view = memoryview(data)
        while view:
            n = write(fd, view)
            if n <= 0:
                raise OSError(errno.EIO, f"write returned {n}")
            view = view[n:]
        os.fsync(fd)
    except BaseException:
        os.close(fd)
        with contextlib.suppress(OSError):
            os.unlink(tmp)
        raise
    os.close(fd)
    try:
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(OSError):
            os.unlink(tmp)
        raise
    _fsync_dir(path.parent)


def atomic_copy(
    src: Path,
    path: Path,
    *,
    write: Writer = os.write,
    before_replace: Callable[[], None] | None = None,
) -> None:
    """:func:`atomic_write` of the file ``src``, streamed in 1 MiB chunks (never all in memory);
    ``before_replace()`` runs after the fsync, before the rename (if it raises, nothing is renamed)."""
    tmp = path.with_name(f".{path.name}.{uuid.uuid4().hex}.part")
    fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
    try:
        with open(src, "rb") as f:
            while chunk := f.read(1 << 20):
                view = memoryview(chunk)
                while view:
                    n = write(fd, view)
                    if n <= 0:
                        raise OSError(errno.EIO, f"write returned {n}")
                    view = view[n:]
        os.fsync(fd)
        os.close(fd)
        fd = -1
        if before_replace is not None:
            before_replace()
        os.replace(tmp, path)
    except BaseException:
        if fd >= 0:
            os.close(fd)
        with contextlib.suppress(OSError):
            os.unlink(tmp)
        raise
    _fsync_dir(path.parent)


def _raw_length(ds: Any, keyword: str) -> int:
    """Length of an element read with ``defer_size`` without loading its value."""
    item = ds.get_item(keyword, keep_deferred=True)  # a RawDataElement: its value stays on disk
    n = getattr(item, "length", None)
    return int(n) if n is not None else len(item.value or b"")


def _same_file_content(a: Path, b: Path) -> bool:
    """Byte-for-byte equal (sizes first, then 1 MiB chunks)."""
    if a.stat().st_size != b.stat().st_size:
        return False
    with open(a, "rb") as fa, open(b, "rb") as fb:
        while True:
            ca, cb = fa.read(1 << 20), fb.read(1 << 20)
            if ca != cb:
                return False
            if not ca:
                return True


def _fsync_dir(d: Path) -> None:
    fd = os.open(d, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


# --------------------------------------------------------------------------- the SCP


@dataclass
class _AssocState:
    calling_ae: str
    peer: str
    last_store_s: float = field(default_factory=time.monotonic)
    """When the association was accepted or last carried a C-STORE (monotonic, s)."""
    series: dict[Path, int] = field(default_factory=dict)
    tallies: dict[Path, OfferTally] = field(default_factory=dict)
    unattributed: Counter[str] = field(default_factory=Counter)
    """Refusals whose series could not be read (charged to every series of the association)."""


class StorageScp:
    """The Storage SCP.  Construct (nothing binds), :meth:`start`, :meth:`stop`.

    Parameters
    ----------
    config : DicomSettings
        The ``[dicom]`` section (validated again as an enabled one: :func:`service.settings.as_enabled`).
    intake_dir : Path
        Root of ``<Study>/<Series>/<SOP>.dcm``; created if missing.
    callbacks : ScpCallbacks
    write : callable
        ``os.write``-like function used by :func:`atomic_write` (fault injection in tests).
    """

    def __init__(
        self,
        config: DicomSettings,
        intake_dir: Path,
        callbacks: ScpCallbacks | None = None,
        *,
        write: Writer = os.write,
    ) -> None:
        self.config = config = as_enabled(config, DicomScpConfigError)
        self.intake_dir = Path(intake_dir)
        self.write_failure: str | None = None
        """Why the last instance could not be written (ENOSPC, EIO…); None once one is stored again."""
        self.callbacks = callbacks or ScpCallbacks()
        self._write = write
        self._networks = parse_networks(config.allowed_peer_addresses, "dicom.allowed_peer_addresses")
        self._allowed_aets = parse_allowed_callers(config.allowed_calling_ae_titles)
        self._lock = threading.Lock()
        self._assocs: dict[int, _AssocState] = {}
        self._server: AssociationServer | None = None
        self.counters: dict[str, int] = {
            "stored": 0, "duplicates": 0, "replaced": 0, "refused": 0, "echoes": 0,
            "released": 0, "aborted": 0, "bytes": 0,
            "rejected_busy": 0, "accept_errors": 0, "transport_errors": 0,
            "rejected_peer_share": 0, "closed_echo_only": 0,
        }  # fmt: skip
        self.association_failure: str | None = None
        """Why the intake last refused or failed an association for its own reasons (all
        ``maximum_associations`` slots taken, ``accept`` failing, a transport error); None once an
        association is released normally again.  A ``GET /status`` problem while set."""
        self._accept_error_logged_at = -1e18

    @property
    def active_associations(self) -> int:
        with self._lock:
            return len(self._assocs)

    @property
    def port(self) -> int:
        if self._server is None:
            raise RuntimeError("the DICOM SCP is not started")
        return int(self._server.server_address[1])

    def start(self) -> None:
        """Bind and serve in pynetdicom's threads (returns at once)."""
        self.intake_dir.mkdir(parents=True, exist_ok=True)
        # receive each C-STORE dataset into a temp file instead of memory: a
        # process-wide pynetdicom switch; this service's only SCP is this one
        _pn_config.STORE_RECV_CHUNKED_DATASET = True
        c = self.config
        ae = AE(ae_title=c.ae_title)
        ae.acse_timeout, ae.dimse_timeout, ae.network_timeout = (
            c.acse_timeout_s, c.dimse_timeout_s, c.network_timeout_s,
        )  # fmt: skip
        ae.maximum_associations = c.maximum_associations
        for sop in STORAGE_CLASSES:
            ae.add_supported_context(sop, list(TRANSFER_SYNTAXES))
        ae.add_supported_context(VERIFICATION)
        handlers: list[Any] = [
            (evt.EVT_CONN_OPEN, self._on_conn_open),
            (evt.EVT_REQUESTED, self._on_requested),
            (evt.EVT_ACCEPTED, self._on_accepted),
            (evt.EVT_C_ECHO, self._on_echo),
            (evt.EVT_C_STORE, self._on_store),
            (evt.EVT_RELEASED, self._on_released),
            (evt.EVT_ABORTED, self._on_aborted),
        ]
        handlers.append((evt.EVT_REJECTED, self._on_rejected))
        try:
            self._server = start_server(
                ae, (c.host, c.port), handlers, "oarmreg-dicom-accept",
                on_accept_error=self._on_accept_error, on_transport_error=self._on_transport_error,
            )  # fmt: skip
        except OSError as e:
            raise DicomScpConfigError(
                f"cannot listen for DICOM on {self.config.host}:{self.config.port} ({e}); "
                "is another SCP (storescp, a PACS) using the port?"
            ) from None
        log.info("DICOM Storage SCP %s on %s:%d → %s", self.config.ae_title, self.config.host,
                 self.port, self.intake_dir)  # fmt: skip
        if not self._allowed_aets:
            log.warning("DICOM SCP: %s", ALLOW_LIST_EMPTY)

    @property
    def allow_list(self) -> str | list[str]:
        """For ``GET /status`` (``listeners.dicom.allowed_callers``): the allow-list, or
        :data:`ALLOW_LIST_EMPTY` when there is none."""
        return list(self.config.allowed_calling_ae_titles) or ALLOW_LIST_EMPTY

    def stop(self) -> None:
        if self._server is not None:
            self._server.shutdown()
            self._server = None

    def __enter__(self) -> StorageScp:
        self.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop()

    # ---- negotiation ----------------------------------------------------------

    def _refuse(self, refusal: ScpRefusal, *, level: int = logging.WARNING) -> None:
        with self._lock:
            self.counters["refused"] += 1
        log.log(level, "DICOM SCP refused (%s) from %s %s: %s", refusal.kind, refusal.calling_ae,
                refusal.peer, refusal.reason)  # fmt: skip
        if self.callbacks.on_refused is not None:
            try:
                self.callbacks.on_refused(refusal)
            except Exception:
                log.exception("DICOM SCP: on_refused callback failed")

    def _association_failed(self, counter: str, reason: str, *, log_it: bool = True) -> None:
        with self._lock:
            self.counters[counter] += 1
            self.association_failure = reason
        if log_it:
            log.warning("DICOM SCP: %s", reason)

    def _on_rejected(self, event: evt.Event) -> None:
        """pynetdicom rejected an association itself (its ACSE checks): all slots taken, mostly."""
        prim = event.assoc.acceptor.primitive
        peer = str(event.assoc.requestor.address)
        calling = str(event.assoc.requestor.ae_title).strip()
        if prim is not None and (prim.result_source, prim.diagnostic) == (0x03, 0x02):
            n = self.config.maximum_associations
            self._association_failed(
                "rejected_busy",
                f"association from {calling} {peer} rejected: all dicom.maximum_associations = {n} slots "
                "are taken (local limit exceeded); the sender must retry; raise dicom.maximum_associations "
                "if the O-arm and other senders need more at once",
            )
        else:
            why = "" if prim is None else f" (result {prim.result}, source {prim.result_source}, "
            why += "" if prim is None else f"diagnostic {prim.diagnostic})"
            self._refuse(ScpRefusal("association", f"association rejected by pynetdicom{why}", calling, peer))

    def _on_accept_error(self, e: OSError) -> None:
        """``accept`` failed (EMFILE: out of descriptors): the peer waits unanswered in the backlog."""
        now = time.monotonic()
        with self._lock:
            quiet = now - self._accept_error_logged_at < 10.0
            if not quiet:
                self._accept_error_logged_at = now
        self._association_failed(
            "accept_errors",
            f"cannot accept a DICOM connection ({e.strerror or e}); the O-arm cannot send scans: check "
            "the descriptor budget (docs/operations.md) and what holds the service's connections",
            log_it=not quiet,
        )

    def _on_transport_error(self, reason: str) -> None:
        self._association_failed(
            "transport_errors", f"association dropped by a transport error: {reason}; see the log"
        )

    def _on_conn_open(self, event: evt.Event) -> None:
        """Bound every blocking read / write of this connection: pynetdicom applies its
        ``network_timeout`` to the listening socket only, so a peer that stops half-way through a PDU
        would hold its thread and association slot forever."""
        sock = getattr(getattr(event.assoc.dul, "socket", None), "socket", None)
        if sock is not None:
            sock.settimeout(self.config.socket_timeout_s)

    def _peer_allowed(self, host: str) -> bool:
        return not self._networks or in_networks(host, self._networks)

    def _on_requested(self, event: evt.Event) -> None:
        assoc = event.assoc
        prim = assoc.requestor.primitive
        calling = str(prim.calling_ae_title).strip() if prim is not None else ""
        peer = str(assoc.requestor.address)
        if not self._peer_allowed(peer):
            assoc.acse.send_reject(0x01, 0x01, 0x01)  # rejected-permanent, service user, no reason
            assoc.kill()  # as pynetdicom's own ACSE does: lets the DUL flush the A-ASSOCIATE-RJ
            self._refuse(
                ScpRefusal("peer", f"peer {peer} not in dicom.allowed_peer_addresses", calling, peer)
            )
        elif self._allowed_aets and not caller_allowed(self._allowed_aets, calling, peer):
            assoc.acse.send_reject(0x01, 0x01, 0x03)  # calling AE title not recognised
            assoc.kill()
            listed = list(self.config.allowed_calling_ae_titles)
            self._refuse(ScpRefusal(
                "calling_ae", f"calling AE title {printable(calling)!r} from {peer} not in "
                f"dicom.allowed_calling_ae_titles {listed}", printable(calling), peer,
            ))  # fmt: skip
        elif self._peer_slots_taken(peer) >= self.config.max_associations_per_peer:
            assoc.acse.send_reject(0x02, 0x03, 0x02)  # rejected-transient, provider, local limit exceeded
            assoc.kill()
            with self._lock:
                self.counters["rejected_peer_share"] += 1
            n, m = self.config.max_associations_per_peer, self.config.maximum_associations
            self._association_failed(
                "rejected_busy",
                f"association from {printable(calling)} {peer} rejected: that address holds its share of "
                f"dicom.max_associations_per_peer = {n} of the dicom.maximum_associations = {m} slots (so "
                "one host cannot lock the O-arm out); the sender must release one first",
            )

    def _peer_slots_taken(self, peer: str) -> int:
        with self._lock:
            return sum(1 for st in self._assocs.values() if st.peer == peer)

    def _on_accepted(self, event: evt.Event) -> None:
        assoc = event.assoc
        state = _AssocState(printable(str(assoc.requestor.ae_title).strip()), str(assoc.requestor.address))
        with self._lock:
            self._assocs[id(assoc)] = state
        names = sorted(
            {UID(cx.abstract_syntax or "").name or str(cx.abstract_syntax) for cx in assoc.rejected_contexts}
        )
        if names:  # one report per association (storescu, for one, proposes ~120 classes)
            shown = ", ".join(names[:8]) + (f" and {len(names) - 8} more" if len(names) > 8 else "")
            # Refusing the standard classes a sender proposes besides CT is the normal case: DEBUG
            # while some context was accepted; a WARNING when none was (wrong modality).
            level = logging.DEBUG if assoc.accepted_contexts else logging.WARNING
            self._refuse(ScpRefusal(
                "context", f"presentation context(s) refused: {shown}; only CT Image Storage and "
                "Enhanced CT Image Storage are accepted", state.calling_ae, state.peer,
            ), level=level)  # fmt: skip

    def _on_echo(self, event: evt.Event) -> int:
        """Answer success; an association that has only echoed for ``network_timeout_s`` (no C-STORE
        since it was accepted or since its last one) is then aborted, so echoes cannot hold a slot."""
        now = time.monotonic()
        with self._lock:
            self.counters["echoes"] += 1
            state = self._assocs.get(id(event.assoc))
            idle = state is not None and now - state.last_store_s > self.config.network_timeout_s
            if idle:
                self.counters["closed_echo_only"] += 1
        if idle and state is not None:
            log.warning("DICOM SCP: association from %s %s closed: only C-ECHO for more than "
                        "dicom.network_timeout_s = %g s", state.calling_ae, state.peer,
                        self.config.network_timeout_s)  # fmt: skip
            threading.Thread(target=event.assoc.abort, name="oarmreg-dicom-echo-abort", daemon=True).start()
        return STATUS_SUCCESS

    # ---- storage ---------------------------------------------------------------

    def _on_store(self, event: evt.Event) -> int:
        assoc = event.assoc
        with self._lock:
            state = self._assocs.get(id(assoc)) or _AssocState("", "")
            state.last_store_s = time.monotonic()
        sop = str(cast(C_STORE, event.request).AffectedSOPInstanceUID or "")
        status, reason, target, series_dir = self._check(event, sop)
        if target is None:
            self._refuse(ScpRefusal("dataset", reason, state.calling_ae, state.peer, sop, status))
            self._tally_failed(state, series_dir, f"0x{status:04X} {reason}")
            return status
        try:
            outcome = self._store(target, event.dataset_path)
        except OSError as e:
            reason = f"cannot write {target} ({e.strerror or e}); check free space on {self.intake_dir}"
            with self._lock:
                self.write_failure = reason
            self._refuse(
                ScpRefusal("disk", reason, state.calling_ae, state.peer, sop, STATUS_OUT_OF_RESOURCES)
            )
            self._tally_failed(state, target.parent, f"0x{STATUS_OUT_OF_RESOURCES:04X} {reason}")
            return STATUS_OUT_OF_RESOURCES
        except InstanceNotStoredError as e:
            reason = f"{sop} not stored: {e}"
            self._refuse(
                ScpRefusal("disk", reason, state.calling_ae, state.peer, sop, STATUS_OUT_OF_RESOURCES)
            )
            self._tally_failed(state, target.parent, f"0x{STATUS_OUT_OF_RESOURCES:04X} {reason}")
            return STATUS_OUT_OF_RESOURCES
        with self._lock:
            self.write_failure = None
            self.counters[outcome] += 1
            self.counters["bytes"] += target.stat().st_size if outcome != "duplicates" else 0
            state.series[target.parent] = state.series.get(target.parent, 0) + 1
            state.tallies.setdefault(target.parent, OfferTally()).add_stored()
        if self.callbacks.on_instance_stored is not None:
            try:
                self.callbacks.on_instance_stored(target, outcome)
            except Exception:
                log.exception("DICOM SCP: on_instance_stored callback failed")
        return STATUS_SUCCESS

    def _tally_failed(self, state: _AssocState, series_dir: Path | None, why: str) -> None:
        with self._lock:
            if series_dir is None:
                state.unattributed[why] += 1
            else:
                state.tallies.setdefault(series_dir, OfferTally()).add_failed(why)

    def _check(self, event: evt.Event, sop: str) -> tuple[int, str, Path | None, Path | None]:
        """``(status, reason, target path or None, series folder or None)`` for one C-STORE request."""
        from pydicom import dcmread

        path = Path(event.dataset_path)
        size = path.stat().st_size
        limit = int(self.config.max_instance_mb * 1024**2)
        series_dir: Path | None = None
        try:
            ds = dcmread(path, defer_size=4096)  # large values (Pixel Data) stay on disk
            cls = str(ds.get("SOPClassUID", ""))
            inst = str(ds.get("SOPInstanceUID", ""))
            modality = str(ds.get("Modality", ""))
            missing = [
                k for k in _REQUIRED.get(cls, ())
                if k not in ds or (_raw_length(ds, k) == 0 if k == "PixelData" else ds[k].is_empty)
            ]  # fmt: skip
            study, series = str(ds.get("StudyInstanceUID", "")), str(ds.get("SeriesInstanceUID", ""))
        except Exception as e:
            return (
                STATUS_CANNOT_UNDERSTAND,
                f"dataset {sop} cannot be decoded ({type(e).__name__}: {e})",
                None,
                None,
            )
        uids_ok = all(is_dicom_uid(u) for u in (study, series, sop))  # PS3.5 §9.1, and path-safe
        if uids_ok:
            series_dir = self.intake_dir / study / series
        req_cls = str(cast(C_STORE, event.request).AffectedSOPClassUID or "")
        if size > limit:
            return (
                STATUS_OUT_OF_RESOURCES,
                f"{sop}: {size / 1024**2:.0f} MB is more than dicom.max_instance_mb = "
                f"{self.config.max_instance_mb:g}",
                None,
                series_dir,
            )
        if cls != req_cls or inst != sop:
            why = f"dataset says SOP Class {cls!r} / Instance {inst!r}, the request {req_cls!r} / {sop!r}"
        elif modality != "CT":
            why = f"Modality is {modality!r}, a CT image needs 'CT'"
        elif missing:
            why = f"required attribute(s) missing or empty: {', '.join(missing)}"
        elif not uids_ok:
            why = f"malformed UID among Study {study!r}, Series {series!r}, SOP {sop!r}"
        else:
            assert series_dir is not None
            return STATUS_SUCCESS, "", series_dir / f"{sop}.dcm", series_dir
        return STATUS_DATASET_MISMATCH, f"{UID(req_cls).name or req_cls} {sop}: {why}", None, series_dir

    def _store(self, target: Path, received: Path) -> str:
        """Put one received instance (pynetdicom's temp file, DICOM File Format) in place; returns
        the counter to bump (stored / duplicates / replaced)."""
        target.parent.mkdir(parents=True, exist_ok=True)
        outcome = "stored"
        if target.exists():
            if _same_file_content(target, received):
                return "duplicates"
            log.warning("DICOM SCP: %s re-sent with different content; replacing", target.name)
            outcome = "replaced"
        hook = self.callbacks.before_replace

        def before() -> None:
            if hook is None:
                return
            try:
                hook(target, outcome)
            except Exception as e:
                log.exception("DICOM SCP: before_replace failed for %s", target)
                raise InstanceNotStoredError(
                    f"the change of series {target.parent.name} could not be recorded ({e}); nothing was "
                    "replaced"
                ) from e

        atomic_copy(received, target, write=self._write, before_replace=before)
        return outcome

    # ---- end of association -------------------------------------------------------

    def _pop(self, event: evt.Event) -> _AssocState | None:
        with self._lock:
            return self._assocs.pop(id(event.assoc), None)

    def _on_released(self, event: evt.Event) -> None:
        state = self._pop(event)
        if state is None:
            return
        with self._lock:
            self.counters["released"] += 1
            self.association_failure = None  # the intake works again
        for series_dir in sorted(set(state.series) | set(state.tallies)):
            n = sum(1 for _ in series_dir.glob("*.dcm"))
            log.info("DICOM SCP: series %s released by %s with %d instance(s) on disk",
                     series_dir.name, state.calling_ae, n)  # fmt: skip
            tally = state.tallies.get(series_dir, OfferTally())
            for why, k in state.unattributed.items():
                tally.failed[why] += k
                tally.offered += k
            if self.callbacks.on_series_settled is not None:
                try:
                    self.callbacks.on_series_settled(series_dir, n, state.calling_ae, tally)
                except Exception:
                    log.exception("DICOM SCP: on_series_settled callback failed")
            elif self.callbacks.on_series_released is not None:
                try:
                    self.callbacks.on_series_released(series_dir, n, state.calling_ae)
                except Exception:
                    log.exception("DICOM SCP: on_series_released callback failed")

    def _on_aborted(self, event: evt.Event) -> None:
        state = self._pop(event)
        if state is None:  # rejected or never established
            return
        with self._lock:
            self.counters["aborted"] += 1
        kind = "A-P-ABORT (network or protocol)" if event.assoc.acse.is_aborted("a-p-abort") else "A-ABORT"
        reason = (
            f"association from {state.calling_ae} {state.peer} aborted ({kind}); series may be incomplete"
        )
        dirs = sorted(state.series)
        log.warning("DICOM SCP: %s; %d series touched", reason, len(dirs))
        if self.callbacks.on_association_aborted is not None:
            try:
                self.callbacks.on_association_aborted(dirs, reason)
            except Exception:
                log.exception("DICOM SCP: on_association_aborted callback failed")
