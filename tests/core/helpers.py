"""Small plugins used by the core tests."""

from __future__ import annotations

import threading
from typing import Any

from erni.blackboard import BBObject, Plugin
from erni.blackboard.testing import wait_until


class Item(BBObject):
    """A plain object with a value."""

    value: int = 0
    tag: str = ""


class Recorder(Plugin):
    """Records every view it is given: (added, changed, removed, reports, members)."""

    kind: Any = Item
    where: Any = None

    def setup(self) -> None:
        self.sub = self.subscribe(self.kind, where=self.where)
        self.views: list[dict[str, Any]] = []
        self.lock = threading.Lock()

    def execute(self) -> None:
        view = {
            "added": list(self.sub.added), "changed": list(self.sub.changed),
            "removed": list(self.sub.removed),
            "reports": {o.uid: self.sub.reports(o) for o in self.sub.changed},
            "members": {o.uid: o for o in self.sub},
        }
        with self.lock:
            self.views.append(view)

    def all(self, key: str) -> list[Any]:
        with self.lock:
            return [o for v in self.views for o in v[key]]


def scheduler_idle(plugin: Plugin) -> bool:
    """Whether the scheduler has done with `plugin`: neither queued nor running (a signal queues it at
    once, so after one this says its run, or its skipped run, is over)."""
    with plugin._sched_lock:
        return not plugin._scheduled and not plugin._running


class Sleeper(Plugin):
    """Counts its runs and the runs at once; each run waits for `gate`, open unless the test closes it
    (`gate.clear()`, then `gate.set()` to let the run held end)."""

    def setup(self) -> None:
        self.active = 0
        self.max_active = 0
        self.count = 0
        self.lock = threading.Lock()
        self.gate = threading.Event()
        self.gate.set()

    def execute(self) -> None:
        with self.lock:
            self.active += 1
            self.count += 1
            self.max_active = max(self.max_active, self.active)
        self.gate.wait(10)
        with self.lock:
            self.active -= 1


class Probe(Plugin):
    """Runs only when woken: `timers_caught_up` times the agent's timer thread with it."""

    def setup(self) -> None:
        self.count = 0

    def execute(self) -> None:
        self.count += 1


def timers_caught_up(probe: Probe, timeout: float = 10.0) -> None:
    """Wait until the timer thread of `probe`'s agent has gone round twice since the call: each wake-up
    due on the agent's clock by now has been handed to its plugin (before the probe's own, due now),
    and the slow-run watch has looked at the clock after that."""
    wait_until(lambda: scheduler_idle(probe), timeout=timeout)
    for _ in range(2):
        runs = probe.count
        probe.wake_in(0.0)
        wait_until(lambda runs=runs: probe.count > runs and scheduler_idle(probe), timeout=timeout,
                   message="the agent's timer thread did not fire a wake-up due now")
