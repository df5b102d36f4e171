"""Agents mode: a scenario's team as real agent processes, tasked and watched the way a user does it.

`TeamRun` starts a `Team` (one agent process per robot, each with its transport, motion over
ARCOS to its simulated robot, MobiNet over SNMP and the mission plugin; a control node),
sends tasks through the control node with the transport's client, and collects every result
update the control node forwards (`results`: the newest per task; `history`: every change,
with the time it arrived). Optionally it leases a watch from one robot agent and keeps the
Poses that agent publishes (`poses`: what the agent itself sees through its driver, odometry
and battery included). The simulator's truth (positions, radio components) comes from the
team's feed samples (`team.samples`), used only to judge the run, never by the agents.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

from erni.blackboard import AllocationResult, TaskState
from erni.sim.experiments import Progress
from erni.sim.scenario import Scenario, ScenarioError
from erni.sim.team import Team, plugin_available


@dataclass
class Update:
    """One result change of a task, as the control node forwarded it."""

    t: float          # s since the tasks were sent (team clock)
    uid: str
    robot: str
    result: AllocationResult


@dataclass
class PoseSample:
    """One Pose a robot agent published (its own odometry and battery), as the watch delivered it."""

    t: float          # s since the tasks were sent (team clock, when it arrived)
    stamp: float      # the agent's own time stamp (epoch s)
    x: float
    y: float
    theta: float
    v: float
    w: float
    battery: float | None


@dataclass
class TeamRun:
    """A team of agent processes for one experiment run."""

    scenario: Scenario
    progress: Progress
    mission: dict[str, Any] = field(default_factory=dict)   # mission settings for every robot
    robot: dict[str, Any] = field(default_factory=dict)     # simulated robot settings (inputs)
    transport: dict[str, Any] = field(default_factory=dict)
    use_mission: bool = True
    feed_hz: float = 10.0
    netns: bool = False    # the real-mesh tier (`erni sim --netns`): namespaces, babeld, MobiNet reading babeld
    heard: list[str] | None = None  # the robots the start waits for the control node to hear (default: every reachable one)
    team: Team | None = None
    t0: float = 0.0
    results: dict[str, AllocationResult] = field(default_factory=dict)
    history: list[Update] = field(default_factory=list)
    owner: dict[str, str] = field(default_factory=dict)     # task uid -> robot
    poses: list[PoseSample] = field(default_factory=list)
    _watch: tuple[str, int] | None = None
    _renew: float = 0.0

    def start(self, timeout: float = 120.0) -> TeamRun:
        """Start the team; return when the control node hears every reachable robot."""
        if self.use_mission and not plugin_available("erni.plugins.mission", "MissionControl"):
            raise ScenarioError("agents mode needs the mission plugin (erni.plugins.mission.MissionControl)")
        self.team = Team(self.scenario, headless=True, control_port=0, record=True, ui=False,
                         mission=self.use_mission, mission_settings={"audio": False, **self.mission},
                         robot_settings=self.robot, transport=self.transport or None, feed_hz=self.feed_hz,
                         netns=self.netns)
        self.team.start(lambda label, done, total: self.progress(f"start: {label}", done, total), timeout=timeout,
                        heard=self.heard)
        self.t0 = self.team.elapsed()
        return self

    @property
    def now(self) -> float:
        """Seconds since `start` returned (the team's clock)."""
        assert self.team is not None
        return self.team.elapsed() - self.t0

    def send(self, robot: str, verb: str, preposition: str, **params: Any) -> str:
        """Send a task to `robot` through the control node; return its uid."""
        assert self.team is not None
        task = self.team.send_task(robot, verb, preposition, **params)
        self.owner[task.uid] = robot
        return str(task.uid)

    def watch(self, robot: str) -> None:
        """Lease a watch from `robot`'s own agent and keep the Poses it publishes."""
        assert self.team is not None
        peer = self.team.peers().get(robot)
        if peer is None or not peer.address:
            raise ScenarioError(f"{robot}: the control node does not know its address")
        host, _, port = peer.address.rpartition(":")
        self._watch = (host, int(port))
        self._renew = 0.0

    def pump(self, seconds: float) -> None:
        """Take in what the control node and watched agents sent during the next `seconds` s."""
        from erni.blackboard.schemas import ResultUpdate, WatchEvent, WatchRequest

        assert self.team is not None
        client = self.team.client()
        end = time.monotonic() + seconds
        while True:
            if self._watch is not None and time.monotonic() >= self._renew:
                client.send(self._watch, "watch.request", WatchRequest(lease=10.0))
                self._renew = time.monotonic() + 4.0
            left = end - time.monotonic()
            msg = client.receive(max(0.0, min(0.05, left)))
            if msg is not None:
                if msg.kind == "task.result" and isinstance(msg.body, ResultUpdate):
                    uid = msg.body.uid
                    old = self.results.get(uid)
                    if old is None or not old.state.done:
                        self.results[uid] = msg.body.result
                        self.history.append(Update(self.now, uid, self.owner.get(uid, ""), msg.body.result))
                elif msg.kind == "watch.event" and isinstance(msg.body, WatchEvent) and msg.body.type == "Pose":
                    d = msg.body.data
                    if d.get("robot") == msg.body.agent:
                        self.poses.append(PoseSample(self.now, float(d["stamp"]), float(d["x"]), float(d["y"]),
                                                     float(d["theta"]), float(d.get("v") or 0.0),
                                                     float(d.get("w") or 0.0), d.get("battery")))
            if time.monotonic() >= end:
                return

    def wait(self, label: str, duration: float, until: Callable[[], bool] | None = None,
             step: float = 0.5) -> bool:
        """Pump for up to `duration` s (progress under `label`); True when `until()` became true."""
        start = self.now
        while self.now - start < duration:
            self.pump(step)
            self.progress(label, round(min(duration, self.now - start), 1), round(duration, 1))
            if until is not None and until():
                return True
        return until is not None and until()

    def final(self, uid: str) -> AllocationResult | None:
        """The task's final result (None while it runs)."""
        r = self.results.get(uid)
        return r if r is not None and r.state.done else None

    def done(self, uids: list[str]) -> bool:
        """True when every task in `uids` has a final result."""
        return all(self.final(u) is not None for u in uids)

    def succeeded_at(self, uid: str) -> float:
        """When the task's success arrived (s after start; NaN if it did not succeed)."""
        for u in self.history:
            if u.uid == uid and u.result.state == TaskState.SUCCEEDED:
                return u.t
        return math.nan

    def samples(self) -> list[Any]:
        """The simulator's feed samples since `start` (truth: positions, components)."""
        assert self.team is not None
        return [s for s in self.team.samples if s.t >= self.t0]

    def stop(self, keep_logs: bool = False) -> None:
        """Stop every process of the team (its run directory stays when `keep_logs`)."""
        if self.team is not None:
            self.team.stop(keep_run_dir=keep_logs)

    def __enter__(self) -> TeamRun:
        return self

    def __exit__(self, kind: type[BaseException] | None, *exc: object) -> None:
        self.stop(keep_logs=kind is not None)  # a failed run keeps the logs its error points to
