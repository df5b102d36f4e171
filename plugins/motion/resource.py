"""RobotMotionResource: the behaviour-stack thread and the poll thread around one robot driver.

The stack thread (`motion-stack-<robot>`) services the behaviour stack: it turns BotMotion
tasks into behaviours, lets the winning behaviour drive the robot through the driver, and
records each task's outcome. While it steers it cycles on each new SIP, as ARIA's robot
cycle does (at most `rate_hz` cycles a second, and after one and a half SIP intervals without a
SIP it cycles anyway, so a lost link and the behaviours' timeouts are noticed); a task or a
cancellation is taken at once. With nothing to steer (no task, the robot halted and standing)
it cycles every `idle_period` until a task wakes it. The poll thread
(`motion-poll-<robot>`) hands the latest robot state and the outcome changes to `publish` at
`pose_rate_hz` (at once for final outcomes): a state that differs from the last one handed over
only in its stamp (a standing robot) is handed over again after `pose_keepalive` only. While
the stack thread steers, it hands over the state of the SIP it just cycled on itself, when that
Pose is due, so a SIP wakes two threads (reader and stack), not three; the poll thread then
only sees to what comes between SIPs (outcomes, keep-alives, a SIP just ahead of its time). A reading
that starts or stops motion (`starts_or_stops`) is handed over at once by whichever thread sees it,
not at the next Pose due, as a final outcome is. Neither
thread touches the blackboard itself: `publish` does, in its own short transactions, so serial
I/O never happens inside one.
"""

from __future__ import annotations

import logging
import math
import threading
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from typing import Any

from erni.blackboard import Task, TaskState
from erni.blackboard.clock import monotonic
from erni.blackboard.errors import UsageError
from erni.blackboard.tasks import (
    AvoidParams,
    BackwardParams,
    ForwardParams,
    GotoParams,
    RandomWalkParams,
    SayParams,
    StopParams,
    TeleportParams,
    TurnParams,
    VelocityParams,
)
from erni.plugins.motion.behaviours import (
    STILL_V,
    STILL_W,
    AvoidObstacles,
    Behaviour,
    BehaviourStack,
    Command,
    GoTo,
    RandomWalk,
    Stop,
    Straight,
    Teleport,
    Turn,
    Velocity,
)
from erni.plugins.motion.driver import ArcosDriver, RobotState

log = logging.getLogger("erni.motion.resource")


@dataclass(frozen=True)
class TaskUpdate:
    """A change of a task's outcome, to be published as its AllocationResult."""

    uid: str
    state: TaskState
    progress: float = 0.0
    values: dict[str, Any] = field(default_factory=dict)
    message: str = ""


Publish = Callable[[list[TaskUpdate], RobotState | None], None]


def same_reading(a: RobotState, b: RobotState) -> bool:
    """True when two states differ at most in their stamps: nothing a Pose shows has changed."""
    return (a.x == b.x and a.y == b.y and a.theta == b.theta and a.v == b.v and a.w == b.w
            and a.battery == b.battery and a.stall_left == b.stall_left and a.stall_right == b.stall_right
            and a.bumpers == b.bumpers and a.motors_enabled == b.motors_enabled and a.sonar == b.sonar)


AT_REST = 1e-3
"""Translation (m/s) and rotation (rad/s) below which a robot reports no motion at all."""


def at_rest(s: RobotState) -> bool:
    """The robot reports no motion at all."""
    return abs(s.v) < AT_REST and abs(s.w) < AT_REST


def standing(s: RobotState) -> bool:
    """The robot stands as a Stop judges it (below STILL_V and STILL_W)."""
    return abs(s.v) < STILL_V and abs(s.w) < STILL_W


def starts_or_stops(shown: RobotState | None, state: RobotState | None) -> bool:
    """`state` starts motion (the Pose shown reports none, `state` some) or stops it (the Pose shown
    moves, `state` stands as a Stop judges it). Between the two levels neither: a robot shown standing
    at 5 mm/s starts nothing at 3 mm/s, nor stops again at 0."""
    if shown is None or state is None:
        return False
    return (at_rest(shown) and not at_rest(state)) or (not standing(shown) and standing(state))


class RobotMotionResource:
    """Executes BotMotion tasks on one robot; thread-safe `submit`/`cancel`, `close()` joins."""

    def __init__(self, driver: ArcosDriver, publish: Publish, *, name: str = "robot",
                 rate_hz: float = 20.0, pose_rate_hz: float = 10.0, avoid_distance: float = 0.4,
                 blocked_timeout: float = 10.0, stall_timeout: float = 1.0, link_grace: float = 2.0,
                 default_timeout: float | None = None, teleport: str = "auto", resend: float = 0.5,
                 latency: float | None = None, pose_keepalive: float = 1.0, idle_period: float = 1.0,
                 progress_interval: float = 0.5, clock: Callable[[], float] = monotonic) -> None:
        if rate_hz <= 0 or pose_rate_hz <= 0:
            raise UsageError(f"rate_hz and pose_rate_hz must be > 0, got {rate_hz} and {pose_rate_hz}")
        if teleport not in ("auto", "sim", "odometry"):
            raise UsageError(f"teleport: expected 'auto', 'sim' or 'odometry', got {teleport!r}")
        if latency is not None and not 0 <= latency <= 2:
            raise UsageError(f"latency: expected seconds in 0..2, got {latency}")
        if pose_keepalive <= 0 or idle_period <= 0 or progress_interval < 0:
            raise UsageError(f"pose_keepalive and idle_period must be > 0 s and progress_interval >= 0 s, got "
                             f"{pose_keepalive}, {idle_period} and {progress_interval}")
        self.driver = driver
        self.publish = publish
        self.name = name
        self.period = 1.0 / rate_hz
        self.pose_period = 1.0 / pose_rate_hz
        self.avoid_distance = avoid_distance
        self.link_grace = link_grace
        self.default_timeout = default_timeout
        self.teleport = teleport
        self.resend = resend
        self.latency = latency
        self.pose_keepalive = pose_keepalive
        self.progress_interval = progress_interval
        self._told: dict[str, tuple[TaskState, float]] = {}  # task uid -> state and time last published
        self._emitted: dict[str, TaskState] = {}  # task uid -> its last state handed over (stack thread)
        self.idle_period = idle_period
        self.clock = clock
        self.stack = BehaviourStack(blocked_timeout=blocked_timeout, stall_timeout=stall_timeout)
        self._inbox: deque[tuple[str, Any]] = deque()
        self._wake = threading.Event()
        self._poll_wake = threading.Event()
        self._steering = False  # the stack thread waits for SIPs (read by the reader thread)
        self._new_sip = False   # a SIP came since the last cycle
        self._shown: RobotState | None = None  # the state last handed to `publish` (read by the reader thread)
        # one publication at a time (poll or stack thread): what was handed over, when, and when the next Pose is due
        self._pub_lock = threading.Lock()
        self._last_state: RobotState | None = None
        self._shown_at = -math.inf
        self._due_at = -math.inf  # when the next Pose may be handed over (`_next_due`)
        self._kept = False  # progress held back by progress_interval: the poll thread comes back for it
        self._stop = threading.Event()
        self._lock = threading.Lock()
        self._updates: dict[str, TaskUpdate] = {}
        self._published: dict[int, int] = {}
        self._last_sent: tuple[float, float] | None = None
        self._last_sent_at = 0.0
        self._link_down_since: float | None = None
        self._says: dict[str, tuple[bytes, float]] = {}  # task uid -> tones not yet sent, and until when to try
        self._threads: list[threading.Thread] = []
        self.cycles = 0
        self.stale_cycles = 0  # cycles while steering with no new SIP: a task, or 1.5 SIP intervals without one
        self.winner: Behaviour | None = None
        if avoid_distance > 0:
            self.stack.push(self._default_avoid())

    def _default_avoid(self) -> AvoidObstacles:
        return AvoidObstacles(AvoidParams(distance=self.avoid_distance),
                              blocked_timeout=self.stack.blocked_timeout)

    # --- life cycle ---------------------------------------------------------------------

    def start(self) -> RobotMotionResource:
        """Open the driver (without waiting for the robot) and start both threads."""
        chained = self.driver.on_sip
        if chained is None:
            self.driver.on_sip = self._sip
        else:
            def both(state: RobotState) -> None:
                self._sip(state)
                chained(state)
            self.driver.on_sip = both
        self.driver.open(wait=False)
        for target, kind in ((self._control_loop, "stack"), (self._poll_loop, "poll")):
            t = threading.Thread(target=target, name=f"motion-{kind}-{self.name}", daemon=True)
            t.start()
            self._threads.append(t)
        return self

    def close(self) -> None:
        """Stop the threads (joined), halt the robot and close the driver."""
        self._stop.set()
        self._wake.set()
        self._poll_wake.set()
        for t in self._threads:
            t.join(timeout=5)
        self._threads.clear()
        self.driver.close()

    def submit(self, task: Task) -> None:
        """Queue a BotMotion task; the stack thread picks it up at once."""
        self._inbox.append(("submit", task))
        self._wake.set()

    def cancel(self, uid: str) -> None:
        """Drop the behaviour of a task that was removed (cancelled) by its requester."""
        self._inbox.append(("cancel", uid))
        self._wake.set()

    # --- the stack thread ---------------------------------------------------------------

    def _control_loop(self) -> None:
        last = -math.inf  # when the last cycle ran
        last_sip = -math.inf  # when the last cycle on a new SIP ran (the rate limit counts from it)
        while not self._stop.is_set():
            if self.idle():  # nothing to steer: sleep until a task comes (or a slow check is due)
                self._steering = False
                delay = last + self.idle_period - self.clock()
                if delay > 0 and not self._inbox:
                    self._wake.wait(delay)
                    self._wake.clear()
                if self._inbox:
                    last_sip = -math.inf  # a task to a standing robot: its steering starts its own pace
            else:
                self._steering = True
                self._await_sip(last, last_sip)
            if self._stop.is_set():
                break
            now = last = self.clock()
            if self._new_sip:
                last_sip = now
            elif self._steering:
                self.stale_cycles += 1
            self._new_sip = False  # the state read by this cycle is at least as new as the SIP that woke it
            try:
                self._drain_inbox(now)
                self._cycle(now)
            except Exception:
                log.exception("%s: behaviour stack cycle failed", self.name)
            if self._steering:
                try:
                    self._publish_sip()
                except Exception:  # the stack thread outlives any publication
                    log.exception("%s: publishing the pose after a cycle failed", self.name)
        if self.driver.connected:
            self.driver.stop()

    def _await_sip(self, last: float, last_sip: float = -math.inf) -> None:
        """While steering: until a new SIP at least `period` after the last cycle on a SIP, a task
        or a cancellation (at once), or one and a half SIP intervals without a SIP after the last
        cycle. The rate counts SIP cycles only, and a task to a standing robot starts it afresh:
        neither the cycle that took the task nor the last cycle of the steering before holds back
        the SIP that shows the task's effect (at 100 Hz they held the first Pose showing motion
        back by half a period on average)."""
        fallback = last + max(self.period, 1.5 * self.driver.sip_interval)
        earliest = last_sip + self.period
        while not self._stop.is_set() and not self._inbox:
            now = self.clock()
            if now >= fallback or (self._new_sip and now >= earliest):
                return
            self._wake.wait((earliest if self._new_sip else fallback) - now)
            self._wake.clear()

    def idle(self) -> bool:
        """Nothing to steer: no task's behaviour, nothing queued, stopped by us and standing still.

        Then the stack thread cycles every `idle_period` instead of every `period` (a cycle
        would only repeat the halt); a submitted or cancelled task wakes it at once.
        """
        state = self.driver.state
        return (not self._inbox and not self._says and self._last_sent == (0.0, 0.0) and self.driver.connected and state is not None
                and at_rest(state)
                and all(b.task_uid is None for b in self.stack.items))

    def _drain_inbox(self, now: float) -> None:
        while self._inbox:
            op, item = self._inbox.popleft()
            if op == "cancel":
                b = self.stack.find(item)
                self._emitted.pop(item, None)
                self._says.pop(item, None)
                if b is not None:
                    self.stack.remove(b)
                    self._published.pop(id(b), None)
                    if isinstance(b, AvoidObstacles):
                        self._restore_avoid()
            else:
                self._accept(item, now)

    def _accept(self, task: Task, now: float) -> None:
        if task.done or self.stack.find(task.uid) is not None:
            return
        prep = task.preposition
        if prep == "clear":
            gone = self.stack.clear(keep=lambda b: b.task_uid is None)
            for b in gone:
                b.cancel(f"cleared by task {task.uid}")
                self._record(b)
            self._emit(TaskUpdate(task.uid, TaskState.SUCCEEDED, 1.0, {"cleared": len(gone)},
                                  f"behaviour stack cleared ({len(gone)} removed)"))
            return
        if prep == "stop":
            p = task.params_as(StopParams)
            ended = 0 if p.hold else self._end_motions(task.uid, p.by or task.source)
            self.stack.push(Stop(task.uid, hold=p.hold, ended=ended))
            return
        if prep == "say":
            tones = bytes(b for d, n in task.params_as(SayParams).tones
                          for b in (max(1, min(255, d)), max(1, min(127, n))))
            self._says[task.uid] = (tones, now + self.link_grace)
            self._play_says(now)
            return
        if prep == "avoid_obstacles":
            enabled = task.params_as(AvoidParams).enabled
            for b in [b for b in self.stack.items if isinstance(b, AvoidObstacles)]:
                self.stack.remove(b)
                if b.task_uid:
                    b.cancel(f"avoidance replaced by task {task.uid}")
                    self._record(b)
            if not enabled:
                self._emit(TaskUpdate(task.uid, TaskState.SUCCEEDED, 1.0, {"enabled": False},
                                      "obstacle avoidance off"))
                return
        behaviour = self._behaviour(task)
        if behaviour is None:
            self._emit(TaskUpdate(task.uid, TaskState.FAILED, 0.0, {},
                                  f"RobotMotionControl cannot perform BotMotion {prep!r}"))
            return
        self.stack.push(behaviour)

    def _end_motions(self, stop: str, by: str | None) -> int:
        """An operator's stop: cancel every motion on the stack, whoever started it (obstacle avoidance
        and holds stay); return how many ended."""
        who = f"{by} (task {stop})" if by else f"task {stop}"
        gone = self.stack.clear(keep=lambda b: isinstance(b, (AvoidObstacles, Stop)))
        for b in gone:
            b.cancel(f"stopped by {who}")
            self._record(b)
        return sum(1 for b in gone if b.task_uid is not None)

    def _play_says(self, now: float) -> None:
        """Send the SAYs waiting for the link; one that could not be sent for `link_grace` s fails."""
        for uid, (tones, until) in list(self._says.items()):
            if self.driver.connected and self.driver.say(tones):
                del self._says[uid]
                self._emit(TaskUpdate(uid, TaskState.SUCCEEDED, 1.0, {"tones": len(tones) // 2}, "tones played"))
            elif now >= until:
                del self._says[uid]
                why = self.driver.last_error or "no answer from the robot"
                self._emit(TaskUpdate(uid, TaskState.FAILED, 0.0, {},
                                      f"link lost: SAY not sent within {self.link_grace:g} s ({why})"))

    def _behaviour(self, task: Task) -> Behaviour | None:
        uid, prep, params = task.uid, task.preposition, task.params_as
        blocked = self.stack.blocked_timeout
        makers: dict[str, Callable[[], Behaviour]] = {
            "goto": lambda: GoTo(params(GotoParams), uid, self.default_timeout),
            "turn": lambda: Turn(params(TurnParams), uid, self.default_timeout),
            "forward": lambda: Straight(params(ForwardParams), 1, uid, self.default_timeout),
            "backward": lambda: Straight(params(BackwardParams), -1, uid, self.default_timeout),
            "velocity": lambda: Velocity(params(VelocityParams), uid),
            "randomwalk": lambda: RandomWalk(params(RandomWalkParams), uid,
                                             turn_distance=max(0.6, 2 * self.avoid_distance)),
            "teleport": lambda: Teleport(params(TeleportParams), uid),
            "avoid_obstacles": lambda: AvoidObstacles(params(AvoidParams), uid, blocked),
        }
        maker = makers.get(prep)
        return maker() if maker else None

    def _restore_avoid(self) -> None:
        if self.avoid_distance > 0 and not any(isinstance(b, AvoidObstacles) for b in self.stack.items):
            self.stack.push(self._default_avoid())

    def _cycle(self, now: float) -> None:
        if self._says:
            self._play_says(now)
        state = self.driver.state
        if not self.driver.connected or state is None:
            self._link_down(now)
            return
        self._link_down_since = None
        result = self.stack.cycle(state, now, self.driver.model, self.lead(state, now), self._last_sent or (0.0, 0.0))
        self.cycles += 1
        self.winner = result.winner
        cmd = result.command
        if cmd.teleport is not None:
            x, y, heading = cmd.teleport
            mode = self.teleport_mode()
            if mode == "sim":
                self.driver.sim_set_pose(x, y, heading)
            else:
                self.driver.relocalise(x, y, math.radians(heading))
            if isinstance(result.winner, Teleport):
                result.winner.performed(mode, now)
            self._last_sent = None
        self._drive(cmd, now)
        for b in result.finished:
            if isinstance(b, AvoidObstacles):
                self._restore_avoid()
        for b in list(self.stack.items) + result.finished:
            self._record(b)

    def teleport_mode(self) -> str:
        """How a teleport is done: `sim` (SIM_SET_POSE) on a simulator, `odometry` on a real robot."""
        if self.teleport != "auto":
            return self.teleport
        return "sim" if self.driver.is_simulator else "odometry"

    def lead(self, state: RobotState, now: float) -> float:
        """How far ahead of `state` a command sent now acts (s): the SIP's age, a SIP period (the
        robot measured the SIP's pose up to a period before sending it and acts on a command at its
        next cycle), and the time to the next correction (the next SIP, or `period` if longer)."""
        if self.latency is not None:
            return self.latency
        interval = self.driver.sip_interval
        return max(0.0, now - state.stamp) + interval + max(self.period, interval)

    def _drive(self, cmd: Command, now: float) -> None:
        wanted = (round(cmd.v, 3), float(round(cmd.w)))
        if wanted != self._last_sent or now - self._last_sent_at > self.resend:
            if self.driver.vel(cmd.v) and self.driver.rvel(cmd.w):
                self._last_sent, self._last_sent_at = wanted, now

    def _link_down(self, now: float) -> None:
        if self._link_down_since is None:
            self._link_down_since = now
            self._last_sent = None
        if now - self._link_down_since < self.link_grace:
            return
        reason = f"link lost: {self.driver.last_error or 'no answer from the robot'}"
        for b in self.stack.clear(keep=lambda b: b.task_uid is None):
            b.fail(reason)
            self._record(b)

    # --- outcomes -----------------------------------------------------------------------

    def _record(self, b: Behaviour) -> None:
        if b.task_uid is None or self._published.get(id(b)) == b.version:
            return
        self._published[id(b)] = b.version
        if b.state.done:
            self._published.pop(id(b), None)
        self._emit(TaskUpdate(b.task_uid, b.state, b.progress, dict(b.values), b.message))

    def _emit(self, update: TaskUpdate) -> None:
        state = self.driver.state
        if state is not None and state.damage:  # the task's requester sees that the robot's data arrives damaged
            update = replace(update, values={**update.values, "line_damage": dict(state.damage)})
        with self._lock:
            self._updates[update.uid] = update
        if update.state.done:
            self._emitted.pop(update.uid, None)
        elif self._emitted.get(update.uid) == update.state:
            return  # progress alone: the poll thread takes it on its next round
        else:
            self._emitted[update.uid] = update.state
        self._poll_wake.set()

    def _final_pending(self) -> bool:
        with self._lock:
            return any(u.state.done for u in self._updates.values())

    def take_updates(self) -> list[TaskUpdate]:
        """Return and forget the outcome changes not yet published."""
        with self._lock:
            updates = list(self._updates.values())
            self._updates.clear()
        return updates

    def _due(self, updates: list[TaskUpdate], now: float) -> tuple[list[TaskUpdate], bool]:
        """The updates to publish now: a new state at once, progress alone at most every
        `progress_interval` (the rest is kept, newest first); and whether any was kept."""
        due, kept = [], False
        for u in updates:
            told = self._told.get(u.uid)
            if u.state.done or told is None or told[0] != u.state or now - told[1] >= self.progress_interval:
                due.append(u)
                if u.state.done:
                    self._told.pop(u.uid, None)
                else:
                    self._told[u.uid] = (u.state, now)
            else:
                kept = True
                with self._lock:
                    self._updates.setdefault(u.uid, u)  # a newer one meanwhile wins
        if len(self._told) > 256:  # tasks removed while running leave no final outcome: forget them
            self._told = {k: v for k, v in self._told.items() if now - v[1] < 60.0}
        return due, kept

    # --- the poll thread ----------------------------------------------------------------

    def _sip(self, state: RobotState) -> None:
        """Reader thread, per SIP: wake the stack thread while it steers (it publishes the Pose
        after its cycle), else the poll thread when the reading differs from the last Pose."""
        if self._steering:
            self._new_sip = True
            self._wake.set()
            return
        shown = self._shown
        if shown is None or not same_reading(state, shown):
            self._poll_wake.set()

    def _publish_sip(self) -> None:
        """Stack thread, after a cycle while steering: hand over the state it cycled on when its
        Pose is due, or at once when it starts or stops motion. A SIP well ahead of its due time is
        skipped (a later SIP is due when it comes); one just ahead, or one that finds the poll
        thread publishing, is left to the poll thread. Never waits: a stop must not queue behind a
        publication."""
        event = starts_or_stops(self._shown, self.driver.state)
        ahead = 0.0 if event else self._due_at - self.clock()
        if ahead > 0.25 * self.driver.sip_interval:
            return
        if ahead > 0 or not self._pub_lock.acquire(blocking=False):
            self._poll_wake.set()
            return
        try:
            self._publish_round()
        finally:
            self._pub_lock.release()

    def _publish_round(self) -> None:
        """Hand the due outcome changes and a fresh state to `publish` (the caller holds `_pub_lock`)."""
        # first: the state read next is at least as new as theirs
        updates, self._kept = self._due(self.take_updates(), self.clock())
        state = self.driver.state  # a new SIP, or the last one re-based (teleport, re-localisation)
        fresh = state if state is not None and state is not self._last_state else None
        if fresh is not None:
            self._last_state = fresh
            now = self.clock()
            shown = self._shown
            if (not updates and shown is not None and now - self._shown_at < self.pose_keepalive
                    and same_reading(fresh, shown)):
                fresh = None  # only the stamp changed (a standing robot): the keep-alive will tell
            else:
                self._shown, self._shown_at = fresh, now
        if fresh is None and not updates:
            return
        if fresh is not None:
            self._due_at = self._next_due(fresh)
        try:
            self.publish(updates, fresh)
        except Exception:
            log.exception("%s: publishing pose and task results failed", self.name)

    def _next_due(self, state: RobotState) -> float:
        """When the Pose after `state` may go: every k-th SIP, k SIP intervals (at least one) as
        near the pose period as there are, half an interval early so a jittered SIP is not held
        back; counted from the SIP's own time, so that a Pose handed over between SIPs (with an
        outcome) sets no phase of its own, and never within half a period of this one."""
        interval = max(1e-3, self.driver.sip_interval)
        every = max(1, round(self.pose_period / interval)) * interval
        return max(state.stamp + every - 0.5 * interval, self.clock() + 0.5 * self.pose_period)

    def _poll_loop(self) -> None:
        while not self._stop.is_set():
            # woken by a changed reading or a task outcome; a standing robot's Pose waits for the keep-alive
            limit = (self.pose_period if self._kept
                     else max(self.pose_period, self._shown_at + self.pose_keepalive - self.clock()))
            self._poll_wake.wait(limit)
            # at most pose_rate_hz publications a second; a final outcome, or a reading that starts or
            # stops motion, goes at once (also when it comes during the wait)
            self._poll_wake.clear()
            while not self._stop.is_set():
                rest = self._due_at - self.clock()
                if rest <= 0 or self._final_pending() or starts_or_stops(self._shown, self.driver.state):
                    break
                self._poll_wake.wait(rest)
                self._poll_wake.clear()
            if self._stop.is_set():
                break
            with self._pub_lock:
                self._publish_round()
        updates = self.take_updates()
        if updates:
            try:
                self.publish(updates, None)
            except Exception:
                log.exception("%s: publishing final task results failed", self.name)
