"""Two-tier tasking: a RemoteBotMotion task planned as local BotMotion steps, and its significant reports.

`plan(task, pose, ...)` turns one RemoteBotMotion task into an ordered list of `StepSpec`s
(BotMotion preposition + parameters), performed one after the other:
- randomwalk, teleport, forward: one step of the same preposition and parameters;
- goto: one BotMotion goto; with `mode="turn_forward"` a turn toward the goal and a forward;
  when the straight line crosses a known obstacle (circles x, y, r in m), goto waypoints
  around it (an auxiliary point beside the obstacle, then the goal).

`Significance` decides which result changes of the remote task are reported (published):
state changes (accepted = pending, started = running, succeeded, failed, cancelled), a new
message, and progress crossing the next multiple of `step` (0.25 by default). Everything else
(values such as distance remaining) travels only with those updates.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field

from erni.blackboard import AllocationResult, Params, Pose, Task, TaskState
from erni.blackboard.tasks import CancelParams, ForwardParams, GotoParams, TurnParams


@dataclass(frozen=True)
class StepSpec:
    """One local BotMotion sub-task of a plan."""

    preposition: str
    params: Params


MOVING = frozenset({"goto", "forward", "randomwalk"})
RESUMABLE = frozenset({"goto", "teleport"})
"""RemoteBotMotion prepositions with an absolute target: after a restart of the robot they are
planned again from where it stands; the others (relative or timed) fail instead of repeating."""


def resumable(task: Task) -> bool:
    """True when `task`, interrupted by a restart of its robot, is resumed rather than failed."""
    return task.verb == "RemoteBotMotion" and task.preposition in RESUMABLE


def plan(task: Task, pose: Pose | None, *, mode: str = "goto", obstacles: Sequence[tuple[float, float, float]] = (),
         margin: float = 0.4) -> list[StepSpec]:
    """Return the BotMotion steps performing a RemoteBotMotion task (cancel has none)."""
    if isinstance(task.params, CancelParams):
        return []
    if not isinstance(task.params, GotoParams):  # randomwalk, teleport, forward: one step, the same parameters
        return [StepSpec(task.preposition, task.params)]
    p = task.params
    goal = (p.x, p.y)
    if pose is None:
        return [StepSpec("goto", p)]
    import numpy as np  # imported at the first planned goto, not at agent start

    from erni.strategies.widep import auxiliary_poi

    here = np.array([pose.x, pose.y])
    points: list[tuple[float, float]] = []
    if obstacles:
        target = np.array(goal, dtype=float)
        start = here
        for _ in range(4):  # at most four detours
            aux = auxiliary_poi(start, target, np.array(obstacles, dtype=float), margin)
            if aux is None:
                break
            points.append((round(float(aux[0]), 3), round(float(aux[1]), 3)))
            start = aux
    if points:
        legs = [StepSpec("goto", GotoParams(x=x, y=y, tolerance=max(0.2, p.tolerance), speed=p.speed,
                                            timeout=p.timeout))
                for x, y in points]
        return legs + [StepSpec("goto", p)]
    if mode == "turn_forward":
        dx, dy = goal[0] - pose.x, goal[1] - pose.y
        dist = math.hypot(dx, dy)
        if dist <= p.tolerance:
            return [StepSpec("goto", p)]
        angle = math.degrees(_wrap(math.atan2(dy, dx) - pose.theta))
        steps: list[StepSpec] = []
        if abs(angle) > 2.0:
            steps.append(StepSpec("turn", TurnParams(angle=round(angle, 2))))
        steps.append(StepSpec("forward", ForwardParams(distance=round(dist, 3), speed=p.speed, timeout=p.timeout)))
        return steps
    return [StepSpec("goto", p)]


def _wrap(a: float) -> float:
    return (a + math.pi) % (2 * math.pi) - math.pi


@dataclass
class Significance:
    """Filters a remote task's result changes down to the significant ones."""

    step: float = 0.25
    state: TaskState | None = None
    bucket: int = -1
    message: str | None = None

    def significant(self, result: AllocationResult) -> bool:
        """True when `result` differs significantly from the last one reported (and records it)."""
        bucket = math.floor(result.progress / self.step + 1e-9) if self.step > 0 else 0
        news = (result.state != self.state or result.message != self.message or bucket > self.bucket)
        if news:
            self.state, self.message, self.bucket = result.state, result.message, max(bucket, self.bucket)
        return news


@dataclass
class RemoteJob:
    """A remote task in progress: its plan, the step being performed and its last report."""

    uid: str
    steps: list[StepSpec]
    index: int = 0
    sub: str | None = None             # uid of the running BotMotion sub-task
    subs: list[str] = field(default_factory=list)
    held: str = ""                     # why the network guard holds it ("" = not held)
    resumed: bool = False              # planned again after a restart of this robot
    report: Significance = field(default_factory=Significance)

    @property
    def moving(self) -> bool:
        """True when the job drives the robot (the network guard applies)."""
        return any(s.preposition in MOVING for s in self.steps[self.index:])

    def progress(self, sub_progress: float) -> float:
        """Overall progress 0..1 of the plan with the current step at `sub_progress`."""
        if not self.steps:
            return 1.0
        return min(1.0, (self.index + max(0.0, min(1.0, sub_progress))) / len(self.steps))
