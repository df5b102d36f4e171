"""Scheduling, wake-ups, hand-offs, isolation and shutdown of the agent host."""

from __future__ import annotations

import logging
import queue
import threading
import time

import pytest

from erni.blackboard import Agent, Plugin
from erni.blackboard.testing import wait_until
from erni.testing import ManualClock
from tests.core.helpers import Item, Probe, Recorder, Sleeper, scheduler_idle, timers_caught_up


def test_execute_runs_only_with_news():
    agent = Agent("s")
    rec = agent.add_plugin(Recorder)
    agent.start()
    try:
        with agent.transaction() as tx:
            tx.add(Item())
        wait_until(lambda: rec.runs == 1)
        agent.scheduler.signal(rec)  # a signal with no delta and no wake-up
        wait_until(lambda: scheduler_idle(rec))
        assert rec.runs == 1
    finally:
        agent.stop()


def test_plugin_never_runs_concurrently_and_signals_coalesce():
    agent = Agent("s", workers=4)
    sleeper = agent.add_plugin(Sleeper)
    agent.start()
    try:
        sleeper.gate.clear()
        sleeper.wake()
        wait_until(lambda: sleeper.active == 1)
        for _ in range(20):  # 20 signals during one run ...
            sleeper.wake()
        sleeper.gate.set()
        wait_until(lambda: sleeper.count == 2 and sleeper.active == 0)
        wait_until(lambda: scheduler_idle(sleeper))
        assert sleeper.count == 2, "... cause exactly one more run"
        assert sleeper.max_active == 1
    finally:
        agent.stop()


def test_a_plugin_signalled_during_its_run_runs_again_on_the_same_worker():
    """A run that publishes what its own plugin subscribes to (a transport applying the statuses it
    receives while a client watches them) signals that plugin again. The worker that ran it runs
    it once more at once: through the queue another worker would wake for it, and the interpreter
    lock would pass between them, for every received frame."""
    agent = Agent("again", workers=4)
    sleeper = agent.add_plugin(Sleeper)
    threads: list[str] = []

    def execute() -> None:
        threads.append(threading.current_thread().name)
        if len(threads) < 20:
            sleeper.wake()  # signalled during its own run
    sleeper.execute = execute  # type: ignore[method-assign]
    queued = []

    class Counting(queue.SimpleQueue):  # type: ignore[type-arg]
        def put(self, item, block=True, timeout=None):  # type: ignore[no-untyped-def]
            queued.append(item)
            super().put(item, block, timeout)
    agent.scheduler._queue = Counting()
    agent.start()
    try:
        sleeper.wake()
        wait_until(lambda: len(threads) == 20)
        wait_until(lambda: scheduler_idle(sleeper))
        assert len(threads) == 20 and len(set(threads)) == 1, threads
        assert sleeper.runs == 20
        assert queued == [sleeper]  # the first signal only: no worker was woken for the other 19
    finally:
        agent.stop()


def test_worker_pool_runs_plugins_in_parallel():
    agent = Agent("p", workers=3)
    sleepers = [agent.add_plugin(Sleeper, name=f"s{i}") for i in range(3)]
    barrier = threading.Barrier(3, timeout=5)
    for s in sleepers:
        s.execute = lambda: barrier.wait()  # type: ignore[method-assign]
    agent.start()
    try:
        for s in sleepers:
            s.wake()
        wait_until(lambda: all(s.runs == 1 for s in sleepers))
        assert all(s.failures == 0 for s in sleepers), "three plugins met at the barrier at once"
    finally:
        agent.stop()


def test_wake_in_and_wake_every():
    clock = ManualClock()
    agent = Agent("w", clock=clock)
    once, periodic = agent.add_plugin(Sleeper, name="once"), agent.add_plugin(Sleeper, name="periodic")
    probe = agent.add_plugin(Probe, name="probe")
    agent.start()
    try:
        once.wake_in(0.05)
        handle = periodic.wake_every(0.02)
        for k in range(1, 6):  # a little over a period each time: one run each
            clock.advance(0.021)
            wait_until(lambda k=k: periodic.count == k and scheduler_idle(periodic))
        assert once.count == 1  # 0.105 s: past its 0.05 s
        handle.cancel()
        clock.advance(1.0)  # fifty periods more
        timers_caught_up(probe)
        wait_until(lambda: scheduler_idle(periodic))
        assert periodic.count == 5, "a cancelled wake_every fires no more"
        assert once.count == 1, "wake_in fires once"
        with pytest.raises(ValueError, match="period > 0"):
            periodic.wake_every(0)
    finally:
        agent.stop()


def test_later_runs_inside_the_next_execute_and_can_publish():
    agent = Agent("l")
    rec = agent.add_plugin(Recorder)
    agent.start()
    try:
        ran_in: list[str] = []

        def work():
            ran_in.append(threading.current_thread().name)
            rec.add(Item(value=42))  # publishing is allowed: we are inside its transaction

        threading.Thread(target=lambda: rec.later(work), name="outside").start()
        wait_until(lambda: agent.query(Item))
        assert ran_in and ran_in[0].startswith("erni-l-worker")
        assert [o.value for o in agent.query(Item)] == [42]
    finally:
        agent.stop()


def test_exceptions_are_isolated_and_logged_with_names(caplog):
    class BadSetup(Plugin):
        def setup(self):
            raise RuntimeError("no robot here")

    class BadExecute(Recorder):
        def execute(self):
            self.add(Item(value=99))
            raise ValueError("bad math")

    agent = Agent("iso")
    agent.add_plugin(BadSetup)
    bad = agent.add_plugin(BadExecute)
    good = agent.add_plugin(Recorder, name="good")
    with caplog.at_level(logging.ERROR):
        agent.start()
        try:
            with agent.transaction() as tx:
                tx.add(Item(value=1))
            wait_until(lambda: good.runs >= 1 and bad.failures >= 1)
        finally:
            agent.stop()
    text = caplog.text
    assert "setup() failed in agent iso, plugin BadSetup" in text
    assert "execute() failed in agent iso, plugin BadExecute" in text
    assert "bad math" in text and "no robot here" in text
    assert [o.value for o in agent.query(Item)] == [1], "the failed run published nothing"
    assert [o.value for o in good.all("added")] == [1]


def test_slow_plugin_is_reported(caplog):
    agent = Agent("slow", slow_plugin_seconds=0.05)
    sleeper = agent.add_plugin(Sleeper)
    with caplog.at_level(logging.WARNING):
        agent.start()
        try:
            sleeper.gate.clear()  # its run lasts until the warning is seen
            sleeper.wake()
            wait_until(lambda: "has been running for" in caplog.text, timeout=3)
        finally:
            sleeper.gate.set()
            agent.stop()
    assert "plugin Sleeper of agent slow" in caplog.text


def test_stop_wakes_every_thread_and_returns_once_they_are_joined():
    """stop() wakes each thread of the agent out of its wait: the workers from their queue, the
    timer thread from a wait for its next look (the slow-run limit, 120 s here) and the retention
    sweeper from its 10 s period. Given a 30 s timeout it returns with every one joined, long
    before that timeout: a thread left to its own wait would hold it there and still be running."""
    agent = Agent("stop", workers=8, slow_plugin_seconds=120.0)
    for i in range(16):
        agent.add_plugin(Recorder, name=f"r{i}").kind = Item
    agent.start()
    with agent.transaction() as tx:
        for i in range(100):
            tx.add(Item(value=i))
    names = {t.name for t in threading.enumerate() if t.name.startswith("erni-stop")}
    assert len(names) == 10  # 8 workers, the timer thread and the retention sweeper
    t0 = time.monotonic()
    agent.stop(timeout=30.0)
    assert not [t for t in threading.enumerate() if t.name.startswith("erni-stop")]
    assert time.monotonic() - t0 < 20.0  # all joined, not given up at the timeout


def test_teardown_is_called_outside_transactions():
    calls = []

    class Owner(Plugin):
        def teardown(self):
            calls.append("teardown")
            with self.transaction():
                self.add(Item(value=5))  # may still publish in a transaction of its own

    agent = Agent("td")
    agent.add_plugin(Owner)
    agent.start()
    agent.stop()
    assert calls == ["teardown"] and len(agent.query(Item)) == 1


def test_signals_during_setup_run_execute_only_after_setup_committed():
    order: list[str] = []

    class Slow(Plugin):
        def setup(self):
            self.sub = self.subscribe(Item)
            self.wake()  # e.g. a socket thread started here hands work over at once
            # held for one run after setup (or, wrongly, run by another worker now: then wait for it)
            wait_until(lambda: self._dirty or "execute" in order)
            self.add(Item(value=1))
            order.append("setup")

        def execute(self):
            order.append("execute")
            assert self.query(Item), "setup's publications are visible to the first run"

    agent = Agent("su", workers=2)
    plugin = agent.add_plugin(Slow)
    agent.start()
    try:
        wait_until(lambda: plugin.runs >= 1)
        assert order[0] == "setup" and plugin.failures == 0
    finally:
        agent.stop()


def test_a_failing_later_hand_off_drops_only_its_own_publications(caplog):
    agent = Agent("lt")
    rec = agent.add_plugin(Recorder)
    agent.start()
    try:
        def good(v):
            return lambda: rec.add(Item(value=v))

        def bad():
            rec.add(Item(value=99))
            raise RuntimeError("bad frame")

        for fn in (good(1), bad, good(2)):
            rec.later(fn)
        wait_until(lambda: len(agent.query(Item)) == 2)
        assert sorted(o.value for o in agent.query(Item)) == [1, 2]
        assert rec.failures == 1 and "bad frame" in caplog.text
    finally:
        agent.stop()


def test_a_setup_within_the_limit_is_never_reported_as_slow(caplog):
    """Timed by the agent's clock, which only the test moves: a loaded machine cannot make the
    setup longer than it is."""
    clock = ManualClock()

    class Careful(Plugin):
        def setup(self):
            clock.advance(0.9)  # 0.9 s of the agent's clock into its setup: within the 1 s limit
            agent.scheduler.check_slow()  # the slow-plugin watch looks now

    agent = Agent("quiet", slow_plugin_seconds=1.0, clock=clock)
    agent.add_plugin(Careful)
    probe = agent.add_plugin(Probe, name="probe")
    with caplog.at_level("WARNING"):
        agent.start()
        clock.advance(5.0)  # long past the limit, with the setup over: the watch looks again
        timers_caught_up(probe)
        agent.stop()
    assert [r.getMessage() for r in caplog.records if "has been running" in r.getMessage()] == []


def test_a_slow_setup_is_reported_with_its_own_duration(caplog):
    """The report comes while the setup still runs and gives how long it has run, on the agent's
    clock: 0.5 s of it pass in the setup before the watch may look, 0.3 s more after."""
    clock = ManualClock()

    class Sluggish(Plugin):
        def setup(self):
            clock.advance(0.5)  # past the 0.3 s limit: the watch looks and reports it, running
            wait_until(lambda: "has been running" in caplog.text, timeout=30)
            clock.advance(0.3)

    agent = Agent("slow", slow_plugin_seconds=0.3, clock=clock)
    agent.add_plugin(Sluggish)
    with caplog.at_level("WARNING"):
        agent.start()
        agent.stop()
    (line,) = [r.getMessage() for r in caplog.records if "has been running" in r.getMessage()]
    assert line == "plugin Sluggish of agent slow has been running for 0.5 s (limit 0.3 s)"
