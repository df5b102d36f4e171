"""ERNI objects as ROS 2 messages: the parts that are plain arithmetic."""

from __future__ import annotations

import math
from fractions import Fraction

from hypothesis import given
from hypothesis import strategies as st

from erni.ros2_messages import stamp_ns_of


@given(st.floats(min_value=0.0, max_value=4e9, allow_nan=False))
def test_a_stamp_in_nanoseconds_is_within_the_floats_own_resolution(seconds: float) -> None:
    exact = Fraction(seconds) * 10**9  # the float's exact value, in ns
    assert abs(stamp_ns_of(seconds) - exact) <= Fraction(math.ulp(seconds)) * 10**9 / 2 + Fraction(1, 2)


def test_a_time_written_in_decimals_keeps_its_digits() -> None:
    assert stamp_ns_of(1750000001.1) == 1_750_000_001_100_000_000
    assert stamp_ns_of(1764215000.123457) == 1_764_215_000_123_457_000  # seconds * 1e9: ..._123_457_024
    assert stamp_ns_of(0.5) == 500_000_000
