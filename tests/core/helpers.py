"""Small plugins used by the core tests."""

from __future__ import annotations

import threading
import time
from typing import Any

from erni.blackboard import BBObject, Plugin


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


def settled(plugin: Plugin) -> bool:
    """Whether the scheduler has done with `plugin`: neither queued nor running (a signal queues it at
    once, so after one this says its run, or its skipped run, is over)."""
    with plugin._sched_lock:
        return not plugin._scheduled and not plugin._running


class Sleeper(Plugin):
    """Runs for `delay` seconds every time it is woken; counts concurrent runs."""

    delay = 0.05

    def setup(self) -> None:
        self.active = 0
        self.max_active = 0
        self.count = 0
        self.lock = threading.Lock()

    def execute(self) -> None:
        with self.lock:
            self.active += 1
            self.count += 1
            self.max_active = max(self.max_active, self.active)
        time.sleep(self.delay)
        with self.lock:
            self.active -= 1
