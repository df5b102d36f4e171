"""ERNI objects as ROS 2 messages: the parts that are plain arithmetic."""

from __future__ import annotations

from fractions import Fraction

from hypothesis import given
from hypothesis import strategies as st

from erni.plugins.ros2.messages import stamp_ns_of


@given(st.floats(min_value=0.0, max_value=4e9, allow_nan=False))
def test_a_stamp_in_nanoseconds_is_the_floats_own_value_to_the_nanosecond(seconds: float) -> None:
    exact = Fraction(seconds) * 10**9  # the float's exact value, in ns
    assert abs(stamp_ns_of(seconds) - exact) <= Fraction(1, 2)


def test_a_stamp_of_today_is_not_rounded_to_256_ns() -> None:
    seconds = 1764215000.123456789  # the float nearest: ...123456716537...
    assert stamp_ns_of(seconds) == 1764215000123456717
