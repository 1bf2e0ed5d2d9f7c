"""Receive one OpenIGTLink TRANSFORM as a client (the demo's "is it really on the wire" check).

With pyigtl importable (a test extra) its ``OpenIGTLinkClient`` is used, an independent
implementation; otherwise this module's plain-socket reader with the project's own
:mod:`service.navigation.igtl.wire` decoder.  :attr:`Received.via` says which.

Either way the probe first sends a header-version-2 message, as SlicerOpenIGTLink does at
connect, so that the server answers in version 2 with metadata (it sends version 1 until then);
only version-2 TRANSFORMs are returned.
"""

from __future__ import annotations

import socket
import time
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from service.errors import IgtlProbeError
from service.navigation.igtl import wire

HELLO_DEVICE = "OarmregProbe"
"""Device name of the version-2 message the probe sends at connect."""


@dataclass(frozen=True)
class Received:
    matrix: npt.NDArray[np.float64]
    metadata: dict[str, str]
    via: str


def receive_transform(
    host: str, port: int, device: str, *, registration_id: str | None = None, timeout_s: float = 10.0
) -> Received:
    """The first ``device`` TRANSFORM (with ``RegistrationId == registration_id`` if given)."""
    try:
        import pyigtl
    except ImportError:
        return _receive_raw(host, port, device, registration_id, timeout_s)
    client = pyigtl.OpenIGTLinkClient(host=host, port=port)
    try:
        hello = pyigtl.StringMessage("oarmreg probe: reads header version 2", device_name=HELLO_DEVICE)
        hello.header_version = 2
        client.send_message(hello, wait=False)
        end = time.monotonic() + timeout_s
        while time.monotonic() < end:
            m = client.wait_for_message(device, timeout=0.5)
            if (
                m is not None
                and m.header_version >= 2
                and (registration_id is None or m.metadata.get("RegistrationId") == registration_id)
            ):
                meta = {str(k): str(v) for k, v in m.metadata.items()}
                return Received(np.asarray(m.matrix, dtype=np.float64), meta, "pyigtl OpenIGTLinkClient")
    finally:
        client.stop()
    raise IgtlProbeError(
        f"no {device} TRANSFORM (registration {registration_id}) from {host}:{port} in {timeout_s} s"
    )


def _receive_raw(
    host: str, port: int, device: str, registration_id: str | None, timeout_s: float
) -> Received:
    end = time.monotonic() + timeout_s
    with socket.create_connection((host, port), timeout=timeout_s) as sock:
        sock.sendall(wire.pack_status(HELLO_DEVICE, timestamp_s=time.time()))
        f = sock.makefile("rb")
        while time.monotonic() < end:
            head = wire.unpack_header(f.read(wire.HEADER_SIZE))
            msg = wire.unpack_body(head, f.read(head.body_size))
            wanted = head.version >= 2 and (
                registration_id is None or msg.metadata.get("RegistrationId") == registration_id
            )
            if head.type == "TRANSFORM" and head.device_name == device and wanted:
                m = wire.unpack_transform_content(msg.content)
                return Received(
                    m, dict(msg.metadata), "service.navigation.igtl.wire decoder on a plain socket"
                )
    raise IgtlProbeError(
        f"no {device} TRANSFORM (registration {registration_id}) from {host}:{port} in {timeout_s} s"
    )
