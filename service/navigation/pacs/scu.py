"""One C-STORE of a Spatial Registration object to the PACS (pynetdicom's SCU), classified.

:func:`c_store` never raises for what the network or the PACS does; it returns a
:class:`StoreOutcome`:

``sent``
    C-STORE response status Success (0x0000) or a Warning (0x0001, 0xB000, 0xB006, 0xB007): the
    PACS has the object.
``refused``
    The PACS answered and said no, permanently: an Error or Failure status that DICOM does not
    class as transient (0xA9xx data set does not match the SOP class, 0xCxxx cannot understand,
    0x0122 SOP class not supported, 0x0124 not authorised, 0x0110 processing failure, ...), a
    permanent association rejection (e.g. called AE title not recognised), or no accepted
    presentation context for Spatial Registration Storage.  Retrying will not help until someone
    changes something; ``dimse_status`` and ``reason`` say what the PACS said.
``transient``
    The PACS answered that it cannot take the object *now*: a status of :data:`TRANSIENT_STATUSES`
    (PS3.4 Annex B.2.3 "Refused: Out of Resources" 0xA700-0xA7FF, PS3.7 Annex C "Resource
    limitation" 0x0213).  Retried with back-off, like ``unreachable``; ``dimse_status`` says which.
``unreachable``
    No answer: connection refused or timed out, TLS handshake failed, association aborted or
    rejected transiently (PS3.8 A-ASSOCIATE-RJ result 2, "rejected-transient"), no C-STORE
    response.  Retried with back-off.
"""

from __future__ import annotations

import logging
import ssl
from dataclasses import dataclass
from io import BytesIO
from typing import Any, Literal

from pydicom import dcmread
from pydicom.uid import ExplicitVRLittleEndian, ImplicitVRLittleEndian

from service.netaddr import printable
from service.settings import PacsSettings

log = logging.getLogger(__name__)

SPATIAL_REGISTRATION_STORAGE = "1.2.840.10008.5.1.4.1.1.66.1"
WARNING_STATUSES = frozenset({0x0001, 0xB000, 0xB006, 0xB007})
"""PS3.4 Annex B.2.3 (C-STORE): the instance was stored, with a coercion or element warning."""

TRANSIENT_STATUS_RANGES: tuple[tuple[int, int], ...] = ((0xA700, 0xA7FF), (0x0213, 0x0213))
"""C-STORE statuses DICOM defines as "try again later": 0xA7xx Refused: Out of Resources (PS3.4
Annex B.2.3, Storage Service Class) and 0x0213 Resource limitation (PS3.7 Annex C, the general
DIMSE failure statuses).  Every other Failure / Error status is permanent."""
RETRIED: frozenset[str] = frozenset({"transient", "unreachable"})
"""Outcomes the export queue retries with back-off."""

Outcome = Literal["sent", "refused", "transient", "unreachable"]


def is_transient(status: int) -> bool:
    """Is DIMSE ``status`` one DICOM defines as transient (:data:`TRANSIENT_STATUS_RANGES`)?"""
    return any(lo <= status <= hi for lo, hi in TRANSIENT_STATUS_RANGES)


@dataclass(frozen=True)
class StoreOutcome:
    kind: Outcome
    dimse_status: int | None
    reason: str


def destination(cfg: PacsSettings) -> str:
    """``AE@host:port`` (``+tls`` when TLS is on), as recorded with each export."""
    return f"{cfg.ae_title}@{cfg.host}:{cfg.port}" + ("+tls" if cfg.tls_ca_file is not None else "")


def tls_context(cfg: PacsSettings) -> ssl.SSLContext | None:
    if cfg.tls_ca_file is None:
        return None
    ctx = ssl.create_default_context(ssl.Purpose.SERVER_AUTH, cafile=str(cfg.tls_ca_file))
    if cfg.tls_cert_file is not None and cfg.tls_key_file is not None:
        ctx.load_cert_chain(str(cfg.tls_cert_file), str(cfg.tls_key_file))
    return ctx


def c_store(sro_bytes: bytes, cfg: PacsSettings) -> StoreOutcome:
    """Send one Part-10 SRO to ``cfg``'s PACS in its own association (see the module docstring)."""
    from pynetdicom import AE, evt

    from dicomnet.scu import associate

    ds = dcmread(BytesIO(sro_bytes))
    ae = AE(ae_title=cfg.calling_ae_title)
    ae.acse_timeout = ae.dimse_timeout = ae.network_timeout = ae.connection_timeout = cfg.timeout_s
    ae.add_requested_context(SPATIAL_REGISTRATION_STORAGE, [ExplicitVRLittleEndian, ImplicitVRLittleEndian])
    received: list[Any] = []
    handlers: list[Any] = [(evt.EVT_ACSE_RECV, lambda event: received.append(event.primitive))]
    where = destination(cfg)
    try:
        ctx = tls_context(cfg)
    except (OSError, ssl.SSLError) as e:
        return StoreOutcome("unreachable", None, f"TLS setup for {where} failed: {e}")
    tls_args = (ctx, cfg.host) if ctx is not None else None
    try:
        assoc = associate(
            ae, cfg.host, cfg.port, ae_title=cfg.ae_title, tls_args=tls_args, evt_handlers=handlers
        )
    except (OSError, ssl.SSLError) as e:
        return StoreOutcome("unreachable", None, f"cannot reach {where}: {e}")
    try:
        if assoc.is_rejected:
            rsp = next((p for p in received if getattr(p, "result", None) in (1, 2)), None)
            text = (
                f"{rsp.result_str} by the {rsp.source_str}: {rsp.reason_str}"
                if rsp is not None
                else "rejected"
            )
            if rsp is not None and rsp.result == 1:
                return StoreOutcome(
                    "refused",
                    None,
                    f"{where} rejected the association ({text}); check pacs.ae_title "
                    "and pacs.calling_ae_title against the PACS's configuration",
                )
            return StoreOutcome("unreachable", None, f"{where} rejected the association ({text})")
        if not assoc.is_established:
            if assoc.is_aborted and received and not assoc.accepted_contexts:
                return StoreOutcome(
                    "refused",
                    None,
                    f"{where} accepts no Spatial Registration Storage "
                    f"({SPATIAL_REGISTRATION_STORAGE}) presentation context",
                )
            return StoreOutcome(
                "unreachable", None, f"no association with {where} (connection refused, timed out or aborted)"
            )
        status = assoc.send_c_store(ds)
        code = int(status.Status) if "Status" in status else None
        if code is None:
            return StoreOutcome(
                "unreachable", None, f"no C-STORE response from {where} (aborted or timed out)"
            )
        comment = printable(str(status.get("ErrorComment", "")).strip(), 200)  # the PACS's text
        if code == 0x0000 or code in WARNING_STATUSES:
            return StoreOutcome(
                "sent", code, f"stored by {where}" + (f" with warning: {comment}" if comment else "")
            )
        said = f"status 0x{code:04X}" + (f" ({comment})" if comment else "")
        if is_transient(code):
            return StoreOutcome(
                "transient", code, f"{where} cannot take the object now: {said} (transient; retried)"
            )
        return StoreOutcome("refused", code, f"{where} refused the object: {said} (permanent; not retried)")
    finally:
        if assoc.is_established:
            assoc.release()
        elif assoc.is_alive():
            assoc.abort()
