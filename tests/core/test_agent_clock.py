"""The agent's clock is injectable: wake-ups, the slow-run watch and task retention follow a test's
ManualClock, so a test of a plugin's timing advances time instead of sleeping through it."""

from __future__ import annotations

import logging
import threading
import time

import pytest

from erni.blackboard import Plugin, Task, TaskState
from erni.blackboard.errors import UsageError
from erni.blackboard.tasks import AllocationResult
from erni.blackboard.testing import wait_until
from erni.testing import ManualClock, agent_with, post_task
from tests.core.helpers import Probe, scheduler_idle, timers_caught_up


class Ticker(Plugin):
    """Wakes every 5 s of the agent's clock and counts it."""

    def setup(self) -> None:
        self.ticks = 0
        self.ticked = threading.Event()
        self.wake_every(5.0)

    def execute(self) -> None:
        self.ticks += 1
        self.ticked.set()


def ticks_after(plugin: Ticker, probe: Probe, clock: ManualClock, seconds: float) -> int:
    clock.advance(seconds)
    timers_caught_up(probe)  # what is due by now has been handed to the ticker ...
    wait_until(lambda: scheduler_idle(plugin))  # ... and run
    return plugin.ticks


def test_wake_ups_follow_the_injected_clock_not_the_wall_clock():
    clock = ManualClock()
    agent = agent_with(Ticker, clock=clock)
    probe = agent.add_plugin(Probe, name="probe")
    with agent:
        ticker = agent.plugins[0]
        assert isinstance(ticker, Ticker)
        wait_until(lambda: scheduler_idle(ticker))
        base = ticker.ticks  # setup's own run
        assert ticks_after(ticker, probe, clock, 4.9) == base  # 4.9 s on the agent's clock: not due
        assert ticks_after(ticker, probe, clock, 0.2) == base + 1  # 5.1 s: due, run without waiting 5 s
        assert ticks_after(ticker, probe, clock, 5.0) == base + 2
        assert ticks_after(ticker, probe, clock, 0.0) == base + 2  # the timers going round moves nothing


class Stuck(Plugin):
    """Its run waits for the test: a plugin that takes long."""

    def setup(self) -> None:
        self.release = threading.Event()
        self.running = threading.Event()
        self.sub = self.subscribe(Task)

    def execute(self) -> None:
        if self.sub.added:
            self.running.set()
            self.release.wait(5)


def test_a_slow_run_is_reported_by_the_agent_s_clock(caplog):
    clock = ManualClock()
    agent = agent_with(Stuck, clock=clock, plugin_name="stuck", workers=2)
    probe = agent.add_plugin(Probe, name="probe")  # runs on the other worker
    with agent, caplog.at_level(logging.WARNING):
        stuck = agent.plugins[0]
        assert isinstance(stuck, Stuck)
        post_task(agent, "BotMotion", "stop")
        assert stuck.running.wait(2)
        clock.advance(0.9)
        timers_caught_up(probe)  # the slow-run watch has looked at 0.9 s
        assert "has been running" not in caplog.text  # within the 1 s limit of the agent's clock
        clock.advance(0.6)  # past the 1 s limit on the agent's clock
        try:
            wait_until(lambda: "has been running" in caplog.text, timeout=2)
        finally:
            stuck.release.set()
    assert "plugin stuck of agent robot1 has been running for 1.5 s" in caplog.text


def test_final_tasks_are_removed_after_the_retention_on_the_agent_s_clock():
    clock = ManualClock()
    agent = agent_with(clock=clock)
    agent.retention.seconds = 60.0
    with agent:
        task = post_task(agent, "BotMotion", "stop")
        with agent.transaction() as tx:
            tx.change(task.evolve(result=AllocationResult(state=TaskState.SUCCEEDED)))
        assert agent.retention.sweep() == 0
        clock.advance(59.0)
        assert agent.retention.sweep() == 0 and agent.blackboard.get(task.uid) is not None
        clock.advance(2.0)
        assert agent.retention.sweep() == 1 and agent.blackboard.get(task.uid) is None


def test_a_manual_clock_does_not_go_back():
    with pytest.raises(UsageError, match="expected seconds >= 0, got -1"):
        ManualClock().advance(-1)


def test_a_plugin_reads_the_agents_clock_both_ways():
    """`self.clock()` is the agent's monotonic reading, `self.clock.wall()` its epoch seconds: a
    ManualClock moves both together, and a plugin outside an agent reads the process's clock."""
    from erni.blackboard.clock import SYSTEM

    clock = ManualClock(start=50.0, wall_start=1_800_000_000.0)
    with agent_with(Ticker, clock=clock) as agent:
        (ticker,) = agent.plugins
        assert ticker.clock is clock
        assert (ticker.clock(), ticker.clock.wall()) == (50.0, 1_800_000_000.0)
        clock.advance(2.5)
        assert (ticker.clock(), ticker.clock.wall()) == (52.5, 1_800_000_002.5)
    assert Ticker().clock is SYSTEM


def test_a_bare_callable_is_the_monotonic_reading_with_the_wall_clock_following_it():
    from erni.blackboard import Agent

    now = [100.0]
    agent = Agent("a", clock=lambda: now[0])
    before = time.time()
    wall = agent.clock.wall()
    now[0] += 30.0
    assert agent.clock() == 130.0
    assert agent.clock.wall() - wall == pytest.approx(30.0)
    assert before - 1.0 <= wall <= time.time() + 1.0
