"""EchoPlugin: a small example performer that answers every task addressed to it.

It succeeds each task of the verbs it is configured for after an optional delay, with the
task's parameters echoed in the result. Useful to try tasking before robots exist, and as
a template for new plugins.
"""

from __future__ import annotations

from pydantic import Field

from erni.blackboard import Plugin, Task, TaskState
from erni.blackboard.objects import Model


class EchoSettings(Model):
    """The `[plugin.settings]` of the echo plugin."""

    verbs: list[str] = Field(default_factory=lambda: ["BotMotion"], description="verbs of the tasks it answers")
    delay: float = Field(0.0, ge=0, description="seconds before the task succeeds")


class EchoPlugin(Plugin[EchoSettings]):
    """Succeeds every task of `verbs` (optionally after `delay` seconds), echoing its params."""

    def setup(self) -> None:
        verbs = set(self.settings.verbs)
        self.tasks = self.subscribe(
            Task, where=lambda t: t.verb in verbs and t.destination in (None, self.agent_name))
        self.due: dict[str, float] = {}

    def execute(self) -> None:
        now = self.clock()
        for task in self.tasks.added:
            if task.done:
                continue
            self.change(task.with_result(TaskState.RUNNING, message="echo: accepted"))
            self.due[task.uid] = now + self.settings.delay
            self.wake_in(self.settings.delay)
        for task in self.tasks.removed:
            self.due.pop(task.uid, None)
        for uid, when in list(self.due.items()):
            current = self.tasks.get(uid)
            if current is None:
                del self.due[uid]
            elif when <= now:
                del self.due[uid]
                self.change(current.with_result(
                    TaskState.SUCCEEDED, progress=1.0, message="echo: done",
                    values={"params": current.params.model_dump(mode="json")}))
