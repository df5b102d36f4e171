"""Two-tier tasking: RemoteBotMotion tasks expanded into BotMotion sub-tasks on a simulated robot."""

from __future__ import annotations

import itertools
import math
import threading
import time

from erni.blackboard import Agent, Pose, Task, TaskState
from erni.blackboard.testing import wait_until
from erni.plugins.mission.plugin import CUE_TASK
from erni.sim.world import World
from tests.core.helpers import scheduler_idle
from tests.mission.conftest import FAST, MOTION, current, plugin, pose_of, send, subs_of


class Recorder:
    """Every committed version of the tasks and poses of one agent, in commit order."""

    def __init__(self, agent: Agent) -> None:
        self.lock = threading.Lock()
        self.ops: list[tuple[str, object]] = []
        agent.blackboard.add_listener(self._seen)

    def _seen(self, ops) -> None:
        with self.lock:
            self.ops.extend((kind, obj) for kind, obj, _ in ops)

    def versions(self, uid: str) -> list[Task]:
        with self.lock:
            return [o for k, o in self.ops if k != "remove" and getattr(o, "uid", None) == uid]

    def tasks(self, where) -> list[Task]:
        with self.lock:
            return [o for k, o in self.ops if k == "add" and isinstance(o, Task) and where(o)]

    def poses(self) -> list[Pose]:
        with self.lock:
            return [o for k, o in self.ops if isinstance(o, Pose)]


def finished(agent: Agent, task: Task, timeout: float = 15.0) -> Task:
    return wait_until(lambda: (t := current(agent, task.uid)) is not None and t.done and t, timeout=timeout,
                      message=f"{task.describe()} did not finish")


def test_remote_goto_is_expanded_performed_and_reported_only_on_significant_changes(robots):
    agent = robots("robot1")
    rec = Recorder(agent)
    task = send(agent, "goto", x=2.5, y=1.0, speed=1.0, tolerance=0.1)
    done = finished(agent, task)
    assert done.state == TaskState.SUCCEEDED, done.result
    p = pose_of(agent)
    assert math.hypot(p.x - 2.5, p.y - 1.0) <= 0.15
    subs = rec.tasks(lambda t: t.parent == task.uid)
    assert [(s.verb, s.preposition, s.source, s.destination) for s in subs] == \
        [("BotMotion", "goto", "robot1", None)]
    assert subs[0].params.x == 2.5 and subs[0].params.y == 1.0
    versions = [v.result for v in rec.versions(task.uid) if v.result is not None]
    states = [r.state for r in versions]
    assert states[0] == TaskState.PENDING and versions[0].message == "accepted by robot1"
    assert states[-1] == TaskState.SUCCEEDED and states.count(TaskState.SUCCEEDED) == 1
    assert TaskState.RUNNING in states
    progress = [r.progress for r in versions]
    assert progress == sorted(progress)
    keys = [(r.state, r.message, math.floor(r.progress / 0.25 + 1e-9)) for r in versions]
    assert all(a != b for a, b in itertools.pairwise(keys)), keys  # every update carries news
    assert len(versions) <= 8, versions  # accepted, started, 3 progress steps, done (+ slack)
    goto_updates = [v for v in rec.versions(subs[0].uid) if v.result is not None]
    assert len(goto_updates) > len(versions)  # the sub-task chattered; the remote task did not
    wait_until(lambda: not subs_of(agent, task.uid), message="finished sub-tasks are cleaned up")


def test_goto_as_turn_then_forward(robots):
    agent = robots("robot1", mission={"goto_mode": "turn_forward"})
    rec = Recorder(agent)
    task = send(agent, "goto", x=0.0, y=2.0, speed=1.5, tolerance=0.15)
    assert finished(agent, task).state == TaskState.SUCCEEDED
    subs = rec.tasks(lambda t: t.parent == task.uid)
    assert [s.preposition for s in subs] == ["turn", "forward"]
    assert abs(subs[0].params.angle - 90.0) < 1.0 and abs(subs[1].params.distance - 2.0) < 0.01
    p = pose_of(agent)
    assert math.hypot(p.x, p.y - 2.0) < 0.3


def test_goto_detours_around_a_known_obstacle(robots):
    world = World.model_validate({"circle": [{"center": [1.5, 0.0], "radius": 0.4}]})
    agent = robots("robot1", world=world, mission={"obstacles": [[1.5, 0.0, 0.4]], "obstacle_margin": 0.4})
    rec = Recorder(agent)
    task = send(agent, "goto", x=3.0, y=0.0, speed=1.5, tolerance=0.1)
    assert finished(agent, task).state == TaskState.SUCCEEDED
    subs = rec.tasks(lambda t: t.parent == task.uid)
    assert len(subs) >= 2 and all(s.preposition == "goto" for s in subs)
    assert (subs[-1].params.x, subs[-1].params.y) == (3.0, 0.0)
    closest = min(math.hypot(p.x - 1.5, p.y) for p in rec.poses() if p.robot == "robot1")
    assert closest > 0.4 + 0.25, closest  # obstacle radius + robot radius never touched


def test_removing_the_remote_task_withdraws_sub_tasks_and_halts(robots):
    agent = robots("robot1")
    rec = Recorder(agent)
    task = send(agent, "forward", distance=30.0, speed=0.8)
    wait_until(lambda: pose_of(agent).v > 0.5, message="robot never got going")
    sub = subs_of(agent, task.uid)[0]
    with agent.transaction() as tx:
        tx.remove(task.uid)
    wait_until(lambda: current(agent, sub.uid) is None, message="sub-task not withdrawn")
    wait_until(lambda: abs(pose_of(agent).v) < 0.01, message="robot not halted")
    stops = rec.tasks(lambda t: t.preposition == "stop" and t.source == "robot1")
    assert len(stops) == 1
    wait_until(lambda: current(agent, stops[0].uid) is None, message="the halting stop stays on the stack")
    assert pose_of(agent).x < 10.0


def test_cancel_task_cancels_remote_tasks_keeps_local_ones_and_halts(robots):
    agent = robots("robot1")
    local = Task(verb="BotMotion", preposition="avoid_obstacles", params={"distance": 0.3}, source="local")
    with agent.transaction() as tx:
        tx.add(local)
    walk = send(agent, "randomwalk", speed=0.5, seed=3)
    wait_until(lambda: abs(pose_of(agent).v) > 0.2, message="random walk never moved")
    cancel = send(agent, "cancel")
    assert finished(agent, cancel).state == TaskState.SUCCEEDED
    gone = current(agent, walk.uid)
    assert gone.state == TaskState.CANCELLED and cancel.uid in gone.result.message
    assert not subs_of(agent, walk.uid)
    assert abs(pose_of(agent).v) < 0.02
    assert current(agent, local.uid) is not None and not current(agent, local.uid).done  # mixed initiative
    bad = send(agent, "cancel", task="no-such-task")
    done = finished(agent, bad)
    assert done.state == TaskState.FAILED and "no-such-task" in done.result.message


def test_a_new_remote_motion_supersedes_the_previous_one(robots):
    agent = robots("robot1")
    first = send(agent, "goto", x=5.0, y=0.0, speed=0.5)
    wait_until(lambda: subs_of(agent, first.uid), message="first goto never started")
    second = send(agent, "goto", x=0.0, y=1.0, speed=1.0)
    old = finished(agent, first)
    assert old.state == TaskState.CANCELLED and second.uid in old.result.message
    assert finished(agent, second).state == TaskState.SUCCEEDED


def test_teleport_and_audio_cue_on_reception(robots, hosts):
    agent = robots("robot1", mission={"audio": True})
    task = send(agent, "teleport", x=1.0, y=-1.0, heading=90.0)
    assert finished(agent, task).state == TaskState.SUCCEEDED
    p = pose_of(agent)
    assert math.hypot(p.x - 1.0, p.y + 1.0) < 0.06
    robot = hosts[0].robots[0]
    wait_until(lambda: robot.said, message="no audio cue played")
    assert robot.said[0] == bytes(b for tone in CUE_TASK for b in tone)
    wait_until(lambda: not agent.query(Task, where=lambda t: t.preposition == "say"),
               message="finished say tasks are removed")


def test_after_a_restart_interrupted_remote_tasks_fail_and_stale_sub_tasks_are_withdrawn(tmp_path):
    journal = tmp_path / "robot1.sqlite"
    first = Agent("robot1", workers=2, journal=journal)
    first.add_plugin("mission", settings={"audio": False, "network_aware": False}, name="mission")
    first.start()
    try:
        task = send(first, "forward", distance=3.0)
        wait_until(lambda: subs_of(first, task.uid), message="no sub-task issued")
        stale = subs_of(first, task.uid)[0]
    finally:
        first.stop()
    second = Agent("robot1", workers=2, journal=journal)
    second.add_plugin("mission", settings={"audio": False, "network_aware": False}, name="mission")
    second.start()
    try:
        done = wait_until(lambda: (t := current(second, task.uid)) is not None and t.done and t,
                          message="the rehydrated remote task was never settled")
        assert done.state == TaskState.FAILED and done.result.message.startswith("interrupted: robot1 restarted")
        assert current(second, stale.uid) is None  # never repeated on the robot
    finally:
        second.stop()


def test_after_a_restart_a_remote_goto_resumes_from_where_the_robot_stands(hosts, tmp_path):
    from erni.sim.robot import SimRobotConfig
    from erni.sim.robot_host import RobotHost
    from erni.sim.world import RobotStart

    host = RobotHost(World().model_copy(update={"robot": [RobotStart(name="robot1")]}), physics_hz=200)
    host.add_robot(SimRobotConfig(name="robot1", **FAST), port=0)
    hosts.append(host.start())
    robot = host.robots[0]

    def start() -> tuple[Agent, Recorder]:
        agent = Agent("robot1", workers=2, journal=tmp_path / "robot1.sqlite")
        agent.add_plugin("motion", settings={**MOTION, "url": host.url()}, name="motion")
        agent.add_plugin("mission", settings={"audio": False, "network_aware": False}, name="mission")
        rec = Recorder(agent)  # before it starts: every version of the remote task is seen
        return agent.start(), rec

    first, _ = start()
    try:
        task = send(first, "goto", x=3.0, y=0.0, speed=0.6, tolerance=0.1)
        wait_until(lambda: robot.x > 0.8, timeout=10, message="the robot never got going")
    finally:
        first.stop()  # the agent dies mid-way (its journal keeps the remote task)
    second, rec = start()
    try:
        done = finished(second, task, timeout=30)
        assert done.state == TaskState.SUCCEEDED, done.result
        assert math.hypot(robot.x - 3.0, robot.y) <= 0.15
        messages = [v.result.message for v in rec.versions(task.uid) if v.result is not None]
        assert any(m.startswith("resumed after a restart of robot1") for m in messages), messages
    finally:
        second.stop()


def test_an_idle_mission_is_not_run_by_every_pose_but_reads_the_newest(robots):
    """Without a job or a deployment, the robot's 10 Hz Poses do not each run the mission; the
    newest is still what it knows at its next run. With a job, every Pose runs it again."""
    agent = robots("robot1", with_motion=False)
    mission = plugin(agent)

    def walk(n: int, y: float) -> None:
        for k in range(n):
            with agent.transaction() as tx:
                pose = Pose(uid="pose:robot1", robot="robot1", x=0.1 * k, y=y)
                if agent.query(Pose):
                    tx.change(pose)
                else:
                    tx.add(pose)
            wait_until(lambda: scheduler_idle(mission))  # the run this Pose asked for, if it asked, is over

    walk(1, 0.0)
    wait_until(lambda: mission.team.mine() is not None, timeout=5, message="the mission never read the Pose")
    before, start = mission.runs, time.monotonic()
    walk(25, 1.0)  # half a second of a walking robot's Poses
    idle_runs = mission.runs - before
    allowed = 2 + math.ceil(time.monotonic() - start)  # its once-a-second timer, however slow this machine
    assert idle_runs <= allowed, f"{idle_runs} runs of an idle mission for 25 Poses (at most {allowed})"
    wait_until(lambda: (m := mission.team.mine()) is not None and abs(m[0] - 2.4) < 1e-9 and m[1] == 1.0, timeout=3,
               message="the idle mission never read the newest Pose")
    task = send(agent, "goto", x=5.0, y=5.0, speed=1.0)  # a job: no motion plugin, so it stays pending
    wait_until(lambda: task.uid in mission.jobs, timeout=5, message="the job was not taken")
    before = mission.runs
    walk(25, 2.0)
    assert mission.runs - before >= 8, f"{mission.runs - before} runs for 25 Poses while a job is on"
