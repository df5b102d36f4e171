"""MissionControl: remote tasks expanded into local BotMotion sub-tasks, network-aware, with deployment strategies.

- RemoteBotMotion tasks addressed to this agent (they arrive through the transport) are
  planned into BotMotion sub-tasks (`parent` = the remote task, `source` = this agent,
  no destination), performed one after the other; the sub-tasks' results are aggregated into
  the remote task's result, which changes only on significant news (see `remote.py`).
  Removing a remote task, or a RemoteBotMotion `cancel` naming one task, withdraws its
  sub-tasks and halts the robot with a BotMotion `stop` hold that is removed once the robot
  reports it halted. A `cancel` of everything is a stop: every job and deployment ends
  `cancelled` and a BotMotion `stop` ends every motion on the robot, whoever started it; a
  BotMotion `stop` from anyone else ends this mission's jobs and deployments the same way.
- Deploy tasks addressed to this agent run a strategy runner (`deploy.py`).
- Network awareness: NetWatch `network_topology` and `link_quality` tasks feed a `NetGuard`;
  when connectivity is at risk while a remote motion task runs, the configured policy
  (`hold`, `stop` or `retreat`) applies, the remote task's message says why, and `hold` /
  `retreat` resume when connectivity returns.
- Audio cues: a remote task received and every connectivity change play a BotMotion `say`.
One driving job at a time: a new remote motion or Deploy task supersedes the previous one.
Local BotMotion tasks of other plugins are never touched (mixed initiative), except by a stop.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from typing import TYPE_CHECKING, Literal

from pydantic import ConfigDict, Field, JsonValue

from erni.blackboard import (
    AllocationResult,
    NetInfo,
    Params,
    Plugin,
    Pose,
    Task,
    TaskState,
    TransactionError,
)
from erni.blackboard.objects import Model
from erni.blackboard.schemas import Peer
from erni.blackboard.tasks import CancelParams, ForwardParams, GotoParams, SayParams, StopParams
from erni.plugins.mission.netaware import NetGuard
from erni.plugins.mission.remote import RemoteJob, Significance, plan, resumable
from erni.plugins.mission.team import TeamView, Territory

if TYPE_CHECKING:
    from erni.blackboard.agent import Timer
    from erni.plugins.mission.deploy import Runner

CUE_TASK = [(4, 72), (4, 79)]          # remote task received: short rising fifth
CUE_LOST = [(10, 67), (10, 60)]        # connectivity at risk: falling
CUE_BACK = [(10, 60), (10, 67)]        # connectivity back: rising


class MissionSettings(Model):
    """Settings of MissionControl (the `[plugin.settings]` table)."""

    model_config = ConfigDict(extra="forbid")

    network_aware: bool = Field(True, description="watch topology and link quality; guard remote motion")
    policy: Literal["hold", "stop", "retreat"] = Field("hold", description="what connectivity at risk does")
    min_link_quality: float = Field(0.3, ge=0, le=1, description="best link below this = at risk")
    articulation: bool = Field(True, description="being a cut vertex of the links at least min_link_quality, or joined to the rest by a weaker link alone = at risk")
    resume_after: float = Field(3.0, ge=0, description="connectivity good this long clears the risk (s)")
    resume_quality: float | None = Field(None, ge=0, le=1, description="a risk clears only with every critical "
                                         "link at least this good (default min_link_quality + 0.2)")
    predict: bool = Field(True, description="stop before a critical link is predicted to fall below "
                          "min_link_quality (trend of its readings, speed away from its neighbour)")
    reading_latency: float = Field(2.5, ge=0, le=120, description="how late link-quality readings are (s): "
                                   "the routing daemon's averaging (about 5 Hello intervals) plus MobiNet's poll")
    braking: float = Field(0.5, gt=0, description="deceleration the guard counts on when it stops the robot (m/s^2)")
    fade_distance: float = Field(4.0, gt=0, description="the guard's model of the radio: a link's quality falls "
                                 "from 1 to 0 over this distance (m); shorter is more cautious")
    retreat_distance: float = Field(1.0, gt=0, description="retreat: go back this far along the good trail (m)")
    net_rate_hz: float = Field(2.0, gt=0, le=100, description="rate of the mission's NetWatch tasks (Hz)")
    progress_step: float = Field(0.25, gt=0, le=1, description="report progress in steps of this size")
    report_period: float = Field(5.0, gt=0, description="Deploy tasks: refresh result values this often (s)")
    goto_mode: Literal["goto", "turn_forward"] = Field("goto", description="how a remote goto is expanded")
    obstacles: list[tuple[float, float, float]] = Field(default_factory=list,
                                                        description="known obstacles: circles (x, y, r) in m")
    walls: list[tuple[float, float, float, float]] = Field(default_factory=list,
                                                           description="known walls (x1, y1, x2, y2) in m (spread)")
    obstacle_margin: float = Field(0.4, ge=0, description="clearance kept from known obstacles (m)")
    obstacle_distance: float = Field(2.0, gt=0, description="spread: desired distance to obstacles (m)")
    wall_distance: float = Field(2.5, gt=0, description="spread: desired distance to walls (m)")
    sensing_range: float | None = Field(None, gt=0, description="spread: obstacles and walls count within this "
                                        "range (m), paper 001's sensing range; none: the neighbourhood range")
    obstacle_weight: float | None = Field(None, gt=0, description="spread: weight of an obstacle or wall "
                                          "(none: as many robots as are in the neighbourhood, so a crowd "
                                          "never pins a robot against it; 1: paper 001's simulation)")
    audio: bool = Field(True, description="play audio cues (BotMotion say)")
    speed: float = Field(0.3, gt=0, le=2.0, description="cruise speed of deployment moves (m/s)")
    separation: float = Field(1.0, ge=0, description="widep: never step closer than this to a robot (m)")
    widep_step_cap: float = Field(1.0, gt=0, description="widep: longest step (m); also at most 0.4 round at `speed`")
    widep_slack: float = Field(0.2, ge=0, description="widep: keep links this much shorter than R (m)")
    widep_settle: float = Field(0.4, ge=0, description="widep: a robot counts as at rest after this long "
                                "without moving (s)")
    pose_keepalive: float = Field(1.0, ge=0, le=60, description="how often a standing robot republishes an "
                                  "unchanged Pose (s; RobotMotionControl's pose_keepalive): a position this old "
                                  "still counts as fresh when judging who is at rest")
    widep_min_step: float = Field(0.1, gt=0, description="widep: shorter steps are not driven (m)")
    widep_stall_rounds: int = Field(15, ge=1, description="widep: fail after this many rounds without "
                                    "the team coming closer to the PoI")
    position_timeout: float = Field(5.0, gt=0, description="forget other robots' positions older than this (s)")
    halt_timeout: float = Field(5.0, gt=0, description="give up waiting for the robot to halt (s)")
    control_period: float = Field(0.2, gt=0, description="spread: shortest period between commands (s)")
    relay_period: float = Field(2.0, gt=0, description="relay: seconds between decisions")
    relay_step: float = Field(1.0, gt=0, description="relay: longest move per decision (m)")
    patrol_spacing: float = Field(1.0, gt=0, description="patrol: lane spacing of the sweep (m)")
    backoff_base: float | None = Field(None, gt=0, description="patrol: back-off unit (s); "
                                       "default 2 heartbeats + 0.5 s")


class MissionControl(Plugin[MissionSettings]):
    """Seat of the robot's autonomy: two-tier tasking, network-aware behaviour, deployment."""

    def setup(self) -> None:
        me = self.agent_name
        s = self.settings
        self.remote = self.subscribe(Task, where=lambda t: t.verb in ("RemoteBotMotion", "Deploy")
                                     and t.destination == me)
        self.mine = self.subscribe(Task, where=lambda t: t.source == me and t.verb in ("BotMotion", "NetWatch")
                                   and t.destination in (None, "", me))
        self.stops = self.subscribe(Task, where=lambda t: t.verb == "BotMotion" and t.preposition == "stop"
                                    and t.source != me and t.destination in (None, "", me))
        self.poses = self.subscribe(Pose)
        self.infos = self.subscribe(NetInfo)
        self.territories = self.subscribe(Territory)
        # roles: spreading counts robots only, never a control node; a peer merely heard again is no news
        self.peers = self.subscribe(Peer, ignore=("last_heard",))
        self.team = TeamView(me, s.position_timeout, clock=self.clock)
        self.guard = NetGuard(me, min_quality=s.min_link_quality, articulation=s.articulation,
                              resume_after=s.resume_after, resume_quality=s.resume_quality,
                              latency=s.reading_latency, braking=s.braking, fade_distance=s.fade_distance,
                              predict=s.predict)
        self.jobs: dict[str, RemoteJob] = {}
        self.runners: dict[str, Runner] = {}
        self.results: dict[str, AllocationResult] = {}    # remote/deploy uid -> last result published
        self.reports: dict[str, Significance] = {}
        self.last_values: dict[str, float] = {}           # deploy uid -> when values were last refreshed
        self.issued: dict[str, Task] = {}                  # my sub-tasks not yet seen back
        self.parent_of: dict[str, str | None] = {}         # my BotMotion sub-task -> parent
        self.halts: dict[str, tuple[str | None, float]] = {}  # stop uid -> (cancel task uid, deadline)
        self.says: dict[str, float] = {}
        self.watches: dict[str, str] = {}
        self.qualities: dict[str, float] | None = None
        self.guard_stop: str | None = None
        self.retreat: str | None = None
        self.territory: Territory | None = None
        self.due: dict[str, float] = {}
        self._timer: Timer | None = None
        self._timer_at = 0.0
        for old in self.query(Task, where=lambda t: t.source == me and t.verb in ("BotMotion", "NetWatch")
                              and t.destination in (None, "", me)):
            self.remove(old)  # a restart: never repeat stale motion; watches are made afresh
        if s.network_aware:
            self.watch("network_topology")
            self.watch("link_quality")
            self.watch("node_position")  # where the neighbours are: is a motion taking it away from one?
        self.wake_every(1.0)

    # -- the Ops interface of the runners ------------------------------------------------

    def issue(self, parent: str | None, preposition: str, params: Params) -> str:
        """Publish a BotMotion sub-task of `parent`; return its uid."""
        task = Task(verb="BotMotion", preposition=preposition, params=params, source=self.agent_name,
                    parent=parent)
        self.add(task)
        self.issued[task.uid] = task
        self.parent_of[task.uid] = parent
        return task.uid

    def withdraw(self, uid: str | None) -> None:
        """Remove one of my sub-tasks (cancelling it) if it is still there."""
        if uid is None:
            return
        self.issued.pop(uid, None)
        self.parent_of.pop(uid, None)
        try:
            self.remove(uid)
        except TransactionError:
            pass

    def sub(self, uid: str | None) -> Task | None:
        """The newest known version of one of my sub-tasks (None once gone)."""
        if uid is None or uid not in self.parent_of:
            return None
        return self.mine.get(uid) or self.issued.get(uid)

    def link_qualities(self) -> dict[str, float] | None:
        """This robot's one-hop link qualities by neighbour name (latest reading; None before the first)."""
        if "link_quality" not in self.watches:
            self.watch("link_quality")
        return None if self.qualities is None else dict(self.qualities)

    def publish_territory(self, territory: Territory) -> None:
        """Publish or update this robot's patrol heartbeat."""
        if self.territory is None and self.territories.get(territory.uid) is None:
            self.add(territory)
        else:
            self.change(territory)
        self.territory = territory

    def watch(self, kind: str) -> None:
        """Start a NetWatch task of this mission (once per kind)."""
        if kind in self.watches:
            return
        task = Task(verb="NetWatch", preposition=kind, params={"rate_hz": self.settings.net_rate_hz},
                    source=self.agent_name)
        self.add(task)
        self.watches[kind] = task.uid

    def report(self, uid: str, state: TaskState, message: str = "", *, progress: float | None = None,
               values: Mapping[str, JsonValue] | None = None, force: bool = False) -> None:
        """Update a remote or Deploy task's result; publish it only when significant (or forced)."""
        task = self.remote.get(uid)
        old = self.results.get(uid)
        if task is None or task.done or (old is not None and old.state.done):
            return
        base = old.model_dump() if old else {}
        base.pop("stamp", None)
        base["state"] = state
        if message:
            base["message"] = message
        if progress is not None:
            base["progress"] = max(0.0, min(1.0, progress))
        if values is not None:
            base["values"] = {**base.get("values", {}), **values}
        new = AllocationResult(**base)
        sig = self.reports.setdefault(uid, Significance(self.settings.progress_step))
        self.results[uid] = new
        if sig.significant(new) or force:
            try:
                self.change(task.evolve(result=new), reports=[new.state.value])
            except TransactionError:
                pass

    # -- each run -----------------------------------------------------------------------

    def execute(self) -> None:
        now = self.clock.wall()  # mission times are wall-clock seconds: Pose and NetInfo stamps
        me = self.agent_name
        for peer in self.peers.added + self.peers.changed:
            if peer.role:
                self.team.role(peer.name, peer.role)
        for pose in self.poses.added + self.poses.changed:
            self.team.pose(pose)
            if pose.robot == me:
                for r in self.runners.values():
                    r.pose(pose)
        self._read_network(now)
        for stop in self.stops.added:
            if not stop.done and not stop.params_as(StopParams).hold:
                self._stopped(stop)
        for task in self.remote.removed:
            self._dropped(task)
        for task in self.remote.added:
            self._received(task, now)
        for task in self.mine.removed:
            self.issued.pop(task.uid, None)
            if self.guard_stop == task.uid:
                self.guard_stop = None
        for task in self.mine.added + self.mine.changed:
            self.issued.pop(task.uid, None)
            self._sub_result(task, now)
        for terr in self.territories.added + self.territories.changed:
            if terr.robot != me:
                for r in self.runners.values():
                    r.heard(terr, now)
        self._tick_runners(now)
        self._guard(now)
        self._housekeeping(now)
        # Poses (10 a second from the robot alone) run the mission only while a deployment or a
        # remote job acts on them; otherwise the newest is read at the next run (once a second at
        # least, and on every network reading), which is all the good-position trail needs
        self.poses.wakes = bool(self.runners or self.jobs)

    # -- network readings ----------------------------------------------------------------

    def _read_network(self, now: float) -> None:
        mine = set(self.watches.values())
        for info in self.infos.added + self.infos.changed:
            if info.kind == "node_position":
                self.team.netinfo(info)
            if info.task not in mine or info.degraded:
                continue
            if info.kind == "network_topology":
                self.guard.topology(info.links)
            elif info.kind == "link_quality":
                self.qualities = {n.name: n.quality for n in info.neighbors}
                # the guard takes the newest evidence too: a routing daemon's quality averages
                # over many Hellos, the last few show a link going bad sooner
                self.guard.quality({n.name: n.quality if n.recent is None else min(n.quality, n.recent)
                                    for n in info.neighbors}, now)

    # -- remote tasks --------------------------------------------------------------------

    def _received(self, task: Task, now: float) -> None:
        if task.done or task.uid in self.jobs or task.uid in self.runners:
            return
        resumed = self.rehydrated(task)
        if resumed and not resumable(task):
            self.report(task.uid, TaskState.FAILED, f"interrupted: {self.agent_name} restarted; a "
                        f"{task.preposition} is not resumed", force=True)
            return
        if not resumed:
            self._say(CUE_TASK)
        if task.verb == "RemoteBotMotion" and task.preposition == "cancel":
            self._cancel_task(task, now)
            return
        self._supersede(task.uid)
        if not resumed:
            self.report(task.uid, TaskState.PENDING, f"accepted by {self.agent_name}")
        if task.verb == "Deploy":
            if task.preposition in ("widep", "spread", "relay"):
                self.watch("node_position")
            from erni.plugins.mission.deploy import RUNNERS  # numpy and the strategies: at the first deployment

            runner = RUNNERS[task.preposition](task, self, self.settings, now)
            for pose in self.poses:
                if pose.robot == self.agent_name:
                    runner.pose(pose)
            for terr in self.territories:  # heartbeats that came before this runner: each is news to it
                if terr.robot != self.agent_name:
                    runner.heard(terr, now)
            self.runners[task.uid] = runner
            self.report(task.uid, TaskState.RUNNING, f"{task.preposition} started")
            self.last_values[task.uid] = now
            return
        self.jobs[task.uid] = RemoteJob(task.uid, [], resumed=resumed)
        self.later(lambda: self._begin(task.uid))  # "accepted" is committed on its own first

    def _begin(self, uid: str) -> None:
        job, task = self.jobs.get(uid), self.remote.get(uid)
        if job is None or task is None or job.steps:
            return
        mine = next((p for p in self.poses if p.robot == self.agent_name), None)
        job.steps = plan(task, mine, mode=self.settings.goto_mode, obstacles=self.settings.obstacles,
                         margin=self.settings.obstacle_margin)
        slowed = self._start_step(job)
        begun = f"resumed after a restart of {self.agent_name}" if job.resumed else "started"
        self.report(uid, TaskState.RUNNING, f"{begun}: {len(job.steps)} step(s){slowed and '; ' + slowed}",
                    progress=0.0)
        if job.moving and self.guard.state.at_risk and not self._improves(job):
            self._apply_policy([job], self.guard.state.reason)

    def _start_step(self, job: RemoteJob) -> str:
        """Issue the job's current step; return why it was slowed ("" when it was not)."""
        step = job.steps[job.index]
        params, slowed = step.params, ""
        s = self.settings
        if s.network_aware and s.predict and isinstance(params, (GotoParams, ForwardParams)):
            ends = self._ends(job)
            leaving = "" if ends is None else self.guard.leaving(*ends)
            cap = round(self.guard.safe_speed(), 2)
            if leaving and params.speed > cap:
                slowed = (f"slowed from {params.speed:g} to {cap:g} m/s: moving away from {leaving}, "
                          "its only link to the team")
                params = params.model_copy(update={"speed": cap})
        job.sub = self.issue(job.uid, step.preposition, params)
        job.subs.append(job.sub)
        return slowed

    def _supersede(self, newcomer: str) -> None:
        for uid in list(self.jobs):
            self._end_job(uid, TaskState.CANCELLED, f"superseded by task {newcomer}")
        for uid in list(self.runners):
            self._end_runner(uid, TaskState.CANCELLED, f"superseded by task {newcomer}")

    def _end_job(self, uid: str, state: TaskState, message: str, **values: JsonValue) -> None:
        job = self.jobs.pop(uid, None)
        if job is None:
            return
        for sub in job.subs:
            self.withdraw(sub)
        self.report(uid, state, message, values=values or None, force=True,
                    progress=1.0 if state == TaskState.SUCCEEDED else None)
        if not any(j.moving for j in self.jobs.values()):
            self._release_guard()

    def _end_runner(self, uid: str, state: TaskState, message: str) -> None:
        runner = self.runners.pop(uid, None)
        self.due.pop(uid, None)
        if runner is None:
            return
        runner.stop()
        self.report(uid, state, message, values=runner.values(), force=True)

    def _dropped(self, task: Task) -> None:
        """The remote source removed (cancelled) its task: withdraw everything and halt."""
        had = task.uid in self.jobs or task.uid in self.runners
        job = self.jobs.pop(task.uid, None)
        if job is not None:
            for sub in job.subs:
                self.withdraw(sub)
        runner = self.runners.pop(task.uid, None)
        self.due.pop(task.uid, None)
        if runner is not None:
            runner.stop()
        self.results.pop(task.uid, None)
        self.reports.pop(task.uid, None)
        if had:
            if not any(j.moving for j in self.jobs.values()):
                self._release_guard()
            self._halt(None, hold=True)

    def _cancel_task(self, task: Task, now: float) -> None:
        target = task.params_as(CancelParams).task
        active = list(self.jobs) + list(self.runners)
        if target is not None and target not in active:
            self.report(task.uid, TaskState.FAILED, f"cancel: no running remote task {target} on "
                        f"{self.agent_name}", force=True)
            return
        victims = [target] if target is not None else active
        who = f"{task.source} (task {task.uid})" if task.source else f"task {task.uid}"
        for uid in victims:
            self._end_job(uid, TaskState.CANCELLED, f"cancelled by {who}")
            self._end_runner(uid, TaskState.CANCELLED, f"cancelled by {who}")
        self._release_guard()
        self.report(task.uid, TaskState.RUNNING, f"stopping; cancelled {len(victims)} task(s)",
                    values={"cancelled": [*victims]})
        # a cancel of everything is a stop: it ends every motion on the robot, whoever started it;
        # a cancel of one task halts the robot only until it stands (what else runs goes on)
        self._halt(task.uid, hold=target is not None, by=task.source or None)

    def _halt(self, cancel: str | None, *, hold: bool, by: str | None = None) -> None:
        uid = self.issue(cancel, "stop", StopParams(hold=hold, by=by))
        self.halts[uid] = (cancel, self.clock.wall() + self.settings.halt_timeout)

    def _stopped(self, stop: Task) -> None:
        """Somebody else stopped this robot (a BotMotion stop): end every job and deployment, so
        nothing of this mission drives it again until a new motion command arrives."""
        params = stop.params_as(StopParams)
        who = f"{params.by or stop.source or 'a stop'} (task {stop.uid})"
        for uid in list(self.jobs):
            self._end_job(uid, TaskState.CANCELLED, f"stopped by {who}")
        for uid in list(self.runners):
            self._end_runner(uid, TaskState.CANCELLED, f"stopped by {who}")
        self._release_guard()

    def _sub_result(self, sub: Task, now: float) -> None:
        uid = sub.uid
        if uid in self.halts:
            r = sub.result  # a failed halt has a result too
            if r is not None and (r.state == TaskState.FAILED or r.values.get("halted") or r.progress >= 1.0):
                cancel, _ = self.halts.pop(uid)
                self.withdraw(uid)
                if cancel is not None:
                    ok = r.state != TaskState.FAILED
                    self.report(cancel, TaskState.SUCCEEDED if ok else TaskState.FAILED,
                                "robot halted" if ok else f"halt failed: {r.message}", force=True)
            return
        if uid in self.says:
            if sub.done:
                del self.says[uid]
                self.withdraw(uid)
            return
        if uid == self.retreat and sub.done:
            self.retreat = None
            self.withdraw(uid)
            if self.guard.state.at_risk and self.guard_stop is None:
                self.guard_stop = self.issue(None, "stop", StopParams(hold=True))
            return
        parent = self.parent_of.get(uid)
        job = self.jobs.get(parent) if parent else None
        if job is None or job.sub != uid:
            return
        r = sub.result
        if r is None:
            return
        values = dict(r.values)
        if r.state == TaskState.SUCCEEDED:
            if job.index + 1 < len(job.steps):
                job.index += 1
                self._start_step(job)
                self.report(job.uid, TaskState.RUNNING, job.held and f"holding: {job.held}" or
                            f"step {job.index + 1} of {len(job.steps)}", progress=job.progress(0.0), values=values)
            else:
                self._end_job(job.uid, TaskState.SUCCEEDED, r.message or "done", **values)
        elif r.state == TaskState.FAILED:
            self._end_job(job.uid, TaskState.FAILED, f"{sub.preposition} failed: {r.message}", **values)
        elif r.state == TaskState.CANCELLED:
            self._end_job(job.uid, TaskState.CANCELLED, f"{sub.preposition} cancelled: {r.message}", **values)
        else:
            msg = f"holding: {job.held}" if job.held else ""
            self.report(job.uid, TaskState.RUNNING, msg, progress=job.progress(r.progress), values=values)

    # -- deployment ----------------------------------------------------------------------

    def _tick_runners(self, now: float) -> None:
        for uid, runner in list(self.runners.items()):
            if now >= runner.due:
                try:
                    runner.due = now + runner.tick(now)
                except ValueError as err:  # bad strategy input: fail the task, say why
                    runner.finish(TaskState.FAILED, f"{runner.kind}: {err}")
            if runner.done:
                self.runners.pop(uid, None)
                self.due.pop(uid, None)
                continue
            if now - self.last_values.get(uid, 0.0) >= self.settings.report_period:
                self.last_values[uid] = now
                self.report(uid, TaskState.RUNNING, values=runner.values(), force=True)
            self.due[uid] = runner.due

    # -- network-aware behaviour ---------------------------------------------------------

    def _guard(self, now: float) -> None:
        if not self.settings.network_aware:
            return
        mine = self.team.mine()
        self.guard.positions({n: (p[0], p[1]) for n, p in self.team.fresh(now).items()})
        change = self.guard.update(now, None if mine is None else mine[:2])
        moving = [j for j in self.jobs.values() if j.moving]
        if change == "risk":
            self.log.info("connectivity at risk: %s", self.guard.state.reason)
            self._say(CUE_LOST)
            self._apply_policy([j for j in moving if not self._improves(j)], self.guard.state.reason)
        elif change == "clear":
            self.log.info("connectivity restored")
            self._say(CUE_BACK)
        if not self.guard.state.at_risk and any(j.held for j in moving):
            self._resume(moving)
        wait = self.guard.pending_clear_in(now)
        if wait is not None:
            self.due["guard"] = now + wait + 0.01
        else:
            self.due.pop("guard", None)

    def _resume(self, moving: list[RemoteJob]) -> None:
        """Connectivity is no longer at risk: resume the held jobs, except those whose motion would
        take the robot further from the neighbour of a critical link that shows loss."""
        free = []
        for job in moving:
            if not job.held:
                continue
            away = self._heads_away(job)
            if away:
                why = f"{self.agent_name} stays: moving on would take it further from {away}, its only link to the team"
                if job.held != why:
                    job.held = why
                    self.report(job.uid, TaskState.RUNNING, f"holding: {why}")
                continue
            free.append(job)
        if len(free) == sum(1 for j in moving if j.held):
            self._release_guard()
        for job in free:
            job.held = ""
            self.report(job.uid, TaskState.RUNNING, "resumed: connectivity restored")

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

    def _improves(self, job: RemoteJob) -> bool:
        """A motion towards the neighbour of every critical link: it improves connectivity."""
        if not job.steps or not self.guard.state.critical or not self.guard.where:
            return False
        mine = self.team.mine()
        if mine is None or not isinstance(job.steps[job.index].params, GotoParams):
            return False
        p = job.steps[job.index].params
        assert isinstance(p, GotoParams)
        return all(n in self.guard.where and math.dist((p.x, p.y), self.guard.where[n]) + 0.3
                   < math.dist(mine[:2], self.guard.where[n]) for n in self.guard.state.critical)

    def _apply_policy(self, jobs: list[RemoteJob], reason: str) -> None:
        if not jobs:
            return
        policy = self.settings.policy
        if policy == "stop":
            for job in jobs:
                self._end_job(job.uid, TaskState.FAILED, f"stopped: {reason}")
            self._halt(None, hold=False, by="the network guard")
            return
        mine = self.team.mine()
        target = None if mine is None else self.guard.retreat_point(mine[:2], self.settings.retreat_distance)
        if policy == "retreat" and target is not None and mine is not None and \
                ((mine[0] - target[0]) ** 2 + (mine[1] - target[1]) ** 2) ** 0.5 > 0.2:
            if self.retreat is None:
                self.retreat = self.issue(None, "goto", GotoParams(x=round(target[0], 3), y=round(target[1], 3),
                                                                   speed=self.settings.speed, tolerance=0.15))
            why = f"retreating to ({target[0]:.2f}, {target[1]:.2f}): {reason}"
        else:
            if self.guard_stop is None:
                self.guard_stop = self.issue(None, "stop", StopParams(hold=True))
            why = f"holding: {reason}"
        for job in jobs:
            job.held = reason
            self.report(job.uid, TaskState.RUNNING, why)

    def _release_guard(self) -> None:
        self.withdraw(self.guard_stop)
        self.guard_stop = None
        self.withdraw(self.retreat)
        self.retreat = None

    # -- audio cues and housekeeping -----------------------------------------------------

    def _say(self, tones: list[tuple[int, int]]) -> None:
        if self.settings.audio:
            uid = self.issue(None, "say", SayParams(tones=tones))
            self.says[uid] = self.clock.wall() + 10.0

    def _housekeeping(self, now: float) -> None:
        for uid, (cancel, deadline) in list(self.halts.items()):
            if now >= deadline:
                del self.halts[uid]
                self.withdraw(uid)
                if cancel is not None:
                    self.report(cancel, TaskState.FAILED, f"the robot did not report halting within "
                                f"{self.settings.halt_timeout:g} s", force=True)
        for uid, deadline in list(self.says.items()):
            if now >= deadline:
                del self.says[uid]
                self.withdraw(uid)
        for uid in list(self.results):
            if uid not in self.jobs and uid not in self.runners and self.results[uid].state.done:
                self.results.pop(uid, None)
                self.reports.pop(uid, None)
        soon = [t for t in list(self.due.values()) + [d for _, d in self.halts.values()] if t > now]
        if not soon:
            return
        when = min(soon)
        if self._timer is not None and self._timer_at <= when + 1e-3 and self._timer_at > now:
            return  # an earlier wake-up is already scheduled
        if self._timer is not None:
            self._timer.cancel()
        self._timer = self.wake_in(max(0.02, when - now))
        self._timer_at = when

    def teardown(self) -> None:
        if self._timer is not None:
            self._timer.cancel()
