"""The robot-side unit checks (issue 40 item 1): radians in a degrees field, metres in a millimetre
field and a rod beyond the arm's reach are named; real mounts pass."""

from __future__ import annotations

import math

from hypothesis import given
from hypothesis import strategies as st

from registration.model.mount_checks import (
    MAX_ROD_LENGTH_MM,
    radian_like_rpy,
    rod_length_problems,
    rpy_problems,
)

HALF_MM = 35.0  # the bai2018 cube's smallest half-size


@given(st.lists(st.integers(-8, 8), min_size=3, max_size=3).filter(any), st.floats(-0.0015, 0.0015))
def test_multiples_of_a_quarter_turn_in_radians_are_named(ks: list[int], jitter: float) -> None:
    rpy = [k * math.pi / 4 + (jitter if k else 0.0) for k in ks]
    assert radian_like_rpy(rpy)
    (msg,) = rpy_problems("robot.tool0_from_phantom", rpy)
    assert "looks like radians" in msg and "robot.tool0_from_phantom.rpy_deg" in msg


@given(st.lists(st.integers(-360, 360), min_size=3, max_size=3))
def test_whole_degree_mounts_pass(degrees: list[int]) -> None:
    """Integer degrees never read as radians (no integer is within 0.002 of k·π/4, k ≠ 0)."""
    assert rpy_problems("robot.tool0_from_phantom", [float(d) for d in degrees]) == []


def test_one_ordinary_degree_value_clears_the_suspicion() -> None:
    assert not radian_like_rpy([3.14159, 12.5, 0.0])
    assert not radian_like_rpy([0.0, 0.0, 0.0])
    assert radian_like_rpy([3.14, 0.0, 0.0])  # pi typed short


def test_rod_lengths() -> None:
    assert rod_length_problems("r", [0.0, 0.0, 200.0], HALF_MM) == []
    assert rod_length_problems("r", [0.0, 0.0, MAX_ROD_LENGTH_MM], HALF_MM) == []
    (metres,) = rod_length_problems("r", [0.0, 0.0, 0.2], HALF_MM)
    assert "looks like metres" in metres and "200.0" in metres
    (inside,) = rod_length_problems("r", [0.0, 0.0, 20.0], HALF_MM)
    assert "inside the phantom" in inside and "looks like metres" not in inside
    (far,) = rod_length_problems("r", [0.0, 0.0, MAX_ROD_LENGTH_MM + 1.0], HALF_MM)
    assert "reach" in far
