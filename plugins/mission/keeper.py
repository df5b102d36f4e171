"""Keeping the robot connected: the network guard's verdicts applied to the mission's remote jobs.

`NetGuard` (netaware.py) judges the links; the `LinkKeeper` acts on its judgement for MissionControl:
it holds or retreats the moving jobs when connectivity is at risk (by the mission's `policy`), lets
them go on when it is restored (unless a job's motion leads away from the neighbour of a lossy
critical link), slows a step that leaves such a neighbour, and owns the hold and the retreat it
issued. It acts through the mission's small `KeeperOps` interface.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Mapping
from typing import TYPE_CHECKING, Protocol

from pydantic import JsonValue

from erni.blackboard import Params, Task, TaskState
from erni.blackboard.tasks import ForwardParams, GotoParams, StopParams
from erni.plugins.mission.netaware import NetGuard
from erni.plugins.mission.remote import RemoteJob
from erni.plugins.mission.team import TeamView

if TYPE_CHECKING:
    from erni.plugins.mission.plugin import MissionSettings

CUE_LOST = [(10, 67), (10, 60)]        # connectivity at risk: falling
CUE_BACK = [(10, 60), (10, 67)]        # connectivity back: rising


class KeeperOps(Protocol):
    """What the keeper may do (implemented by MissionControl)."""

    agent_name: str

    def issue(self, parent: str | None, preposition: str, params: Params) -> str: ...
    def withdraw(self, uid: str | None) -> None: ...
    def report(self, uid: str, state: TaskState, message: str = "", *, progress: float | None = None,
               values: Mapping[str, JsonValue] | None = None, force: bool = False) -> None: ...
    def end_job(self, uid: str, state: TaskState, message: str) -> None: ...
    def halt(self, cancel: str | None, *, hold: bool, by: str | None = None) -> None: ...
    def say(self, tones: list[tuple[int, int]]) -> None: ...


class LinkKeeper:
    """The mission's network-aware behaviour: the guard's verdicts applied to the moving jobs."""

    def __init__(self, ops: KeeperOps, guard: NetGuard, team: TeamView, settings: MissionSettings,
                 log: logging.Logger) -> None:
        self.ops = ops
        self.guard = guard
        self.team = team
        self.settings = settings
        self.log = log
        self.guard_stop: str | None = None   # the hold this keeper issued (a BotMotion stop)
        self.retreat: str | None = None      # the retreat it issued (a BotMotion goto)

    def check(self, now: float, moving: list[RemoteJob]) -> float | None:
        """Give the guard the team's positions, act on its verdict for the `moving` jobs; return in how
        many seconds it wants to look again (None: at no particular time)."""
        mine = self.team.mine()
        self.guard.positions({n: (p[0], p[1]) for n, p in self.team.fresh(now).items()})
        change = self.guard.update(now, None if mine is None else mine[:2])
        if change == "risk":
            self.log.info("connectivity at risk: %s", self.guard.state.reason)
            self.ops.say(CUE_LOST)
            self.apply_policy([j for j in moving if not self.improves(j)], self.guard.state.reason)
        elif change == "clear":
            self.log.info("connectivity restored")
            self.ops.say(CUE_BACK)
        if not self.guard.state.at_risk and any(j.held for j in moving):
            self._resume(moving)
        return self.guard.pending_clear_in(now)

    def admit(self, job: RemoteJob) -> None:
        """A job begins: while connectivity is at risk, the policy applies to it at once (unless its
        motion improves connectivity)."""
        if job.moving and self.guard.state.at_risk and not self.improves(job):
            self.apply_policy([job], self.guard.state.reason)

    def slowed(self, job: RemoteJob, params: GotoParams | ForwardParams) -> tuple[GotoParams | ForwardParams, str]:
        """The step's parameters, slowed to the guard's safe speed when it moves away from the neighbour
        of a critical link; with why ("" when not slowed)."""
        ends = self._ends(job)
        leaving = "" if ends is None else self.guard.leaving(*ends)
        cap = round(self.guard.safe_speed(), 2)
        if leaving and params.speed > cap:
            return params.model_copy(update={"speed": cap}), (
                f"slowed from {params.speed:g} to {cap:g} m/s: moving away from {leaving}, its only link to the team")
        return params, ""

    def finished(self, sub: Task) -> bool:
        """Whether `sub` is the retreat, ended: then the robot holds where it led while connectivity is
        still at risk."""
        if sub.uid != self.retreat or not sub.done:
            return False
        self.retreat = None
        self.ops.withdraw(sub.uid)
        if self.guard.state.at_risk and self.guard_stop is None:
            self.guard_stop = self.ops.issue(None, "stop", StopParams(hold=True))
        return True

    def forget(self, uid: str) -> None:
        """One of the mission's sub-tasks is gone: if it was the hold, there is none now."""
        if self.guard_stop == uid:
            self.guard_stop = None

    def release(self) -> None:
        """Withdraw the hold and the retreat."""
        self.ops.withdraw(self.guard_stop)
        self.guard_stop = None
        self.ops.withdraw(self.retreat)
        self.retreat = None

    def _resume(self, moving: list[RemoteJob]) -> None:
        """Connectivity is no longer at risk: resume the held jobs, except those whose motion would
        take the robot further from the neighbour of a critical link that shows loss."""
        free = []
        for job in moving:
            if not job.held:
                continue
            away = self._heads_away(job)
            if away:
                why = f"{self.ops.agent_name} stays: moving on would take it further from {away}, its only link to the team"
                if job.held != why:
                    job.held = why
                    self.ops.report(job.uid, TaskState.RUNNING, f"holding: {why}")
                continue
            free.append(job)
        if len(free) == sum(1 for j in moving if j.held):
            self.release()
        for job in free:
            job.held = ""
            self.ops.report(job.uid, TaskState.RUNNING, "resumed: connectivity restored")

    def _ends(self, job: RemoteJob) -> tuple[tuple[float, float], tuple[float, float]] | None:
        """Where the robot is and where the job's current step drives it (None: not known, or a
        random walk, which picks its own ways)."""
        mine = self.team.mine()
        if mine is None or not job.steps:
            return None
        step = job.steps[min(job.index, len(job.steps) - 1)]
        p = step.params
        here = (mine[0], mine[1])
        if isinstance(p, GotoParams):
            return here, (p.x, p.y)
        if isinstance(p, ForwardParams):
            return here, (here[0] + math.cos(mine[2]), here[1] + math.sin(mine[2]))
        return None

    def _heads_away(self, job: RemoteJob) -> str:
        """The neighbour of a lossy critical link that the job's motion takes the robot away from
        (a random walk: none; if one of its ways leads off, the prediction holds it again)."""
        ends = self._ends(job)
        return "" if ends is None else self.guard.away(*ends)

    def improves(self, job: RemoteJob) -> bool:
        """A motion towards the neighbour of every critical link: it improves connectivity."""
        if not job.steps or not self.guard.state.critical or not self.guard.where:
            return False
        mine = self.team.mine()
        p = job.steps[job.index].params
        if mine is None or not isinstance(p, GotoParams):
            return False
        return all(n in self.guard.where and math.dist((p.x, p.y), self.guard.where[n]) + 0.3
                   < math.dist(mine[:2], self.guard.where[n]) for n in self.guard.state.critical)

    def apply_policy(self, jobs: list[RemoteJob], reason: str) -> None:
        """Connectivity is at risk for `jobs`: stop them, retreat, or hold, as the mission's policy says."""
        if not jobs:
            return
        policy = self.settings.policy
        if policy == "stop":
            for job in jobs:
                self.ops.end_job(job.uid, TaskState.FAILED, f"stopped: {reason}")
            self.ops.halt(None, hold=False, by="the network guard")
            return
        mine = self.team.mine()
        target = None if mine is None else self.guard.retreat_point(mine[:2], self.settings.retreat_distance)
        if policy == "retreat" and target is not None and mine is not None and \
                ((mine[0] - target[0]) ** 2 + (mine[1] - target[1]) ** 2) ** 0.5 > 0.2:
            if self.retreat is None:
                self.retreat = self.ops.issue(None, "goto", GotoParams(x=round(target[0], 3), y=round(target[1], 3),
                                                                       speed=self.settings.speed, tolerance=0.15))
            why = f"retreating to ({target[0]:.2f}, {target[1]:.2f}): {reason}"
        else:
            if self.guard_stop is None:
                self.guard_stop = self.ops.issue(None, "stop", StopParams(hold=True))
            why = f"holding: {reason}"
        for job in jobs:
            job.held = reason
            self.ops.report(job.uid, TaskState.RUNNING, why)
