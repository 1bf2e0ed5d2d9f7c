"""Golden lines for the project's serial joint protocol (docs/robot-link.md)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from drivers.base import RobotStatus
from drivers.errors import ProtocolError
from drivers.serial_link import (
    MAX_LINE_BYTES,
    JointLine,
    LineSplitter,
    StatusLine,
    checksum,
    decode_line,
    encode_joint_line,
    encode_status_line,
)

# q = 10, 20, 30, 40, 50, 60 deg in radians, seq 7.  Checksum = XOR of the bytes between '$' and '*'.
JOINT_LINE = b"$J,7,0.174532925,0.34906585,0.523598776,0.698131701,0.872664626,1.04719755*5B\r\n"
STATUS_LINE = b"$S,3,1,0,0,0,0,2,1*52\r\n"


def test_checksum_is_xor_of_payload() -> None:
    payload = JOINT_LINE[1 : JOINT_LINE.index(b"*")]
    x = 0
    for b in payload:
        x ^= b
    assert checksum(payload) == x == int(JOINT_LINE[-4:-2], 16)


def test_joint_line_golden_encode_and_decode() -> None:
    q = [math.radians(d) for d in (10, 20, 30, 40, 50, 60)]
    assert encode_joint_line(7, q) == JOINT_LINE
    msg = decode_line(JOINT_LINE)
    assert isinstance(msg, JointLine) and msg.seq == 7
    assert [math.degrees(v) for v in msg.joints_rad] == pytest.approx([10, 20, 30, 40, 50, 60], abs=1e-6)


def test_status_line_golden_encode_and_decode() -> None:
    st = RobotStatus(1, 0, 0, 0, 0, 2, 1, 0.0)
    assert encode_status_line(3, st) == STATUS_LINE
    msg = decode_line(STATUS_LINE)
    assert msg == StatusLine(3, 1, 0, 0, 0, 0, 2, 1)


def test_float32_values_round_trip_exactly() -> None:
    rng = np.random.default_rng(0)
    q32 = rng.uniform(-4.7, 4.7, size=(200, 6)).astype(np.float32)
    for row in q32:
        msg = decode_line(encode_joint_line(0, [float(v) for v in row]))
        assert isinstance(msg, JointLine)
        assert np.array_equal(np.asarray(msg.joints_rad, dtype=np.float32), row)


def test_lowercase_checksum_accepted() -> None:
    assert decode_line(JOINT_LINE.replace(b"*5B", b"*5b")) == decode_line(JOINT_LINE)


def test_bad_checksum_rejected() -> None:
    with pytest.raises(ProtocolError, match="checksum mismatch"):
        decode_line(JOINT_LINE.replace(b"*5B", b"*5C"))


def test_flipped_payload_bit_rejected() -> None:
    bad = JOINT_LINE.replace(b"0.174532925", b"0.174532924")
    with pytest.raises(ProtocolError, match="checksum"):
        decode_line(bad)


def test_nan_joint_rejected_even_with_valid_checksum() -> None:
    line = encode_joint_line(1, [math.nan, 0, 0, 0, 0, 0])
    with pytest.raises(ProtocolError, match="non-finite"):
        decode_line(line)


def test_wrong_field_count_rejected() -> None:
    with pytest.raises(ProtocolError, match="joint fields"):
        decode_line(encode_joint_line(1, [0.0] * 5))


@pytest.mark.parametrize("line", [b"J,1,2*00\r\n", b"$J,1,2\r\n", b"garbage\r\n", b"$*\r\n", b"$J,1*ZZ\r\n"])
def test_malformed_lines_rejected(line: bytes) -> None:
    with pytest.raises(ProtocolError):
        decode_line(line)


def test_unknown_sentence_is_skipped() -> None:
    p = b"X,1,2"
    assert decode_line(b"$" + p + b"*" + f"{checksum(p):02X}".encode() + b"\r\n") is None


def test_splitter_handles_splits_and_overlong_garbage() -> None:
    s = LineSplitter()
    data = JOINT_LINE + STATUS_LINE
    lines = [ln for b in data for ln in s.feed(bytes([b]))]
    assert lines == [JOINT_LINE, STATUS_LINE]
    s.feed(b"\xff" * (MAX_LINE_BYTES + 1))
    assert s.overflows == 1
    assert s.feed(b"tail of garbage\r\n" + JOINT_LINE) == [b"tail of garbage\r\n", JOINT_LINE]
