"""The one place ERNI's runtime reads time.

Two readings, one object: calling a clock gives seconds on a monotonic clock (durations, deadlines,
timers, rate limits); `clock.wall()` gives seconds since the epoch (stamps that travel between
agents or into files: a Pose's stamp, a task's creation, a result's stamp, a log line).

Every agent has one (`Agent(clock=...)`, `SYSTEM` by default) and gives it to its plugins
(`self.clock` in a plugin) and its transport; a test gives its own (`erni.testing.ManualClock`) and
owns both readings. Code with no agent at hand (a model's default stamp) reads `wall()` and
`monotonic()` here, the process's clock. Nothing else in blackboard/, transport/ or plugins/ reads
`time.time`, `time.monotonic` or their kin directly (tests/test_clock_reads.py counts).
"""

from __future__ import annotations

import time
from collections.abc import Callable
from typing import Protocol, runtime_checkable

__all__ = ["SYSTEM", "Clock", "SystemClock", "as_clock", "monotonic", "wall"]


@runtime_checkable
class Clock(Protocol):
    """Monotonic seconds when called; seconds since the epoch from `wall()`."""

    def __call__(self) -> float: ...

    def wall(self) -> float: ...


class SystemClock:
    """The machine's clocks: `time.monotonic` and `time.time`."""

    def __call__(self) -> float:
        return time.monotonic()

    def wall(self) -> float:
        return time.time()

    def __repr__(self) -> str:
        return "SYSTEM"


SYSTEM: Clock = SystemClock()
"""The process's clock: what an agent uses unless given another."""


def monotonic() -> float:
    """Seconds on the process's monotonic clock (for code with no agent at hand)."""
    return SYSTEM()


def wall() -> float:
    """Seconds since the epoch on the process's clock (a model's default stamp)."""
    return SYSTEM.wall()


class _Wrapped:
    """A bare monotonic callable given where a clock is expected: its wall reading is the process's,
    moved by as much as the callable has moved since it was wrapped."""

    def __init__(self, fn: Callable[[], float]) -> None:
        self._fn = fn
        self._offset = time.time() - fn()
        watch = getattr(fn, "on_advance", None)
        if callable(watch):
            self.on_advance = watch

    def __call__(self) -> float:
        return self._fn()

    def wall(self) -> float:
        return self._fn() + self._offset


def as_clock(clock: Clock | Callable[[], float]) -> Clock:
    """`clock` as a `Clock`: a clock as it is; a bare callable of monotonic seconds wrapped, its wall
    reading following it from the process's wall time now."""
    if isinstance(clock, Clock):
        return clock
    return _Wrapped(clock)
