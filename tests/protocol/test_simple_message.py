"""Golden bytes for simple_message as sent by the Stäubli VAL3 driver.

Test vectors: research/staubli-link.md §1.4 (JOINT_POSITION) and §1.5 (STATUS).
"""

from __future__ import annotations

import math
import struct
import tracemalloc

import pytest

from drivers.errors import ProtocolError
from drivers.simple_message import (
    JOINT_FEEDBACK_LENGTH,
    JOINT_POSITION_LENGTH,
    MAX_LENGTH,
    MIN_LENGTH,
    MSG_JOINT_FEEDBACK,
    MSG_JOINT_POSITION,
    MSG_STATUS,
    FrameReassembler,
    Header,
    JointFeedback,
    JointPosition,
    Status,
    Unknown,
    decode_message,
    encode,
    encode_joint_position,
)

# §1.4: q = 10, 20, 30, 40, 50, 60 deg, sequence 0, comm_type TOPIC, reply 0
JOINT_POSITION_HEX = (
    "380000000a000000010000000000000000000000c2b8323ec2b8b23e920a063fc2b8323ff3665f3f920a863f"
    "00000000000000000000000000000000"
)
JOINT_POSITION_DEG = (10.0, 19.999999, 30.000001, 39.999999, 50.0, 60.000002)  # as stated in §1.4
# §1.5: powered, auto, motion possible
STATUS_HEX = "280000000d000000010000000000000001000000000000000000000000000000000000000200000001000000"


def _body(hex_frame: str) -> bytes:
    return bytes.fromhex(hex_frame)[4:]


def test_joint_position_golden_decodes_to_stated_degrees() -> None:
    raw = bytes.fromhex(JOINT_POSITION_HEX)
    assert len(raw) == 60 and struct.unpack_from("<i", raw)[0] == JOINT_POSITION_LENGTH == 56
    msg = decode_message(_body(JOINT_POSITION_HEX))
    assert isinstance(msg, JointPosition)
    assert msg.header == Header(MSG_JOINT_POSITION, 1, 0)
    assert msg.sequence == 0
    deg = [math.degrees(v) for v in msg.joints_rad[:6]]
    assert deg == pytest.approx(JOINT_POSITION_DEG, abs=1e-6)
    assert msg.joints_rad[6:] == (0.0, 0.0, 0.0, 0.0)


def test_joint_position_golden_reencodes_to_same_bytes() -> None:
    msg = decode_message(_body(JOINT_POSITION_HEX))
    assert encode(msg).hex() == JOINT_POSITION_HEX
    # and encoding from degrees the way the VAL3 driver does gives the same bytes
    q = [math.radians(d) for d in (10, 20, 30, 40, 50, 60)]
    assert encode_joint_position(q).hex() == JOINT_POSITION_HEX


def test_status_golden_decodes_and_reencodes() -> None:
    msg = decode_message(_body(STATUS_HEX))
    assert isinstance(msg, Status)
    assert msg.header == Header(MSG_STATUS, 1, 0)
    assert (msg.drives_powered, msg.e_stopped, msg.error_code, msg.in_error) == (1, 0, 0, 0)
    assert (msg.in_motion, msg.mode, msg.motion_possible) == (0, 2, 1)
    assert encode(msg).hex() == STATUS_HEX


def test_joint_feedback_round_trip_and_layout() -> None:
    msg = JointFeedback(0, 0x2, 1.5, (0.1, 0.2, 0.3, 0.4, 0.5, 0.6), (0.0,) * 6, (0.0,) * 6)
    raw = encode(msg)
    assert len(raw) == 148 and struct.unpack_from("<i", raw)[0] == JOINT_FEEDBACK_LENGTH
    # industrial_core joint_feedback.h wire offsets: robot_id 16, valid_fields 20, time 24, positions 28
    assert struct.unpack_from("<iif", raw, 16) == (0, 2, 1.5)
    assert struct.unpack_from("<f", raw, 28)[0] == pytest.approx(0.1)
    back = decode_message(raw[4:])
    assert isinstance(back, JointFeedback) and back.header.msg_type == MSG_JOINT_FEEDBACK
    assert back.positions_rad[:6] == pytest.approx((0.1, 0.2, 0.3, 0.4, 0.5, 0.6), abs=1e-7)
    assert encode(back) == raw


def test_unknown_type_is_kept_by_length_and_reencodes() -> None:
    raw = struct.pack("<4i", 16, 1600, 1, 0) + b"\x01\x02\x03\x04"
    msg = decode_message(raw[4:])
    assert isinstance(msg, Unknown) and msg.header.msg_type == 1600 and msg.body == b"\x01\x02\x03\x04"
    assert encode(msg) == raw


def test_known_type_with_wrong_body_size_is_a_protocol_error() -> None:
    body = _body(JOINT_POSITION_HEX)[:-4]
    with pytest.raises(ProtocolError, match="JOINT_POSITION"):
        decode_message(body)


def test_frame_shorter_than_header_is_a_protocol_error() -> None:
    with pytest.raises(ProtocolError, match="header"):
        decode_message(b"\x00" * 8)


def _stream() -> bytes:
    unknown = struct.pack("<4i", 16, 1600, 1, 0) + b"abcd"
    return (
        bytes.fromhex(JOINT_POSITION_HEX)
        + bytes.fromhex(STATUS_HEX)
        + unknown
        + bytes.fromhex(JOINT_POSITION_HEX)
    )


def test_reassembly_at_every_split_point() -> None:
    data = _stream()
    expected = FrameReassembler().feed(data)
    assert len(expected) == 4
    for cut in range(1, len(data)):
        r = FrameReassembler()
        frames = r.feed(data[:cut]) + r.feed(data[cut:])
        assert frames == expected, cut
        assert r.buffered == 0


def test_reassembly_byte_by_byte() -> None:
    data = _stream()
    r = FrameReassembler()
    frames = [f for b in data for f in r.feed(bytes([b]))]
    assert [decode_message(f).header.msg_type for f in frames] == [10, 13, 1600, 10]


def test_reassembly_of_val3_three_write_pattern() -> None:
    raw = bytes.fromhex(JOINT_POSITION_HEX)
    r = FrameReassembler()
    assert r.feed(raw[:4]) == [] and r.feed(raw[4:16]) == []
    assert r.feed(raw[16:]) == [raw[4:]]


@pytest.mark.parametrize("length", [MIN_LENGTH - 1, 0, -1, MAX_LENGTH + 1, 0x7FFFFFFF, -0x80000000])
def test_insane_length_prefix_is_rejected(length: int) -> None:
    r = FrameReassembler()
    with pytest.raises(ProtocolError, match="length prefix"):
        r.feed(struct.pack("<i", length))
    assert r.buffered == 0


def test_oversized_prefix_is_rejected_without_allocating_it() -> None:
    r = FrameReassembler()
    tracemalloc.start()
    try:
        with pytest.raises(ProtocolError):
            r.feed(struct.pack("<i", 0x7FFFFFFF) + b"\x00" * 16)
        _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    assert peak < 64 * 1024, f"peak allocation {peak} bytes while rejecting a 2 GiB prefix"


def test_bounds_are_sane() -> None:
    assert MIN_LENGTH == 12  # a bare header
    assert JOINT_FEEDBACK_LENGTH + 4 < MAX_LENGTH <= 64 * 1024
