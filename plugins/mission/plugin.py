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
from erni.plugins.mission.keeper import CUE_BACK as CUE_BACK
from erni.plugins.mission.keeper import CUE_LOST as CUE_LOST
from erni.plugins.mission.keeper import LinkKeeper
from erni.plugins.mission.netaware import NetGuard
from erni.plugins.mission.remote import RemoteJob, Significance, plan, resumable
from erni.plugins.mission.team import TeamView, Territory

if TYPE_CHECKING:
    from erni.blackboard.agent import Timer
    from erni.plugins.mission.deploy import Runner

CUE_TASK = [(4, 72), (4, 79)]          # remote task received: short rising fifth


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
        self.keeper = LinkKeeper(self, self.guard, self.team, s, self.log)
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
            self.keeper.forget(task.uid)
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
            self.say(CUE_TASK)
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
        self.keeper.admit(job)

    def _start_step(self, job: RemoteJob) -> str:
        """Issue the job's current step; return why it was slowed ("" when it was not)."""
        step = job.steps[job.index]
        params, slowed = step.params, ""
        s = self.settings
        if s.network_aware and s.predict and isinstance(params, (GotoParams, ForwardParams)):
            params, slowed = self.keeper.slowed(job, params)
        job.sub = self.issue(job.uid, step.preposition, params)
        job.subs.append(job.sub)
        return slowed

    def _supersede(self, newcomer: str) -> None:
        for uid in list(self.jobs):
            self.end_job(uid, TaskState.CANCELLED, f"superseded by task {newcomer}")
        for uid in list(self.runners):
            self._end_runner(uid, TaskState.CANCELLED, f"superseded by task {newcomer}")

    def end_job(self, uid: str, state: TaskState, message: str, **values: JsonValue) -> None:
        """End remote job `uid`: withdraw its sub-tasks, report its final state."""
        job = self.jobs.pop(uid, None)
        if job is None:
            return
        for sub in job.subs:
            self.withdraw(sub)
        self.report(uid, state, message, values=values or None, force=True,
                    progress=1.0 if state == TaskState.SUCCEEDED else None)
        if not any(j.moving for j in self.jobs.values()):
            self.keeper.release()

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
                self.keeper.release()
            self.halt(None, hold=True)

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
            self.end_job(uid, TaskState.CANCELLED, f"cancelled by {who}")
            self._end_runner(uid, TaskState.CANCELLED, f"cancelled by {who}")
        self.keeper.release()
        self.report(task.uid, TaskState.RUNNING, f"stopping; cancelled {len(victims)} task(s)",
                    values={"cancelled": [*victims]})
        # a cancel of everything is a stop: it ends every motion on the robot, whoever started it;
        # a cancel of one task halts the robot only until it stands (what else runs goes on)
        self.halt(task.uid, hold=target is not None, by=task.source or None)

    def halt(self, cancel: str | None, *, hold: bool, by: str | None = None) -> None:
        """Stop the robot (holding it with `hold`); the `cancel` task succeeds once it stands."""
        uid = self.issue(cancel, "stop", StopParams(hold=hold, by=by))
        self.halts[uid] = (cancel, self.clock.wall() + self.settings.halt_timeout)

    def _stopped(self, stop: Task) -> None:
        """Somebody else stopped this robot (a BotMotion stop): end every job and deployment, so
        nothing of this mission drives it again until a new motion command arrives."""
        params = stop.params_as(StopParams)
        who = f"{params.by or stop.source or 'a stop'} (task {stop.uid})"
        for uid in list(self.jobs):
            self.end_job(uid, TaskState.CANCELLED, f"stopped by {who}")
        for uid in list(self.runners):
            self._end_runner(uid, TaskState.CANCELLED, f"stopped by {who}")
        self.keeper.release()

    def _sub_result(self, sub: Task, now: float) -> None:
        if self._own_result(sub) or self.keeper.finished(sub):
            return
        parent = self.parent_of.get(sub.uid)
        job = self.jobs.get(parent) if parent else None
        if job is not None and job.sub == sub.uid and sub.result is not None:
            self._step_result(job, sub, sub.result)

    def _own_result(self, sub: Task) -> bool:
        """Whether `sub` is one of the mission's halts or cues (then its result is taken here)."""
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
            return True
        if uid in self.says:
            if sub.done:
                del self.says[uid]
                self.withdraw(uid)
            return True
        return False

    def _step_result(self, job: RemoteJob, sub: Task, r: AllocationResult) -> None:
        """The current step of `job` reported: on to the next step, the job's end, or its progress."""
        values = dict(r.values)
        if r.state == TaskState.SUCCEEDED:
            if job.index + 1 < len(job.steps):
                job.index += 1
                self._start_step(job)
                self.report(job.uid, TaskState.RUNNING, job.held and f"holding: {job.held}" or
                            f"step {job.index + 1} of {len(job.steps)}", progress=job.progress(0.0), values=values)
            else:
                self.end_job(job.uid, TaskState.SUCCEEDED, r.message or "done", **values)
        elif r.state == TaskState.FAILED:
            self.end_job(job.uid, TaskState.FAILED, f"{sub.preposition} failed: {r.message}", **values)
        elif r.state == TaskState.CANCELLED:
            self.end_job(job.uid, TaskState.CANCELLED, f"{sub.preposition} cancelled: {r.message}", **values)
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
        wait = self.keeper.check(now, [j for j in self.jobs.values() if j.moving])
        if wait is not None:
            self.due["guard"] = now + wait + 0.01
        else:
            self.due.pop("guard", None)

    # -- audio cues and housekeeping -----------------------------------------------------

    def say(self, tones: list[tuple[int, int]]) -> None:
        """Play an audio cue (when the mission's `audio` is on)."""
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
