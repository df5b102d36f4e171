"""Helpers for plugin authors' tests: wait for a condition without sleeping blindly."""

from __future__ import annotations

import time
from collections.abc import Callable
from typing import TypeVar

from erni.blackboard.clock import monotonic

T = TypeVar("T")


def wait_until(condition: Callable[[], T], timeout: float = 5.0, interval: float = 0.005,
               message: str | None = None) -> T:
    """Poll `condition()` until it returns a truthy value and return it; AssertionError on timeout."""
    deadline = monotonic() + timeout
    while True:
        value = condition()
        if value:
            return value
        if monotonic() >= deadline:
            raise AssertionError(message or f"condition not met within {timeout} s: {condition}")
        time.sleep(interval)


__all__ = ["wait_until"]
