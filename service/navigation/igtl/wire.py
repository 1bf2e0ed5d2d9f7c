"""OpenIGTLink wire format: the 58-byte header, TRANSFORM content, the version-2 extended
header with metadata, and the CRC64 that covers the body.

References (openigtlink/OpenIGTLink ``Documents/Protocol``): ``header.md`` (header),
``transform.md`` (TRANSFORM), ``v3_proposal.md`` (extended header + metadata); the
timestamp fraction follows ``Source/igtlutil/igtl_util.c`` ``igtl_nanosec_to_frac``.
Everything is big-endian.

Header (58 bytes)::

    V uint16 | TYPE char[12] | DEVICE_NAME char[20] | TIME_STAMP uint32 sec + uint32 frac
    | BODY_SIZE uint64 | CRC64 uint64 (over the whole body)

Body, header version 2::

    EXT_HEADER_SIZE uint16 (=12) | METADATA_HEADER_SIZE uint16 | METADATA_SIZE uint32
    | MSG_ID uint32 | content | metadata header | metadata

Metadata header: ``INDEX_COUNT uint16`` then per pair ``KEY_SIZE uint16, VALUE_ENCODING
uint16 (IANA MIBenum, 3 = US-ASCII, 106 = UTF-8), VALUE_SIZE uint32``; then the keys and
values concatenated pairwise (key1 value1 key2 value2 …).

This module is pure (bytes in, bytes out) and is pinned by golden bytes produced by
pyigtl's encoder in ``tests/protocol/test_igtl_wire.py``.
"""

from __future__ import annotations

import struct
import sys
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field

import crcmod  # type: ignore[import-untyped]
import numpy as np
import numpy.typing as npt

from registration.arrays import F64
from service.errors import IgtlCrcError, IgtlWireError

HEADER_SIZE = 58
EXT_HEADER_SIZE = 12
TYPE_SIZE = 12
DEVICE_NAME_SIZE = 20
TRANSFORM_CONTENT_SIZE = 48
IANA_US_ASCII = 3
IANA_UTF8 = 106
MAX_BODY_SIZE = 64 * 1024 * 1024
"""Refuse to read bodies larger than this (a corrupt or hostile BODY_SIZE)."""

_HEADER = struct.Struct(">H12s20sIIQQ")
_EXT = struct.Struct(">HHII")
_TRANSFORM = struct.Struct(">12f")
_META_ITEM = struct.Struct(">HHI")

# CRC-64/ECMA-182 as OpenIGTLink computes it (igtl_util.c ``crc_table``): polynomial
# 0x42F0E1EBA9EA3693, MSB first (not reflected), initial value 0, no final XOR.
CRC64_POLY = 0x42F0E1EBA9EA3693
_MASK64 = (1 << 64) - 1


def _crc_table() -> tuple[int, ...]:
    table = []
    for byte in range(256):
        crc = byte << 56
        for _ in range(8):
            crc = ((crc << 1) ^ CRC64_POLY) if crc & (1 << 63) else (crc << 1)
            crc &= _MASK64
        table.append(crc)
    return tuple(table)


_CRC_TABLE = _crc_table()


def crc64_py(data: bytes, crc: int = 0) -> int:
    """CRC-64/ECMA-182 in pure Python (the reference for :func:`crc64`; ~8.5 MB/s, benchmarks only)."""
    t = _CRC_TABLE
    for b in data:
        crc = t[((crc >> 56) ^ b) & 0xFF] ^ ((crc << 8) & _MASK64)
    return crc


# crcmod's generator polynomial carries the x^64 term (bit 64 set).
_crc64_crcmod = crcmod.mkCrcFun((1 << 64) | CRC64_POLY, initCrc=0, rev=False, xorOut=0)


def crc64(data: bytes, crc: int = 0) -> int:
    """CRC-64/ECMA-182 (OpenIGTLink's variant: init 0, no reflection, no final XOR), by crcmod's
    C extension (benchmarks/bench_igtl_crc.py); ``crc`` continues a CRC."""
    return int(_crc64_crcmod(data, crc))


def native_crc() -> bool:
    """True when crcmod runs its C extension.  crcmod falls back to pure Python silently when its
    extension was not built (no compiler at install time); the server refuses to start then."""
    return bool(getattr(sys.modules.get("crcmod.crcmod"), "_usingExtension", False))


def nanosec_to_frac(nanosec: int) -> int:
    """OpenIGTLink's 32-bit fraction of a second (``igtl_nanosec_to_frac``, bitwise)."""
    base = 1_000_000_000
    mask = 0x80000000
    r = 0
    while mask:
        base = (base + 1) >> 1
        if nanosec >= base:
            r |= mask
            nanosec -= base
        mask >>= 1
    return r


def frac_to_nanosec(frac: int) -> int:
    """Inverse of :func:`nanosec_to_frac` (``igtl_frac_to_nanosec``)."""
    base = 1_000_000_000
    mask = 0x80000000
    r = 0
    while mask:
        base = (base + 1) >> 1
        if frac & mask:
            r += base
        mask >>= 1
    return r


def timestamp_fields(t_s: float) -> tuple[int, int]:
    """``(seconds, fraction)`` of a UNIX time in seconds, as OpenIGTLink packs it."""
    sec = int(t_s)
    return sec, nanosec_to_frac(int((t_s - sec) * 1e9))


@dataclass(frozen=True)
class Header:
    """The 58-byte header, decoded."""

    version: int
    type: str
    device_name: str
    timestamp_s: float
    body_size: int
    crc: int


@dataclass(frozen=True)
class Message:
    """A decoded message: header, content bytes, and (header v2) metadata and MSG_ID."""

    header: Header
    content: bytes
    metadata: dict[str, str] = field(default_factory=dict)
    message_id: int = 0


def _fixed(text: str, size: int, what: str) -> bytes:
    try:
        raw = text.encode("ascii")
    except UnicodeEncodeError:
        raise IgtlWireError(f"{what} {text!r} must be ASCII") from None
    if len(raw) > size:
        raise IgtlWireError(
            f"{what} {text!r} is {len(raw)} bytes; OpenIGTLink allows {size} (receivers would cut it)"
        )
    return raw


def pack_header(
    msg_type: str, device_name: str, timestamp_s: float, body: bytes, *, version: int = 2
) -> bytes:
    """The 58-byte header for ``body`` (CRC64 and BODY_SIZE computed here)."""
    sec, frac = timestamp_fields(timestamp_s)
    return _HEADER.pack(
        version,
        _fixed(msg_type, TYPE_SIZE, "message type"),
        _fixed(device_name, DEVICE_NAME_SIZE, "device name"),
        sec,
        frac,
        len(body),
        crc64(body),
    )


def unpack_header(raw: bytes) -> Header:
    """Decode a 58-byte header (raises :class:`IgtlWireError` for a wrong size or body size)."""
    if len(raw) != HEADER_SIZE:
        raise IgtlWireError(f"an OpenIGTLink header is {HEADER_SIZE} bytes, got {len(raw)}")
    version, typ, name, sec, frac, body_size, crc = _HEADER.unpack(raw)
    if body_size > MAX_BODY_SIZE:
        raise IgtlWireError(f"BODY_SIZE {body_size} exceeds the {MAX_BODY_SIZE}-byte limit")
    return Header(
        version=version,
        type=typ.rstrip(b"\0").decode("ascii", errors="replace"),
        device_name=name.rstrip(b"\0").decode("ascii", errors="replace"),
        timestamp_s=sec + frac_to_nanosec(frac) * 1e-9,
        body_size=body_size,
        crc=crc,
    )


def pack_metadata(metadata: Mapping[str, str]) -> tuple[bytes, bytes]:
    """``(metadata header, metadata)`` for header version 2 (values ASCII if possible, else UTF-8)."""
    if len(metadata) > 0xFFFF:
        raise IgtlWireError(f"at most 65535 metadata pairs, got {len(metadata)}")
    head = [struct.pack(">H", len(metadata))]
    body = []
    for key, value in metadata.items():
        k = key.encode("utf-8")
        enc = IANA_US_ASCII if value.isascii() else IANA_UTF8
        v = value.encode("ascii" if enc == IANA_US_ASCII else "utf-8")
        if len(k) > 0xFFFF:
            raise IgtlWireError(f"metadata key {key[:30]!r}… longer than 65535 bytes")
        head.append(_META_ITEM.pack(len(k), enc, len(v)))
        body += [k, v]
    return b"".join(head), b"".join(body)


def unpack_metadata(head: bytes, body: bytes) -> dict[str, str]:
    """Decode the metadata header + metadata of a version-2 body."""
    if len(head) < 2:
        raise IgtlWireError(f"metadata header of {len(head)} bytes has no INDEX_COUNT")
    (count,) = struct.unpack_from(">H", head)
    if len(head) != 2 + count * _META_ITEM.size:
        raise IgtlWireError(f"metadata header is {len(head)} bytes for {count} pairs")
    out: dict[str, str] = {}
    pos = 0
    for i in range(count):
        ksize, enc, vsize = _META_ITEM.unpack_from(head, 2 + i * _META_ITEM.size)
        if pos + ksize + vsize > len(body):
            raise IgtlWireError(f"metadata pair {i} runs past the end of the metadata")
        key = body[pos : pos + ksize].decode("utf-8", errors="replace")
        pos += ksize
        codec = "ascii" if enc == IANA_US_ASCII else "utf-8"
        out[key] = body[pos : pos + vsize].decode(codec, errors="replace")
        pos += vsize
    return out


def pack_message(
    msg_type: str,
    device_name: str,
    content: bytes,
    *,
    timestamp_s: float,
    metadata: Mapping[str, str] | None = None,
    header_version: int = 2,
    message_id: int = 0,
) -> bytes:
    """A whole message.  ``header_version=1`` sends the bare content (no metadata)."""
    if header_version == 1:
        if metadata:
            raise IgtlWireError("metadata needs header version 2")
        body = content
    elif header_version == 2:
        mhead, mbody = pack_metadata(metadata or {})
        ext = _EXT.pack(EXT_HEADER_SIZE, len(mhead), len(mbody), message_id & 0xFFFFFFFF)
        body = ext + content + mhead + mbody
    else:
        raise IgtlWireError(f"header version must be 1 or 2, got {header_version}")
    return pack_header(msg_type, device_name, timestamp_s, body, version=header_version) + body


def unpack_body(header: Header, body: bytes, *, check_crc: bool = True) -> Message:
    """Split a body into content and metadata; verify its CRC64."""
    if len(body) != header.body_size:
        raise IgtlWireError(f"body is {len(body)} bytes, header says {header.body_size}")
    if check_crc and crc64(body) != header.crc:
        raise IgtlCrcError(
            f"CRC64 mismatch on {header.type} {header.device_name!r}: "
            f"header {header.crc:#018x}, body {crc64(body):#018x}"
        )
    if header.version < 2:
        return Message(header, body)
    if len(body) < EXT_HEADER_SIZE:
        raise IgtlWireError(f"version-2 body of {len(body)} bytes has no extended header")
    ext_size, mhead_size, mbody_size, msg_id = _EXT.unpack_from(body)
    end = len(body) - mhead_size - mbody_size
    if ext_size < EXT_HEADER_SIZE or end < ext_size:
        raise IgtlWireError(
            f"extended header ({ext_size} B) + metadata ({mhead_size}+{mbody_size} B) "
            f"do not fit a {len(body)}-byte body"
        )
    meta = unpack_metadata(body[end : end + mhead_size], body[end + mhead_size :])
    return Message(header, body[ext_size:end], meta, msg_id)


def unpack_message(raw: bytes) -> Message:
    """Decode one complete message (header + body)."""
    header = unpack_header(raw[:HEADER_SIZE])
    return unpack_body(header, raw[HEADER_SIZE:])


# --------------------------------------------------------------------------- TRANSFORM


def pack_transform_content(matrix: npt.ArrayLike) -> bytes:
    """12 float32: R11 R21 R31 R12 R22 R32 R13 R23 R33 TX TY TZ (upper 3×4, column-major)."""
    m = np.asarray(matrix, dtype=np.float64)
    if m.shape != (4, 4) or not np.all(np.isfinite(m)):
        raise IgtlWireError(f"a TRANSFORM needs a finite 4×4 matrix, got shape {m.shape}")
    vals = [float(v) for v in m[:3, :3].T.reshape(9)] + [float(v) for v in m[:3, 3]]
    return _TRANSFORM.pack(*vals)


def unpack_transform_content(content: bytes) -> F64:
    """The 4×4 float64 matrix of a TRANSFORM content (last row 0 0 0 1)."""
    if len(content) != TRANSFORM_CONTENT_SIZE:
        raise IgtlWireError(f"TRANSFORM content is {TRANSFORM_CONTENT_SIZE} bytes, got {len(content)}")
    v = _TRANSFORM.unpack(content)
    m = np.eye(4)
    m[:3, :3] = np.asarray(v[:9], dtype=np.float64).reshape(3, 3).T
    m[:3, 3] = v[9:]
    return m


def pack_transform(
    matrix: npt.ArrayLike,
    device_name: str,
    *,
    timestamp_s: float,
    metadata: Mapping[str, str] | None = None,
    message_id: int = 0,
    header_version: int = 2,
) -> bytes:
    """A TRANSFORM message carrying ``matrix`` (mm) under ``device_name``."""
    return pack_message(
        "TRANSFORM",
        device_name,
        pack_transform_content(matrix),
        timestamp_s=timestamp_s,
        metadata=metadata,
        header_version=header_version,
        message_id=message_id,
    )


# --------------------------------------------------------------------------- STATUS

# status.md / igtlStatusMessage.h codes used here
STATUS_INVALID = 0
STATUS_OK = 1
STATUS_UNKNOWN_ERROR = 2
STATUS_TIME_OUT = 7
STATUS_NOT_READY = 13
STATUS_STRING_MAX = 1000
"""Longest status string sent (bytes; the protocol has no limit, a reader's screen has)."""
_STATUS_HEAD = struct.Struct(">Hq20s")


def status_content(code: int, *, subcode: int = 0, error_name: str = "", status_string: str = "") -> bytes:
    """STATUS content (``status.md``: C uint16, S int64, E char[20], M null-terminated string)."""
    text = status_string.encode("ascii", errors="replace")[:STATUS_STRING_MAX]
    return _STATUS_HEAD.pack(code, subcode, _fixed(error_name, 20, "error name")) + text + b"\0"


def unpack_status_content(content: bytes) -> tuple[int, int, str, str]:
    """``(code, subcode, error_name, status_string)`` of a STATUS content."""
    if len(content) < _STATUS_HEAD.size:
        raise IgtlWireError(f"STATUS content is at least {_STATUS_HEAD.size} bytes, got {len(content)}")
    code, sub, name = _STATUS_HEAD.unpack_from(content)
    text = content[_STATUS_HEAD.size :].split(b"\0", 1)[0]
    return code, sub, name.rstrip(b"\0").decode("ascii", "replace"), text.decode("ascii", "replace")


def pack_status(
    device_name: str,
    *,
    timestamp_s: float,
    code: int = STATUS_OK,
    subcode: int = 0,
    error_name: str = "",
    status_string: str = "",
    header_version: int = 2,
) -> bytes:
    """A STATUS message.

    With ``header_version=2`` and no metadata this is what SlicerOpenIGTLink sends at connect to
    announce that it reads version-2 headers (SlicerOpenIGTLink PR #65).
    """
    content = status_content(code, subcode=subcode, error_name=error_name, status_string=status_string)
    return pack_message(
        "STATUS", device_name, content, timestamp_s=timestamp_s, header_version=header_version
    )


# --------------------------------------------------------------------------- CAPABILITY, POINT


def capability_content(types: Sequence[str]) -> bytes:
    """CAPABILITY content: the message types, 12 bytes each, null-padded (``capability.md``;
    what ``igtl::CapabilityMessage::Pack`` of the reference library writes)."""
    return b"".join(_fixed(t, TYPE_SIZE, "message type").ljust(TYPE_SIZE, b"\0") for t in types)


POINT_ELEMENT_SIZE = 136
_POINT = struct.Struct(">64s32s4B3ff20s")


@dataclass(frozen=True)
class Point:
    """One POINT element (``point.md``): position in mm, the sphere's diameter in mm."""

    name: str
    position_mm: tuple[float, float, float]
    group: str = "Fiducial"
    rgba: tuple[int, int, int, int] = (255, 255, 0, 255)
    diameter_mm: float = 0.0
    owner: str = ""


def point_content(points: Sequence[Point]) -> bytes:
    """POINT content: 136 bytes per point (name 64, group 32, RGBA, XYZ float32, diameter, owner 20)."""
    out = []
    for p in points:
        name = p.name.encode("ascii", errors="replace")[:64]
        group, owner = _fixed(p.group, 32, "point group"), _fixed(p.owner, DEVICE_NAME_SIZE, "point owner")
        xyz = (float(v) for v in p.position_mm)
        out.append(_POINT.pack(name, group, *p.rgba, *xyz, float(p.diameter_mm), owner))
    return b"".join(out)
