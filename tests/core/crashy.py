"""A plugin that publishes tasks as fast as it can (for the kill -9 journal test)."""

from __future__ import annotations

from erni.blackboard import Plugin, Task, new_uid


class Flood(Plugin):
    """Adds a task, changes an older one and removes an older one on every run."""

    def setup(self) -> None:
        self.n = 0
        self.prefix = new_uid()[:6]  # a new run never reuses the uids of the last one
        self.mine: list[Task] = []
        self.wake_every(0.001)

    def execute(self) -> None:
        for _ in range(20):
            self.n += 1
            task = Task(uid=f"{self.prefix}-{self.n:08d}", verb="BotMotion", preposition="stop", source=self.agent_name)
            self.add(task)
            self.mine.append(task)
        if len(self.mine) > 30:
            self.change(self.mine[-25].with_result("running", progress=0.5))
            self.remove(self.mine.pop(0))
