"""Deploy tasks on one robot: each strategy's runner turns the pure strategy into BotMotion sub-tasks.

A runner is ticked by MissionControl inside `execute()` (cheap decisions only) and talks to
the blackboard through the small `Ops` interface the plugin implements: issue or withdraw a
BotMotion sub-task, read a sub-task, report on the Deploy task, read the team's positions
and this robot's link qualities. Every runner meters the robot's energy (paper 000's model)
from its poses and reports it in its result values (`energy_j`, `distance_m`, `moving_s`,
`elapsed_s`).

- widep: lockstep rounds of `period` s on the wall clock (shared by the team): at the start
  of a round every robot takes one WiDep step (a BotMotion goto) short enough to end well
  before the next round, decided only once every robot it knows has been seen at rest, so
  all decisions of a round see the same settled layout, as in the synchronous algorithm whose
  bound keeps the team connected (links are kept `widep_slack` shorter than R for odometry
  error). A robot whose position is older than `position_timeout`, or that is not seen at
  rest, holds everyone who knows it for that round. Succeeds when the PoI is covered (a known
  robot within `tolerance`); fails, saying what held it, after `widep_stall_rounds` rounds in
  which the team came no closer to the PoI.
- spread: every `dt` a BotMotion velocity from equation (15)/(16) with this robot and its
  known neighbours; succeeds after `duration` (runs until cancelled without one).
- relay: every `relay_period` a relay decision from the link qualities to `source` and
  `destination`; a goto when it must move; stays running (balanced or not) until cancelled.
- patrol: sweeps its blocks with gotos, publishes a `Territory` heartbeat every `heartbeat`
  s, and takes over a silent neighbour's block (TakeoverTable); runs until cancelled.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Mapping
from typing import TYPE_CHECKING, ClassVar, Protocol

import numpy as np
from numpy.typing import NDArray
from pydantic import JsonValue

from erni.blackboard import Params, Pose, Task, TaskState
from erni.blackboard.clock import Clock
from erni.blackboard.tasks import GotoParams, PatrolParams, RelayParams, SpreadParams, VelocityParams, WidepParams
from erni.plugins.mission.team import TeamView, Territory
from erni.strategies import patrol as patrol_core
from erni.strategies.energy import EnergyMeter
from erni.strategies.potential import SpreadConfig, robot_command
from erni.strategies.relay import relay_step
from erni.strategies.widep import widep_step

if TYPE_CHECKING:
    from erni.plugins.mission.plugin import MissionSettings


class Ops(Protocol):
    """What a runner may do (implemented by MissionControl)."""

    agent_name: str
    team: TeamView

    @property
    def clock(self) -> Clock: ...

    def issue(self, parent: str | None, preposition: str, params: Params) -> str: ...
    def withdraw(self, uid: str | None) -> None: ...
    def sub(self, uid: str | None) -> Task | None: ...
    def report(self, uid: str, state: TaskState, message: str = "", *, progress: float | None = None,
               values: Mapping[str, JsonValue] | None = None, force: bool = False) -> None: ...
    def link_qualities(self) -> dict[str, float] | None: ...
    def publish_territory(self, territory: Territory) -> None: ...


class Runner:
    """Base of the strategy runners: energy metering, the current motion sub-task, value reports.

    Each runner reads its own preposition's parameters (`task.params_as(WidepParams)`, ...) as `self.p`.
    """

    kind: ClassVar[str] = ""

    def __init__(self, task: Task, ops: Ops, settings: MissionSettings, now: float) -> None:
        self.uid = task.uid
        self.ops = ops
        self.s = settings
        self.meter = EnergyMeter()
        self.started = now
        self.motion: str | None = None  # uid of the BotMotion sub-task moving the robot
        self.due = now
        self.done = False
        self.extra: dict[str, JsonValue] = {}  # the strategy's own result values
        self.message = ""

    def pose(self, pose: Pose) -> None:
        """Meter this robot's motion."""
        self.meter.update(pose.stamp, pose.x, pose.y)

    def values(self) -> dict[str, JsonValue]:
        """Result values: the strategy's own plus the energy meter's, counted up to now (Pose
        stamps are wall-clock times)."""
        return {**self.extra, **self.meter.values(until=self.ops.clock.wall())}

    def motion_state(self) -> TaskState | None:
        """State of the current motion sub-task (None when there is none or it is gone)."""
        t = self.ops.sub(self.motion)
        return None if t is None else t.state

    def move(self, preposition: str, params: Params) -> None:
        """Replace the current motion sub-task with a new one."""
        self.ops.withdraw(self.motion)
        self.motion = self.ops.issue(self.uid, preposition, params)

    def finish(self, state: TaskState, message: str) -> None:
        """End the Deploy task (its sub-task withdrawn)."""
        self.ops.withdraw(self.motion)
        self.motion = None
        self.done = True
        self.ops.report(self.uid, state, message, values=self.values(), force=True,
                        progress=1.0 if state == TaskState.SUCCEEDED else None)

    def stop(self) -> None:
        """Withdraw everything this runner issued."""
        self.ops.withdraw(self.motion)
        self.motion = None

    def tick(self, now: float) -> float:
        """Decide; return the seconds until the next tick."""
        raise NotImplementedError

    def heard(self, territory: Territory, now: float) -> None:
        """A patrol heartbeat of another robot (only the patrol runner cares)."""


class WidepRunner(Runner):
    """PoI coverage: WiDep steps toward the PoI under the RNG connectivity bound, in lockstep rounds.

    A round's decision is taken on a settled snapshot: every robot the team view knows must have
    been seen standing still (for `widep_settle` s, in a reading taken after its previous step
    could have ended), so all decisions of a round see the layout the synchronous algorithm
    assumes and its bound (R - d+(u)) / 2 applies as it is. A robot not yet seen settled at the
    start of a round is waited for during the first quarter of the round, then the round is sat
    out. A step shorter than `widep_min_step` is not driven (a goto that short would "arrive"
    without moving); a robot whose team has not come closer to the PoI for `widep_stall_rounds`
    rounds fails its task, saying what held it.
    """

    kind = "widep"

    def __init__(self, task: Task, ops: Ops, settings: MissionSettings, now: float) -> None:
        super().__init__(task, ops, settings, now)
        self.p = task.params_as(WidepParams)
        self.start_distance: float | None = None  # to the PoI when the first step was decided (m)
        self.decided = -1                          # the last round a decision was taken in
        self.best = math.inf                       # closest any known robot came to the PoI (m)
        self.own_best = math.inf                   # closest this robot came to it (m)
        self.idle_rounds = 0                        # rounds since the team last came closer
        self.why = ""                               # what held the last decision

    def tick(self, now: float) -> float:
        p = self.p
        period = p.period
        k = math.floor(now / period)
        round_start = k * period
        next_round = round_start + period - now + 1e-3
        # every robot ever heard counts: one that fell out of view must not free this robot
        names, pos = self.ops.team.array(now, everyone=True)
        if not names or names[0] != self.ops.agent_name:
            self.ops.report(self.uid, TaskState.RUNNING, "waiting for this robot's pose")
            return next_round
        poi = np.array([p.x, p.y])
        dists = np.hypot(*(pos - poi).T)
        within = [n for n, d in zip(names, dists) if d <= p.tolerance]
        if within:
            self.extra.update(covered_by=within[0])
            self.finish(TaskState.SUCCEEDED, f"PoI ({p.x:g}, {p.y:g}) covered by {within[0]}")
            return period
        if k <= self.decided:
            return next_round
        state = self.motion_state()
        if state is not None and not state.done:
            return next_round  # still finishing the last step: sit this round out
        stale = self.ops.team.stale(names, now)
        moving = [] if stale else self._unsettled(names, round_start, period)
        if moving and now < round_start + 0.25 * period:
            return 0.2  # wait a little for the others to come to rest
        self.decided = k
        if self.start_distance is None:
            self.start_distance = round(float(dists[0]), 3)
            self.extra["start_distance"] = self.start_distance
        if self._stalled(float(dists[0]), float(dists.min()), period):
            return period
        progress = max(0.0, 1.0 - float(dists[0]) / self.start_distance) if self.start_distance > 0 else 0.0
        if stale or moving:
            self.why = (f"no fresh position of {', '.join(stale)}" if stale
                        else f"{', '.join(moving)} not seen at rest")
            self.ops.report(self.uid, TaskState.RUNNING, f"holding: {self.why}", progress=progress)
            return next_round
        cap = min(self.s.widep_step_cap, 0.4 * self.s.speed * period)  # at rest before the next round
        step = widep_step(pos, 0, poi, p.range, tolerance=p.tolerance, obstacles=self._obstacles(),
                          margin=self.s.obstacle_margin, separation=self.s.separation, step_cap=cap,
                          slack=self.s.widep_slack, fixed=[not self.ops.team.is_robot(n) for n in names])
        self.extra.update(neighbours=len(names) - 1, bound_m=round(step.limit, 3), step_m=round(step.length, 3),
                          distance_m_to_poi=round(float(dists[0]), 3), auxiliary=step.auxiliary,
                          rounds_without_progress=self.idle_rounds)
        if step.length < self.s.widep_min_step:
            self.why = f"the connectivity bound allows {step.length:.2f} m (bound {step.limit:.2f} m)"
            self.ops.report(self.uid, TaskState.RUNNING, f"holding: {self.why}", progress=progress,
                            values=self.values())
            return next_round
        self.why = ""
        self.move("goto", GotoParams(x=round(float(step.target[0]), 3), y=round(float(step.target[1]), 3),
                                     speed=self.s.speed, tolerance=0.05))
        msg = "heading for an auxiliary PoI" if step.auxiliary else "stepping toward the PoI"
        self.ops.report(self.uid, TaskState.RUNNING, msg, progress=progress, values=self.values())
        return next_round

    def _unsettled(self, names: list[str], round_start: float, period: float) -> list[str]:
        """The other robots not seen at rest since the previous round's steps could have ended."""
        # a standing robot republishes its unchanged Pose only every pose_keepalive (plus delivery)
        fresh_after = round_start - max(0.5 * period, self.s.pose_keepalive + 0.5)
        return [n for n in names[1:] if not self.ops.team.settled(n, fresh_after, self.s.widep_settle)]

    def _obstacles(self) -> NDArray[np.float64] | None:
        """The known obstacles (nodes known not to be robots go to `widep_step` as `fixed`)."""
        return np.array(self.s.obstacles, dtype=float).reshape(-1, 3) if self.s.obstacles else None

    def _stalled(self, mine: float, best: float, period: float) -> bool:
        """Count rounds in which neither the team nor this robot came 5 cm closer to the PoI; fail after too many."""
        if best < self.best - 0.05 or mine < self.own_best - 0.05:
            self.best = min(self.best, best)
            self.own_best = min(self.own_best, mine)
            self.idle_rounds = 0
            return False
        self.idle_rounds += 1
        if self.idle_rounds < self.s.widep_stall_rounds:
            return False
        self.extra.update(stalled=True, rounds_without_progress=self.idle_rounds)
        self.finish(TaskState.FAILED, f"no progress toward the PoI for {self.idle_rounds} rounds of "
                    f"{period:g} s: the closest robot is {best:.2f} m from it"
                    + (f"; {self.why}" if self.why else ""))
        return True


class SpreadRunner(Runner):
    """Potential-field self-deployment: velocity commands from equation (15) or (16)."""

    kind = "spread"

    def __init__(self, task: Task, ops: Ops, settings: MissionSettings, now: float) -> None:
        super().__init__(task, ops, settings, now)
        p = self.p = task.params_as(SpreadParams)
        self.cfg = SpreadConfig(distance=p.distance, gain=p.gain, dt=p.dt, range=p.range,
                                neighbourhood=p.neighbourhood, model=p.model, vmax=settings.speed,
                                wmax=math.radians(90), obstacle_distance=settings.obstacle_distance,
                                wall_distance=settings.wall_distance, obstacle_weight=settings.obstacle_weight,
                                sensing=settings.sensing_range)
        self.speed = 0.0
        self.omega = 0.0

    def tick(self, now: float) -> float:
        p = self.p
        period = max(p.dt, self.s.control_period)
        if p.duration is not None and now - self.started >= p.duration:
            self.finish(TaskState.SUCCEEDED, f"spread for {p.duration:g} s")
            return period
        mine = self.ops.team.where.get(self.ops.agent_name)
        names, pos = self.ops.team.array(now, robots_only=True)
        if mine is None or not names or names[0] != self.ops.agent_name:
            self.ops.report(self.uid, TaskState.RUNNING, "waiting for this robot's pose")
            return period
        theta = mine[2]
        speed, omega = self.speed, self.omega  # the robot's measured velocities (last Pose)
        cfg = self.cfg if period == p.dt else dataclasses.replace(self.cfg, dt=period)
        v, w = robot_command(pos, theta, speed, omega, 0, cfg, self._obstacles(), self._walls())
        if abs(v) < 0.01 and abs(w) < 0.02:
            v, w = 0.0, 0.0
        if len(pos) > 1:
            d = np.hypot(*(pos[1:] - pos[0]).T)
            self.extra["nearest_m"] = round(float(d.min()), 3)
        self.extra["neighbours"] = len(names) - 1
        self.move("velocity", VelocityParams(v=round(v, 3), w=round(math.degrees(w), 2),
                                             duration=round(max(3 * period, 1.0), 2)))
        self.ops.report(self.uid, TaskState.RUNNING, "spreading", values=self.values())
        return period

    def pose(self, pose: Pose) -> None:
        super().pose(pose)
        self.speed, self.omega = pose.v, pose.w

    def _obstacles(self) -> NDArray[np.float64] | None:
        return np.array(self.s.obstacles, dtype=float) if self.s.obstacles else None

    def _walls(self) -> NDArray[np.float64] | None:
        return np.array(self.s.walls, dtype=float) if self.s.walls else None


class RelayRunner(Runner):
    """Relay positioning: move along source-destination toward the worse link until balanced."""

    kind = "relay"

    STALL = 5  # decisions unbalanced without moving 0.1 m before the result says the relay is stuck

    def __init__(self, task: Task, ops: Ops, settings: MissionSettings, now: float) -> None:
        super().__init__(task, ops, settings, now)
        self.p = task.params_as(RelayParams)
        self.anchor: NDArray[np.float64] | None = None  # where it was when it last moved or balanced
        self.idle = 0  # unbalanced decisions since then

    def tick(self, now: float) -> float:
        p = self.p
        period = self.s.relay_period
        state = self.motion_state()
        if state is not None and not state.done:
            return min(period, 0.25)
        where = self.ops.team.fresh(now)
        missing = [n for n in (self.ops.agent_name, p.source, p.destination) if n not in where]
        if missing:
            self.ops.report(self.uid, TaskState.RUNNING, f"waiting for the position of {', '.join(missing)}")
            return period
        q = self.ops.link_qualities()
        if q is None:
            self.ops.report(self.uid, TaskState.RUNNING, "waiting for link quality readings")
            return period
        qs, qd = q.get(p.source), q.get(p.destination)  # not a neighbour: no link (quality 0)
        me, src, dst = (np.array(where[n][:2]) for n in (self.ops.agent_name, p.source, p.destination))
        move = relay_step(me, src, dst, qs, qd, tolerance=p.tolerance, max_step=self.s.relay_step)
        self.extra.update(q_source=qs, q_destination=qd, imbalance=round(move.imbalance, 3),
                          balanced=move.balanced)
        off = float(np.hypot(*(move.target - me)))
        if off >= 0.1:
            self.move("goto", GotoParams(x=round(float(move.target[0]), 3), y=round(float(move.target[1]), 3),
                                         speed=self.s.speed, tolerance=0.05))
        msg = "balanced" if move.balanced else f"moving toward {p.source if move.along < 0 else p.destination}"
        if move.balanced or self.anchor is None or float(np.hypot(*(me - self.anchor))) >= 0.1:
            self.anchor, self.idle = me, 0
        else:
            self.idle += 1
        self.extra["stalled"] = self.idle >= self.STALL
        if self.idle >= self.STALL:
            msg = (f"stalled: links unbalanced (imbalance {move.imbalance:+.2f}) and no move for {self.idle} "
                   "decisions")
        # one report per decision (every relay_period s): the requester sees each measurement
        self.ops.report(self.uid, TaskState.RUNNING, msg, values=self.values(), force=True)
        return period


class PatrolRunner(Runner):
    """Territory patrol with heartbeats and takeover of a silent neighbour's block."""

    kind = "patrol"

    def __init__(self, task: Task, ops: Ops, settings: MissionSettings, now: float) -> None:
        super().__init__(task, ops, settings, now)
        p = self.p = task.params_as(PatrolParams)
        block = (p.xmin, p.ymin, p.xmax, p.ymax)
        self.events: list[JsonValue] = []  # "kind robot" of every takeover event, oldest first
        self.event_at: list[JsonValue] = []  # when each happened (epoch s)
        self.table = patrol_core.TakeoverTable(ops.agent_name, block, silence=p.silence,
                                               base=settings.backoff_base or 2.0 * p.heartbeat + 0.5)
        self.path: list[tuple[float, float]] = []
        self.waypoint = 0
        self.beat = 0
        self.next_beat = now
        self._replan()

    def _replan(self) -> None:
        holds = self.table.holds
        order = [self.ops.agent_name] + sorted(n for n in holds if n != self.ops.agent_name)
        path: list[tuple[float, float]] = []
        for name in order:
            pts = patrol_core.sweep_path(holds[name], self.s.patrol_spacing, self.s.obstacle_margin)
            path.extend((round(float(x), 3), round(float(y), 3)) for x, y in pts)
        self.path = path
        self.waypoint = self.waypoint % len(path) if path else 0
        self.extra["holds"] = [*sorted(holds)]

    def heard(self, territory: Territory, now: float) -> None:
        events = self.table.heard(territory.robot, territory.block, now, tuple(territory.holds),
                                  territory.claims)
        self._events(events, now)

    def _events(self, events: list[patrol_core.Event], now: float) -> None:
        if not events:
            return
        self.extra["events"] = self.events
        self.extra["event_at"] = self.event_at
        for ev in events:
            self.events.append(f"{ev.kind} {ev.about}")
            self.event_at.append(round(now, 3))
        self._replan()
        last = events[-1]
        text = {"silent": "{} fell silent", "claim": "took over the block of {}", "yield": "yielded {}'s block",
                "return": "gave {}'s block back"}[last.kind].format(last.about)
        self.message = text
        self.ops.report(self.uid, TaskState.RUNNING, text, values=self.values(), force=True)

    def tick(self, now: float) -> float:
        p = self.p
        self._events(self.table.tick(now), now)
        if now >= self.next_beat:
            self.beat += 1
            hb = self.table.heartbeat()
            xmin, ymin, xmax, ymax = hb["block"]
            self.ops.publish_territory(Territory(uid=f"territory:{self.ops.agent_name}", robot=self.ops.agent_name,
                                                 task=self.uid, block=(xmin, ymin, xmax, ymax), holds=hb["holds"],
                                                 claims=hb["claims"], beat=self.beat, stamp=now))
            self.next_beat = now + p.heartbeat
        state = self.motion_state()
        if self.path and (state is None or state.done):
            if state is not None:
                self.waypoint = (self.waypoint + 1) % len(self.path)
            x, y = self.path[self.waypoint]
            self.move("goto", GotoParams(x=x, y=y, speed=self.s.speed, tolerance=0.2))
            self.ops.report(self.uid, TaskState.RUNNING, self.message or "patrolling", values=self.values())
        return min(p.heartbeat, max(0.1, self.next_beat - now))


RUNNERS: dict[str, type[Runner]] = {r.kind: r for r in (WidepRunner, SpreadRunner, RelayRunner, PatrolRunner)}
