"""Reactive motion behaviours and the stack that arbitrates between them (paper 004, 4.2.2).

Each cycle the stack scans its behaviours from the top; the first that fires (proposes a
`Command`) drives the robot for that cycle, and only that one. The top is decided by
priority, then by push order: teleport > stop > obstacle avoidance > motion behaviours
(newest first). Obstacle avoidance fires only when the behaviour below it would drive
towards an obstacle closer than its distance, so it overrides motion commands and nothing else.

Behaviours are pure logic: they see a `Context` (the robot state, the clock, the model) and
report their outcome in `state`, `progress`, `values` and `message`; no I/O happens here.
"""

from __future__ import annotations

import functools
import math
import random
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any, ClassVar

from erni.blackboard import TaskState
from erni.blackboard.tasks import (
    AvoidParams,
    DistanceParams,
    GotoParams,
    RandomWalkParams,
    TeleportParams,
    TurnParams,
    VelocityParams,
)
from erni.plugins.motion.driver import RobotState
from erni.plugins.motion.robots import RobotModel, Transducer


@dataclass(frozen=True)
class Command:
    """What the winning behaviour asks of the robot this cycle: v (m/s), w (deg/s), a teleport."""

    v: float = 0.0
    w: float = 0.0
    teleport: tuple[float, float, float] | None = None  # x (m), y (m), heading (deg)


STOP = Command()

STILL_V = 0.01
"""A robot reporting less than this translation (m/s) and less than STILL_W rotation stands: a Stop
succeeds on such a reading, and a Pose that first shows it is published at once."""
STILL_W = 0.02
"""The rotation (rad/s) below which a robot stands (with STILL_V)."""


@dataclass
class Context:
    """What behaviours see in one cycle.

    `lead` is how far ahead of the state a command sent now acts: the SIP's age plus the
    robot's reaction time. Behaviours that must stop on a mark plan from `predicted()`, the
    pose extrapolated over the lead, so the robot ends on the mark after it has stopped.
    """

    state: RobotState
    now: float
    model: RobotModel
    below: Callable[[], Command | None] = lambda: None
    lead: float = 0.0
    commanded: tuple[float, float] = (0.0, 0.0)  # the last v (m/s) and w (deg/s) sent to the robot

    def _toward(self, value: float, target: float, up: float, down: float) -> float:
        """Where a speed moving toward `target` with the given accelerations is after `lead` seconds."""
        step = (up if abs(target) > abs(value) and value * target >= 0 else down) * self.lead
        return value + max(-step, min(step, target - value))

    def speeds(self) -> tuple[float, float]:
        """The translational (m/s) and rotational (rad/s) speeds when a command sent now starts to act:
        the robot keeps heading for the last command meanwhile, within its accelerations."""
        m, s = self.model, self.state
        v = self._toward(s.v, self.commanded[0], m.limit("accel"), m.limit("decel"))
        w = self._toward(s.w, math.radians(self.commanded[1]), math.radians(m.limit("rot_accel")),
                         math.radians(m.limit("rot_decel")))
        return v, w

    def predicted(self) -> tuple[float, float, float]:
        """The pose (x, y, theta) the robot will have when a command sent now starts to act."""
        s, t = self.state, self.lead
        v1, w1 = self.speeds()
        v, w = (s.v + v1) / 2, (s.w + w1) / 2
        th = s.theta + w * t / 2  # mid-point heading of the arc
        return s.x + v * t * math.cos(th), s.y + v * t * math.sin(th), s.theta + w * t

    def stopped(self) -> bool:
        """The robot reports no translation or rotation."""
        return abs(self.state.v) < 0.005 and abs(self.state.w) < math.radians(0.5)

    def echoes(self) -> list[tuple[float, float, float]]:
        """Each sonar echo as (x, y) in the robot's frame (m, ahead and left) and the transducer's bearing
        (worked out once per state: every behaviour of a cycle asks for the same; not to be altered)."""
        global _last_echoes
        state, model = self.state, self.model
        last = _last_echoes
        if last is not None and last[0] is state and last[1] is model:
            return last[2]
        out = []
        ring = _ring_of(model.sonar)
        for num, rng in state.sonar.items():
            t = ring[num] if 0 <= num < len(ring) else None
            if t is None:
                continue
            sx, sy, deg, cos_a, sin_a = t
            out.append((sx + rng * cos_a, sy + rng * sin_a, deg))
        _last_echoes = (state, model, out)
        return out

    def path_clearance(self, direction: int, corridor: float | None = None) -> float:
        """Return the free distance (m) ahead (direction 1) or behind (-1) within the body's corridor."""
        r = self.model.radius
        half = (corridor if corridor is not None else r + 0.05)
        best = math.inf
        for px, py, _ in self.echoes():
            ahead = px * direction
            if ahead > 0 and abs(py) <= half:
                best = min(best, max(0.0, ahead - r))
        return best

    def side_space(self) -> float:
        """Return free space on the left minus on the right (m), to choose a way out."""
        left = right = 0.0
        for num, rng in self.state.sonar.items():
            pose = self.model.sonar[num] if 0 <= num < len(self.model.sonar) else None
            if pose is None:
                continue
            a = pose[2]
            if 0 < a < 180:
                left += min(rng, 3.0) * math.sin(math.radians(a))
            elif -180 < a < 0:
                right += min(rng, 3.0) * -math.sin(math.radians(a))
        return left - right


_last_echoes: tuple[RobotState, RobotModel, list[tuple[float, float, float]]] | None = None
"""The echoes of the last state `Context.echoes` worked out (replaced whole: any thread may read it)."""


@functools.lru_cache(maxsize=16)
def _ring_of(sonar: tuple[Transducer | None, ...]) -> tuple[tuple[float, float, float, float, float] | None, ...]:
    """Each transducer as (x, y, bearing in deg, cos and sin of the bearing), by sonar number."""
    return tuple(None if t is None else (t[0], t[1], t[2], math.cos(math.radians(t[2])), math.sin(math.radians(t[2])))
                 for t in sonar)


def wrap(a: float) -> float:
    """Wrap an angle in radians to [-pi, pi)."""
    return (a + math.pi) % (2 * math.pi) - math.pi


def _brake(remaining: float, decel: float, floor: float = 0.04) -> float:
    """Return the speed from which `decel` stops the robot within `remaining`, plus a creep floor."""
    return math.sqrt(2 * decel * max(0.0, remaining)) + floor


def clip(value: float, limit: float) -> float:
    """Clip to [-limit, limit]."""
    return max(-limit, min(limit, value))


class Behaviour:
    """One reactive behaviour, usually backing one BotMotion task (`task_uid`)."""

    priority: ClassVar[int] = 0
    kind: ClassVar[str] = "behaviour"

    def __init__(self, task_uid: str | None = None, timeout: float | None = None) -> None:
        self.task_uid = task_uid
        self.timeout = timeout
        self.state = TaskState.PENDING
        self.progress = 0.0
        self.values: dict[str, Any] = {}
        self.message = ""
        self.started: float | None = None
        self.seq = 0
        self.blocked_since: float | None = None
        self.blocked_by = 0.0
        self.stalled_since: float | None = None
        self.version = 0  # bumped on every outcome change worth publishing

    def begin(self, ctx: Context) -> None:
        """Called once, in the first cycle the behaviour is on the stack."""
        self.started = ctx.now
        self.state = TaskState.RUNNING
        self.version += 1

    def propose(self, ctx: Context) -> Command | None:
        """Return the command this behaviour wants this cycle, or None if it does not fire."""
        raise NotImplementedError

    def check(self, ctx: Context) -> None:
        """Apply the time limit; called every cycle for every behaviour on the stack."""
        if self.timeout is not None and self.started is not None and ctx.now - self.started > self.timeout:
            self.fail(f"timed out after {self.timeout:g} s")

    def report(self, progress: float | None = None, message: str | None = None, **values: Any) -> None:
        """Update progress and values; significant changes bump `version`."""
        old = (round(self.progress, 2), self.message, self._rounded(self.values))
        if progress is not None:
            self.progress = max(0.0, min(1.0, progress))
        if message is not None:
            self.message = message
        self.values.update(values)
        if (round(self.progress, 2), self.message, self._rounded(self.values)) != old:
            self.version += 1

    @staticmethod
    def _rounded(values: dict[str, Any]) -> tuple[tuple[str, Any], ...]:
        return tuple(sorted((k, round(v, 2) if isinstance(v, float) else v) for k, v in values.items()))

    def succeed(self, message: str = "done", **values: Any) -> None:
        """Finish successfully."""
        if not self.state.done:
            self.values.update(values)
            self.state, self.progress, self.message = TaskState.SUCCEEDED, 1.0, message
            self.version += 1

    def fail(self, reason: str) -> None:
        """Finish with a failure reason (stalled, blocked, timed out, link lost)."""
        if not self.state.done:
            self.state, self.message = TaskState.FAILED, reason
            self.version += 1

    def cancel(self, reason: str) -> None:
        """Finish because the stack dropped the behaviour (clear)."""
        if not self.state.done:
            self.state, self.message = TaskState.CANCELLED, reason
            self.version += 1

    def overridden(self, ctx: Context, obstacle: float, limit: float) -> None:
        """Avoidance held this behaviour back this cycle; fail as blocked after `limit` s."""
        if self.blocked_since is None:
            self.blocked_since = ctx.now
        self.blocked_by = obstacle
        if ctx.now - self.blocked_since > limit:
            self.fail(f"blocked by an obstacle {obstacle:.2f} m away")
        else:
            self.report(message=f"held by obstacle avoidance ({obstacle:.2f} m)")

    def drove(self, ctx: Context) -> None:
        """This behaviour drove the robot this cycle."""
        if self.blocked_since is not None:
            self.blocked_since = None
            self.report(message="")

    def __repr__(self) -> str:
        return f"<{type(self).__name__} {self.task_uid} {self.state.value}>"


class Stop(Behaviour):
    """Halt the robot.

    A hold (`hold=True`, the network guard's pause) keeps the robot halted while on the stack and
    stays running until its task is removed; the motions underneath resume then. A stop (the
    operator's) succeeds once the robot stands: the resource has ended every motion before
    pushing it, so nothing is left to resume.
    """

    priority = 2
    kind = "stop"

    def __init__(self, task_uid: str | None = None, *, hold: bool = True, ended: int = 0) -> None:
        super().__init__(task_uid)
        self.hold = hold
        self.ended = ended

    def propose(self, ctx: Context) -> Command | None:
        s = ctx.state
        if abs(s.v) < STILL_V and abs(s.w) < STILL_W and not self.values.get("halted"):
            if self.hold:
                self.report(1.0, "halted; holding until the task is removed", halted=True)
            else:
                self.succeed(f"halted; {self.ended} motion(s) ended", halted=True, ended=self.ended)
        return STOP


class Teleport(Behaviour):
    """Set the pose once, then confirm it.

    The resource performs the teleport and tells the behaviour how (`performed`): on a
    simulator with SIM_SET_POSE, which succeeds once the SIPs and the simulator's SIMSTAT both
    put the robot at the target (a simulator that sends no SIMSTAT within `confirm` seconds is
    taken at its SIPs' word); on a real robot by re-localising odometry only, which says so.
    """

    priority = 3
    kind = "teleport"

    def __init__(self, params: TeleportParams, task_uid: str | None = None, timeout: float = 3.0,
                 confirm: float = 1.0) -> None:
        super().__init__(task_uid, timeout)
        self.target = (params.x, params.y, params.heading)
        self.confirm = confirm
        self.sent = False
        self.mode: str | None = None
        self.sent_at = math.inf

    def performed(self, mode: str, now: float) -> None:
        """The resource moved the robot (`sim`) or re-localised its odometry (`odometry`) at `now`."""
        self.mode, self.sent_at = mode, now

    def _near(self, x: float, y: float, theta: float) -> bool:
        tx, ty, hdg = self.target
        return math.hypot(x - tx, y - ty) < 0.05 and abs(wrap(theta - math.radians(hdg))) < math.radians(3)

    def propose(self, ctx: Context) -> Command | None:
        if not self.sent:
            self.sent = True
            return Command(teleport=self.target)
        s = ctx.state
        if self.mode == "odometry":
            self.succeed("odometry re-localised: this robot cannot be moved by software, its pose now reads "
                         "the target", x=s.x, y=s.y, heading=math.degrees(s.theta), moved=False)
        elif self.mode == "sim" and self._near(s.x, s.y, s.theta):
            true = s.sim_pose if s.sim_stamp >= self.sent_at else None
            if true is not None and self._near(*true):
                self.succeed("pose set; the simulator reports the robot there", x=s.x, y=s.y,
                             heading=math.degrees(s.theta), moved=True)
            elif true is None and ctx.now - self.sent_at > self.confirm:
                self.succeed("pose set (the simulator sent no SIMSTAT to confirm it)", x=s.x, y=s.y,
                             heading=math.degrees(s.theta), moved=True)
        return STOP

    def check(self, ctx: Context) -> None:
        if self.timeout is not None and self.started is not None and ctx.now - self.started > self.timeout:
            s = ctx.state
            true = s.sim_pose if s.sim_stamp >= self.sent_at else None
            where = f"; the simulator reports it at ({true[0]:.2f}, {true[1]:.2f}, " \
                    f"{math.degrees(true[2]):.0f} deg)" if true else ""
            self.fail(f"timed out after {self.timeout:g} s: the robot did not reach the new pose{where}")


class AvoidObstacles(Behaviour):
    """Override motion that would bring the robot closer than `distance` to an obstacle."""

    priority = 1
    kind = "avoid_obstacles"

    def __init__(self, params: AvoidParams, task_uid: str | None = None, blocked_timeout: float = 10.0) -> None:
        super().__init__(task_uid)
        self.distance = params.distance
        self.blocked_timeout = blocked_timeout
        self.victim: Behaviour | None = None
        self.fired = 0

    def propose(self, ctx: Context) -> Command | None:
        if self.values.get("distance") != self.distance:
            self.report(message="watching", distance=self.distance)
        wanted = ctx.below()
        if wanted is None or abs(wanted.v) < 1e-3:
            return None
        free = ctx.path_clearance(1 if wanted.v > 0 else -1)
        v = abs(ctx.state.v)
        if free >= self.distance + v * v / (2 * ctx.model.limit("decel")) + (0.1 + ctx.lead) * v:
            return None
        self.fired += 1
        self.report(obstacle=round(free, 2), overrides=self.fired)
        return Command(0.0, wanted.w)


STRAIGHT_TOLERANCE = 0.02
"""How far (m) from the requested distance a forward or backward may end, measured once stopped."""


class _Settling(Behaviour):
    """A behaviour that brakes onto a mark, waits until the robot has stopped, then checks the error.

    Phase `drive` plans from the predicted pose (`Context.predicted`), so latency does not carry
    the robot past the mark; when the prediction reaches the mark the behaviour asks for a halt
    (`settle`). Once the robot reports standing still, the error is measured: inside the
    tolerance the task succeeds, otherwise it drives again to correct, from a standstill.
    """

    def __init__(self, task_uid: str | None, timeout: float | None) -> None:
        super().__init__(task_uid, timeout)
        self.phase = "drive"
        self.settle_seq = -1
        self.corrections = 0
        self.sign = 0.0  # which way this drive goes to the mark, set when it starts

    def passed(self, ahead: float, left: float, aim: float) -> bool:
        """The (predicted) position is on the mark, or beyond it, seen from where this drive started."""
        if not self.sign:
            self.sign = 1.0 if left >= 0 else -1.0
        return ahead * self.sign <= aim

    def settle(self, ctx: Context) -> Command:
        self.phase = "settle"
        self.settle_seq = ctx.state.seq
        return STOP

    def settled(self, ctx: Context) -> bool:
        """The robot has stopped, seen in a SIP that came after the halt was asked for."""
        return ctx.state.seq > self.settle_seq and ctx.stopped()

    def redrive(self) -> None:
        self.phase = "drive"
        self.sign = 0.0
        self.corrections += 1

    def creep(self, speed: float, residual: float, floor: float) -> float:
        """A correction from a standstill goes no faster than covers 1.5 times the residual per second,
        so its own latency and braking cannot carry it past the mark again."""
        return speed if not self.corrections else min(speed, max(floor, 1.5 * abs(residual)))


class GoTo(_Settling):
    """Drive to (x, y): turn towards the goal, then drive, braking to stop inside the tolerance."""

    kind = "goto"

    def __init__(self, params: GotoParams, task_uid: str | None = None, timeout: float | None = None) -> None:
        super().__init__(task_uid, params.timeout or timeout)
        self.p = params
        self.initial = 0.0

    def begin(self, ctx: Context) -> None:
        super().begin(ctx)
        self.initial = max(1e-6, math.hypot(self.p.x - ctx.state.x, self.p.y - ctx.state.y))

    def propose(self, ctx: Context) -> Command | None:
        s = ctx.state
        dist = math.hypot(self.p.x - s.x, self.p.y - s.y)
        self.report(1.0 - dist / self.initial, distance_remaining=round(dist, 3))
        if self.phase == "settle":
            if not self.settled(ctx):
                return STOP
            if dist <= self.p.tolerance:
                self.succeed("arrived", distance_remaining=round(dist, 3), corrections=self.corrections)
                return STOP
            self.redrive()
        px, py, pth = ctx.predicted()
        dx, dy = self.p.x - px, self.p.y - py
        ahead = math.hypot(dx, dy)
        aim = self.p.tolerance / 2  # stop well inside the tolerance, not on its edge
        decel = ctx.model.limit("decel")
        err = wrap(math.atan2(dy, dx) - pth)
        coasting = max(0.0, ctx.speeds()[0]) ** 2 / (2 * decel) * math.cos(err)  # still covered once halted
        if ahead - coasting <= aim or (dist <= self.p.tolerance and ctx.stopped()):
            return self.settle(ctx)
        w = clip(math.degrees(2.5 * err), ctx.model.limit("max_rv"))
        v = 0.0
        if abs(err) < math.radians(60):
            v = self.creep(min(self.p.speed, ctx.model.limit("max_v"), _brake(ahead - aim, decel)), dist, 0.04)
            v *= math.cos(err)
        return Command(v, w)


class Turn(_Settling):
    """Turn in place by a relative angle, counting the rotation actually made."""

    kind = "turn"

    def __init__(self, params: TurnParams, task_uid: str | None = None, timeout: float | None = None) -> None:
        super().__init__(task_uid, timeout)
        self.p = params
        self.turned = 0.0
        self.last = 0.0

    def begin(self, ctx: Context) -> None:
        super().begin(ctx)
        self.last = ctx.state.theta
        if self.timeout is None:  # the turn, its accelerations, room for corrections
            rate = min(self.p.rate, ctx.model.limit("max_rv"))
            self.timeout = (abs(self.p.angle) / rate + 2 * rate / ctx.model.limit("rot_accel")) * 2 + 8.0

    def propose(self, ctx: Context) -> Command | None:
        th = ctx.state.theta
        self.turned += math.degrees(wrap(th - self.last))
        self.last = th
        left = self.p.angle - self.turned
        self.report(self.turned / self.p.angle if self.p.angle else 1.0, angle_remaining=round(left, 1))
        if self.phase == "settle":
            if not self.settled(ctx):
                return STOP
            if abs(left) <= self.p.tolerance:
                self.succeed("turned", angle_remaining=round(left, 2), turned=round(self.turned, 2),
                             corrections=self.corrections)
                return STOP
            self.redrive()
        w = math.degrees(ctx.speeds()[1])
        ahead = left - (math.degrees(ctx.state.w) + w) / 2 * ctx.lead
        aim = self.p.tolerance / 2
        rot_decel = ctx.model.limit("rot_decel")
        if self.passed(ahead - math.copysign(w * w / (2 * rot_decel), ahead), left, aim):
            return self.settle(ctx)  # halting now stops the turn on the mark
        rate = min(self.p.rate, ctx.model.limit("max_rv"), max(3.0, _brake(abs(ahead) - aim, rot_decel, 0.0)))
        rate = self.creep(rate, left, 3.0)
        return Command(0.0, math.copysign(rate, ahead))


class Straight(_Settling):
    """Drive a distance forward (or backward), holding the starting heading, ending within 2 cm."""

    def __init__(self, params: DistanceParams, direction: int, task_uid: str | None = None,
                 timeout: float | None = None) -> None:
        super().__init__(task_uid, params.timeout or timeout)
        self.p = params
        self.direction = direction
        self.kind = "forward" if direction > 0 else "backward"  # type: ignore[misc]
        self.origin = (0.0, 0.0, 0.0)

    def begin(self, ctx: Context) -> None:
        super().begin(ctx)
        self.origin = (ctx.state.x, ctx.state.y, ctx.state.theta)

    def _along(self, x: float, y: float) -> float:
        x0, y0, th0 = self.origin
        return ((x - x0) * math.cos(th0) + (y - y0) * math.sin(th0)) * self.direction

    def propose(self, ctx: Context) -> Command | None:
        s = ctx.state
        along = self._along(s.x, s.y)
        left = self.p.distance - along
        self.report(along / self.p.distance, distance_remaining=round(left, 3))
        if self.phase == "settle":
            if not self.settled(ctx):
                return STOP
            if abs(left) <= STRAIGHT_TOLERANCE:
                self.succeed("distance covered", travelled=round(along, 3), distance_remaining=round(left, 3),
                             corrections=self.corrections)
                return STOP
            self.redrive()
        px, py, _ = ctx.predicted()
        ahead = self.p.distance - self._along(px, py)
        aim = STRAIGHT_TOLERANCE / 4
        decel = ctx.model.limit("decel")
        v = ctx.speeds()[0]
        if self.passed(ahead - math.copysign(v * v / (2 * decel), ahead), left, aim):
            return self.settle(ctx)  # halting now stops the robot on the mark
        speed = self.creep(min(self.p.speed, ctx.model.limit("max_v"), _brake(abs(ahead) - aim, decel)), left, 0.04)
        w = clip(math.degrees(2.0 * wrap(self.origin[2] - s.theta)), 30.0)
        return Command(math.copysign(speed, ahead) * self.direction, w)


class Velocity(Behaviour):
    """Hold a linear and angular velocity, for `duration` or until removed."""

    kind = "velocity"

    def __init__(self, params: VelocityParams, task_uid: str | None = None) -> None:
        super().__init__(task_uid)
        self.p = params

    def propose(self, ctx: Context) -> Command | None:
        assert self.started is not None
        elapsed = ctx.now - self.started
        if self.p.duration is not None:
            if elapsed >= self.p.duration:
                self.succeed("duration elapsed", elapsed=round(elapsed, 2))
                return STOP
            self.report(elapsed / self.p.duration)
        return Command(self.p.v, self.p.w)


class RandomWalk(Behaviour):
    """Wander at cruise speed, turning away from obstacles, for `duration` or until removed."""

    kind = "randomwalk"

    def __init__(self, params: RandomWalkParams, task_uid: str | None = None, turn_distance: float = 0.8) -> None:
        super().__init__(task_uid)
        self.p = params
        self.rng = random.Random(params.seed)
        self.turn_distance = turn_distance
        self.escape = 0.0  # turning direction while escaping, 0 when cruising
        self.wander = 0.0
        self.next_wander = 0.0
        self.travelled = 0.0
        self.last: tuple[float, float] | None = None

    def propose(self, ctx: Context) -> Command | None:
        assert self.started is not None
        s = ctx.state
        if self.last is not None:
            self.travelled += math.hypot(s.x - self.last[0], s.y - self.last[1])
        self.last = (s.x, s.y)
        elapsed = ctx.now - self.started
        if self.p.duration is not None and elapsed >= self.p.duration:
            self.succeed("duration elapsed", travelled=round(self.travelled, 2))
            return STOP
        self.report(elapsed / self.p.duration if self.p.duration else 0.0, travelled=round(self.travelled, 1))
        free = ctx.path_clearance(1)
        rate = min(60.0, ctx.model.limit("max_rv"))
        if self.escape:
            if free > self.turn_distance * 1.3:
                self.escape = 0.0
            else:
                return Command(0.0, self.escape * rate)
        if free < self.turn_distance:
            side = ctx.side_space()
            self.escape = 1.0 if side > 0 or (side == 0 and self.rng.random() < 0.5) else -1.0
            return Command(0.0, self.escape * rate)
        if ctx.now >= self.next_wander:
            self.wander = self.rng.uniform(-25.0, 25.0)
            self.next_wander = ctx.now + self.rng.uniform(1.0, 3.0)
        return Command(min(self.p.speed, ctx.model.limit("max_v")), self.wander)


@dataclass
class CycleResult:
    """The outcome of one stack cycle."""

    command: Command
    winner: Behaviour | None
    finished: list[Behaviour] = field(default_factory=list)


class BehaviourStack:
    """An ordered set of behaviours; `cycle()` lets the first that fires drive the robot."""

    def __init__(self, blocked_timeout: float = 10.0, stall_timeout: float = 1.0) -> None:
        self.items: list[Behaviour] = []
        self.blocked_timeout = blocked_timeout
        self.stall_timeout = stall_timeout
        self._seq = 0

    def push(self, behaviour: Behaviour) -> None:
        """Put a behaviour on the stack (above others of the same priority)."""
        self._seq += 1
        behaviour.seq = self._seq
        self.items.append(behaviour)

    def ordered(self) -> list[Behaviour]:
        """The behaviours from the top of the stack down."""
        return sorted(self.items, key=lambda b: (b.priority, b.seq), reverse=True)

    def find(self, task_uid: str) -> Behaviour | None:
        """Return the behaviour backing a task."""
        return next((b for b in self.items if b.task_uid == task_uid), None)

    def remove(self, behaviour: Behaviour) -> None:
        """Take a behaviour off the stack."""
        if behaviour in self.items:
            self.items.remove(behaviour)

    def clear(self, keep: Callable[[Behaviour], bool] = lambda b: False) -> list[Behaviour]:
        """Empty the stack (except what `keep` accepts); return what was removed."""
        gone = [b for b in self.items if not keep(b)]
        self.items = [b for b in self.items if keep(b)]
        return gone

    def cycle(self, state: RobotState, now: float, model: RobotModel, lead: float = 0.0,
              commanded: tuple[float, float] = (0.0, 0.0)) -> CycleResult:
        """Run one control cycle: check every behaviour, let the first that fires drive."""
        order = self.ordered()
        base = Context(state, now, model, lead=lead, commanded=commanded)
        for b in order:
            if b.started is None:
                b.begin(base)
            b.check(base)
        order = [b for b in order if not b.state.done]
        cache: dict[int, tuple[int | None, Command | None]] = {}

        def first_from(i: int) -> tuple[int | None, Command | None]:
            if i not in cache:
                if i >= len(order):
                    cache[i] = (None, None)
                else:
                    ctx = Context(state, now, model, below=lambda: first_from(i + 1)[1], lead=lead,
                                  commanded=commanded)
                    cmd = order[i].propose(ctx)
                    cache[i] = (i, cmd) if cmd is not None else first_from(i + 1)
            return cache[i]

        index, command = first_from(0)
        winner = order[index] if index is not None else None
        if winner is not None and index is not None:
            winner.drove(base)
            below = cache.get(index + 1)
            if isinstance(winner, AvoidObstacles) and below and below[0] is not None:
                order[below[0]].overridden(base, winner.values.get("obstacle", 0.0), self.blocked_timeout)
            self._watch_stall(winner, state, now, command)
        finished = [b for b in self.items if b.state.done]
        for b in finished:
            self.items.remove(b)
        return CycleResult(command or STOP, winner, finished)

    def _watch_stall(self, b: Behaviour, state: RobotState, now: float, command: Command | None) -> None:
        if command is not None and abs(command.v) > 1e-3 and state.stalled:
            if b.stalled_since is None:
                b.stalled_since = now
            elif now - b.stalled_since > self.stall_timeout:
                b.fail("stalled: the wheels cannot turn (bumped into something?)")
        else:
            b.stalled_since = None
