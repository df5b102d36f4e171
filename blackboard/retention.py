"""Retention: finished tasks leave the blackboard (and so the journal and every plugin's memory)
a configurable time after they finished.

The time counts on this agent's monotonic clock from when it saw the task final. A task that
comes back final from the journal after a restart counts from when it ended, as the journal's
row says (its last write, on the wall clock, the only clock that spans a restart): a restart
does not keep a finished task longer. A finished sub-task stays as
long as its parent runs. Removing a finished task is what its requester would do: the
transport drops its notes of it and tells the other end, which drops its copy too.
"""

from __future__ import annotations

import logging
import threading
from typing import TYPE_CHECKING

from erni.blackboard.blackboard import REMOVE, Op
from erni.blackboard.errors import ErniError
from erni.blackboard.tasks import Task

if TYPE_CHECKING:
    from erni.blackboard.agent import Agent


class Retention:
    """Removes tasks `seconds` after they became final; a component of the agent (start/stop)."""

    def __init__(self, agent: Agent, seconds: float):
        self.agent = agent
        self.seconds = seconds
        self.log = logging.getLogger(f"erni.{agent.name}.retention")
        self._done: dict[str, float] = {}  # uid -> when it was seen final (the agent's clock)
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self.removed = 0

    def listener(self, ops: list[Op]) -> None:
        """Blackboard commit listener: note when tasks become final (no I/O, no transaction)."""
        for _, obj, _ in ops:
            if isinstance(obj, Task):
                break
        else:  # no task in this commit (most of them: readings, statuses)
            return
        now = self.agent.clock()
        with self._lock:
            for kind, obj, _ in ops:
                if not isinstance(obj, Task):
                    continue
                if kind == REMOVE or not obj.done:
                    self._done.pop(obj.uid, None)
                else:
                    self._done.setdefault(obj.uid, now)

    def ended(self, uid: str, ago: float) -> None:
        """Task `uid` (on the board, final) ended `ago` seconds before now: it leaves `seconds` after
        that, not after it was seen (a task rehydrated final)."""
        now = self.agent.clock()
        with self._lock:
            if uid in self._done:
                self._done[uid] = now - max(0.0, ago)

    def start(self) -> None:
        """Start the sweeping thread."""
        self._stop.clear()
        self._thread = threading.Thread(target=self._run, name=f"erni-{self.agent.name}-retention", daemon=True)
        self._thread.start()

    def stop(self) -> None:
        """Stop the sweeping thread."""
        self._stop.set()
        if self._thread is not None:
            self._thread.join(2)
            self._thread = None

    def _run(self) -> None:
        period = min(max(self.seconds / 4, 0.05), 10.0)
        while not self._stop.wait(period):
            try:
                self.sweep()
            except ErniError as err:  # a conflicting commit: next sweep
                self.log.warning("retention sweep skipped: %s", err)

    def sweep(self, now: float | None = None) -> int:
        """Remove the tasks final for longer than the retention; return how many."""
        now = self.agent.clock() if now is None else now
        with self._lock:
            due = [uid for uid, since in self._done.items() if now - since >= self.seconds]
        if not due:
            return 0
        board = self.agent.blackboard
        gone = 0
        with board.transaction("retention") as tx:
            for uid in due:
                task = board.get(uid)
                if not isinstance(task, Task) or not task.done:
                    continue
                parent = board.get(task.parent) if task.parent else None
                if isinstance(parent, Task) and not parent.done:
                    continue  # a step of a task that still runs: kept with it
                tx.remove(task)
                gone += 1
        self.removed += gone
        return gone
