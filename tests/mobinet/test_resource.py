"""MobiNetResource scheduling, isolated from SNMP with a scripted NetworkSource."""

from __future__ import annotations

import asyncio
import logging
import threading
import time

from erni.blackboard import Position
from erni.blackboard.testing import wait_until
from erni.plugins.mobinet.resource import (
    MobiNetResource,
    NetView,
    NetworkSource,
    SourceError,
)


class ScriptedSource:
    """A NetworkSource whose reads and writes take `delay` s and fail while `failing`."""

    def __init__(self, delay: float = 0.0) -> None:
        self.delay = delay
        self.failing = False
        self.reads: list[frozenset[str]] = []
        self.writes: list[Position] = []
        self.done = 0  # reads and writes that came to their end (not abandoned)
        self.closed = False

    async def read(self, parts):
        self.reads.append(parts)
        await asyncio.sleep(self.delay)
        self.done += 1
        if self.failing:
            raise SourceError("scripted failure")
        return NetView(node="me", address="10.0.0.1")

    async def write_position(self, position):
        await asyncio.sleep(self.delay)
        self.done += 1
        if self.failing:
            raise SourceError("scripted write failure")
        self.writes.append(position)

    async def aclose(self):
        self.closed = True


class Recorder:
    def __init__(self) -> None:
        self.lock = threading.Lock()
        self.got: list[tuple[str, NetView | None, str]] = []

    def __call__(self, key, view, error):
        with self.lock:
            self.got.append((key, view, error))

    def keys(self):
        with self.lock:
            return [k for k, _, _ in self.got]


def make(source, **kw):
    rec = Recorder()
    res = MobiNetResource(lambda: source, rec, logging.getLogger("test.mobinet"), **kw).start()
    return res, rec


def test_scripted_source_satisfies_the_protocol():
    assert isinstance(ScriptedSource(), NetworkSource)


def test_watches_at_the_same_rate_share_reads_and_unwatch_stops_delivery():
    src = ScriptedSource()
    res, rec = make(src)
    try:
        res.watch("a", frozenset({"neighbors"}), 50.0)
        res.watch("b", frozenset({"topology"}), 50.0)
        wait_until(lambda: rec.keys().count("a") >= 5 and rec.keys().count("b") >= 5)
        assert frozenset({"neighbors", "topology"}) in src.reads      # one read served both
        assert len(src.reads) < len(rec.keys())
        res.unwatch("a")
        wait_until(lambda: res.watching() == ["b"])
        n = rec.keys().count("a")
        wait_until(lambda: rec.keys().count("b") >= 15)
        assert rec.keys().count("a") == n
    finally:
        res.close()
    assert src.closed


def test_calls_never_wait_for_a_slow_source_and_close_abandons_it():
    """Every read and write hangs for an hour: calls return while one is in flight, and close()
    abandons it, its thread ended (the bounds are for progress only: waiting would take an hour)."""
    src = ScriptedSource(delay=3600.0)
    res, rec = make(src)
    try:
        res.watch("a", frozenset({"routes"}), 10.0)
        wait_until(lambda: src.reads)
        t0 = time.monotonic()
        res.watch("b", frozenset({"topology"}), 10.0)
        res.write_position(Position(x=1, y=2))
        res.unwatch("a")
        assert time.monotonic() - t0 < 20.0
        assert src.done == 0                          # returned with the read still hung
    finally:
        thread = res._thread
        t0 = time.monotonic()
        res.close(timeout=30.0)
        assert time.monotonic() - t0 < 20.0           # did not wait for the hung read ...
        assert thread is not None and not thread.is_alive()  # ... and did not leave it running
    assert rec.got == [] and src.done == 0


def test_failures_are_delivered_and_logged_once_per_interval(caplog):
    caplog.set_level(logging.WARNING, logger="test.mobinet")
    src = ScriptedSource()
    src.failing = True
    res, rec = make(src, log_interval=60.0)
    try:
        res.watch("a", frozenset({"neighbors"}), 100.0)
        wait_until(lambda: len(rec.got) >= 5)
        assert all(view is None and err == "scripted failure" for _, view, err in rec.got)
        src.failing = False
        wait_until(lambda: rec.got[-1][1] is not None and rec.got[-1][2] == "")
    finally:
        res.close()
    lines = [r.getMessage() for r in caplog.records]
    assert lines == ["network read failed: scripted failure"]


def test_only_the_latest_pose_is_written_and_failed_writes_are_retried():
    src = ScriptedSource(delay=0.05)
    res, _ = make(src, retry_delay=0.05)
    try:
        for i in range(20):                              # faster than the source can write
            res.write_position(Position(x=float(i), y=0.0))
        wait_until(lambda: src.writes and src.writes[-1].x == 19.0)
        assert len(src.writes) < 20
        src.failing = True
        res.write_position(Position(x=42.0, y=0.0))
        wait_until(lambda: res.stats["write_errors"] >= 2)   # retried without a new pose
        src.failing = False
        wait_until(lambda: src.writes[-1].x == 42.0)
    finally:
        res.close()


def looked_again(res: MobiNetResource, rec: Recorder, key: str) -> list[str]:
    """Wait until the poller has read for a new watch `key`, due now, and return the keys delivered
    before it: a watch due by now joins that read and is delivered first."""
    res.watch(key, frozenset({"links"}), 0.001)
    wait_until(lambda: key in rec.keys(), timeout=30)
    res.unwatch(key)
    return rec.keys()[:rec.keys().index(key)]


def test_watches_fall_due_on_the_injected_clock():
    """A watch of 1 Hz is read when the resource's clock has moved a second, not when a second of
    wall time has passed (erni.testing.ManualClock, as for an agent)."""
    from erni.testing import ManualClock

    clock = ManualClock()
    src, rec = ScriptedSource(), Recorder()
    res = MobiNetResource(lambda: src, rec, logging.getLogger("test"), clock=clock).start()
    try:
        res.watch("w", frozenset({"links"}), 1.0)
        wait_until(lambda: len(src.reads) == 1, timeout=30)  # a new watch is read at once (the clock stands)
        assert looked_again(res, rec, "probe1") == ["w"]  # the poller looked again: the clock has not moved
        clock.advance(0.5)
        assert looked_again(res, rec, "probe2") == ["w", "probe1"]  # half a period: not due
        clock.advance(0.6)
        wait_until(lambda: rec.keys().count("w") == 2, timeout=30)
        assert rec.keys() == ["w", "probe1", "probe2", "w"] and len(src.reads) == 4
    finally:
        res.close()


def test_a_watch_added_later_falls_into_the_pace_of_a_faster_one():
    """A 1 Hz watch added between two reads of a 2 Hz one is read once at once, then only with the
    2 Hz watch (every other read of it): the source is read twice a second, not three times (ManualClock)."""
    from erni.testing import ManualClock

    clock = ManualClock()
    src, rec = ScriptedSource(), Recorder()
    res = MobiNetResource(lambda: src, rec, logging.getLogger("test"), clock=clock).start()
    try:
        res.watch("fast", frozenset({"neighbors"}), 2.0)
        wait_until(lambda: len(src.reads) == 1, timeout=30)
        clock.advance(0.2)
        res.watch("slow", frozenset({"topology"}), 1.0)
        wait_until(lambda: len(src.reads) == 2, timeout=30)  # a new watch is read at once
        assert src.reads[1] == frozenset({"topology"})
        # 4 s in steps of 0.25 s, the poller made to look at each (a watch due within a fifth of its
        # period joins that look): unaligned, the slow watch would be read at 1.2 s, 2.2 s ... alone
        for i in range(16):
            clock.advance(0.25)
            looked_again(res, rec, f"probe{i}")
        later = src.reads[2:]
        slow = [r for r in later if "topology" in r]
        assert slow and all("neighbors" in r for r in slow)  # never read on its own again
        assert 3 <= len(slow) <= 5 and 7 <= sum("neighbors" in r for r in later) <= 9
    finally:
        res.close()
