"""OpenIGTLink wire format, pinned by golden bytes from pyigtl's encoder (an independent
implementation) and by the CRC-64/ECMA-182 check value."""

from __future__ import annotations

import numpy as np
import pyigtl
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from service.errors import IgtlWireError
from service.navigation.igtl import wire

M = np.array(
    [
        [0.36, 0.48, -0.8, 12.5],
        [-0.8, 0.6, 0.0, -40.25],
        [0.48, 0.64, 0.6, 101.0],
        [0.0, 0.0, 0.0, 1.0],
    ]
)
T_S = 1_700_000_000.25


def pyigtl_bytes(metadata: dict[str, str] | None, header_version: int, msg_id: int = 0) -> bytes:
    msg = pyigtl.TransformMessage(M, timestamp=T_S, device_name="RobotToImage")
    msg.header_version = header_version
    msg.message_id = msg_id
    if metadata:
        msg.metadata = dict(metadata)
    return bytes(msg.pack())


def test_crc64_check_value() -> None:
    # CRC-64/ECMA-182 catalogue check value (init 0, no reflection, no xorout) for "123456789".
    assert wire.crc64(b"123456789") == 0x6C40DF5F0B497347
    assert wire.crc64(b"") == 0


def test_transform_v1_golden_bytes_equal_pyigtl() -> None:
    ours = wire.pack_transform(M, "RobotToImage", timestamp_s=T_S, header_version=1)
    assert ours == pyigtl_bytes(None, 1)
    assert len(ours) == wire.HEADER_SIZE + 48


def test_transform_v2_with_metadata_golden_bytes_equal_pyigtl() -> None:
    meta = {"TransformStatus": "OK", "FRE_mm": "0.412", "RegistrationId": "reg-7"}
    ours = wire.pack_transform(M, "RobotToImage", timestamp_s=T_S, metadata=meta, message_id=42)
    assert ours == pyigtl_bytes(meta, 2, 42)


def test_golden_header_fields() -> None:
    raw = wire.pack_transform(M, "RobotToImage", timestamp_s=T_S, header_version=1)
    # V=1, TYPE "TRANSFORM" NUL-padded to 12, name NUL-padded to 20, 0.25 s = 0x40000000 frac.
    assert raw[:2] == b"\x00\x01"
    assert raw[2:14] == b"TRANSFORM\0\0\0"
    assert raw[14:34] == b"RobotToImage" + b"\0" * 8
    assert raw[34:42] == (1_700_000_000).to_bytes(4, "big") + bytes.fromhex("40000000")
    assert raw[42:50] == (48).to_bytes(8, "big")
    assert raw[50:58] == wire.crc64(raw[58:]).to_bytes(8, "big")


def test_decode_pyigtl_message_round_trip() -> None:
    meta = {"TransformStatus": "INVALID", "Note": "no registration"}
    msg = wire.unpack_message(pyigtl_bytes(meta, 2, 9))
    assert msg.header.type == "TRANSFORM" and msg.header.device_name == "RobotToImage"
    assert msg.header.timestamp_s == pytest.approx(T_S, abs=1e-6)
    assert msg.metadata == meta and msg.message_id == 9
    np.testing.assert_allclose(wire.unpack_transform_content(msg.content), M, atol=1e-5)


def test_utf8_metadata_value_round_trip() -> None:
    # pyigtl 0.3.4 cannot encode non-ASCII values (it catches the wrong exception), so ours only.
    meta = {"Refusal": "ambiguous match: margin 0.2 mm < 1 mm (résumé)"}
    raw = wire.pack_transform(M, "RobotToImage", timestamp_s=T_S, metadata=meta)
    assert wire.unpack_message(raw).metadata == meta


def test_pyigtl_decodes_our_message() -> None:
    meta = {"TransformStatus": "OK", "TRE_pred_mm": "0.9"}
    raw = wire.pack_transform(M, "ToolToImage", timestamp_s=T_S, metadata=meta, message_id=3)
    fields = pyigtl.MessageBase.parse_header(raw[:58])
    rx = pyigtl.MessageBase.create_message(fields["message_type"])
    rx.unpack(fields, raw[58:])
    assert rx.device_name == "ToolToImage" and rx.metadata == meta
    np.testing.assert_allclose(rx.matrix, M, atol=1e-5)


def test_crc_mismatch_refused() -> None:
    raw = bytearray(wire.pack_transform(M, "RobotToImage", timestamp_s=T_S))
    raw[-1] ^= 0x01
    with pytest.raises(IgtlWireError, match="CRC64 mismatch"):
        wire.unpack_message(bytes(raw))


def test_device_name_longer_than_20_bytes_refused_not_truncated() -> None:
    with pytest.raises(IgtlWireError, match="20"):
        wire.pack_transform(M, "CTImageToRobotBaseFrameVeryLong", timestamp_s=T_S)


def test_non_finite_matrix_refused() -> None:
    bad = M.copy()
    bad[0, 3] = np.nan
    with pytest.raises(IgtlWireError, match="finite"):
        wire.pack_transform_content(bad)


def test_timestamp_fraction_round_trip() -> None:
    for ns in (0, 1, 250_000_000, 999_999_999):
        assert abs(wire.frac_to_nanosec(wire.nanosec_to_frac(ns)) - ns) <= 1


def test_oversized_body_refused() -> None:
    raw = bytearray(wire.pack_transform(M, "RobotToImage", timestamp_s=T_S, header_version=1))
    raw[42:50] = (wire.MAX_BODY_SIZE + 1).to_bytes(8, "big")
    with pytest.raises(IgtlWireError, match="BODY_SIZE"):
        wire.unpack_header(bytes(raw[:58]))


@given(st.binary(max_size=5000), st.integers(0, 2**64 - 1))
@settings(max_examples=60, deadline=None)
def test_crcmod_crc64_equals_the_reference_table_loop(data: bytes, start: int) -> None:
    """The C CRC (crcmod) is the pure-Python table loop it replaced, for any bytes and start value."""
    assert wire.crc64(data, start) == wire.crc64_py(data, start)


def test_crcmod_runs_its_c_extension() -> None:
    """crcmod falls back to pure Python silently; the server refuses to start then (issue #32)."""
    assert wire.native_crc()


def test_status_capability_and_point_contents_as_the_reference_library_packs_them() -> None:
    # bytes of igtl::CapabilityMessage::Pack (libopenigtlink 1.11) for TRANSFORM, GET_STATUS
    assert wire.capability_content(["TRANSFORM", "GET_STATUS"]).hex() == (
        "5452414e53464f524d0000004745545f5354415455530000"
    )
    code, sub, name, text = wire.unpack_status_content(
        wire.status_content(13, error_name="INVALID", status_string="no current registration")
    )
    assert (code, sub, name, text) == (13, 0, "INVALID", "no current registration")
    point = wire.Point("+x-r1c1 0.021 mm", (1.5, -2.0, 3.25), diameter_mm=4.0)
    raw = wire.pack_message(
        "POINT", "PhantomSpheres", wire.point_content([point]), timestamp_s=0.0, header_version=1
    )
    msg = pyigtl.MessageBase.create_message("POINT")
    msg.unpack(pyigtl.MessageBase.parse_header(raw[: wire.HEADER_SIZE]), raw[wire.HEADER_SIZE :])
    np.testing.assert_allclose(np.asarray(msg.positions), [[1.5, -2.0, 3.25]])
    assert list(msg.names) == ["+x-r1c1 0.021 mm"] and list(msg.diameters) == [4.0]
