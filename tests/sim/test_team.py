"""A simulated team of real agent processes: remote tasking through the control node, radio range."""

from __future__ import annotations

import math
import time

import pytest

from erni.blackboard import Task, TaskState
from erni.blackboard.schemas import ResultUpdate
from erni.blackboard.testing import wait_until
from erni.sim.scenario import Scenario
from erni.sim.team import CONTROL, Team, TeamError

FAST = {"beacon_period": 0.3, "peer_timeout": 1.5, "task_ttl": 10.0}


def make_team(tmp_path, count: int, mission: bool = False, **radio) -> Team:
    scenario = Scenario(robots={"count": count, "spacing": 1.5},
                        radio={"comm_range": 10.0, "lossless_range": 6.0, **radio})
    return Team(scenario, run_dir=tmp_path / "run", headless=True, control_port=0, transport=FAST,
                mission=mission, ui=False)


def send(team: Team, robot: str, verb: str, prep: str, **params) -> Task:
    client = team.client()
    task = Task(verb=verb, preposition=prep, params=params, destination=robot, source=client.endpoint.name)
    client.send(team.control_address, "task.add", task)
    return task


def final_result(team: Team, uid: str, timeout: float):
    client = team.client()
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        msg = client.receive(0.1)
        if msg and msg.kind == "task.result" and isinstance(msg.body, ResultUpdate) and msg.body.uid == uid:
            if msg.body.result.state.done:
                return msg.body.result
    raise AssertionError(f"no final result for task {uid} within {timeout} s")


@pytest.mark.parametrize("verb, mission", [("BotMotion", False), ("RemoteBotMotion", True)])
def test_remote_goto_from_the_control_node_reaches_its_goal(tmp_path, verb, mission):
    team = make_team(tmp_path, 3, mission=mission)
    try:
        team.start(timeout=60)
        assert set(team.peers()) >= {"robot1", "robot2", "robot3"}
        robot = team.robot("robot2")
        goal = (robot.x + 1.0, robot.y + 1.5)
        task = send(team, "robot2", verb, "goto", x=goal[0], y=goal[1], speed=0.8, tolerance=0.1)
        result = final_result(team, task.uid, timeout=30)
        assert result.state is TaskState.SUCCEEDED, result.message
        assert math.hypot(robot.x - goal[0], robot.y - goal[1]) < 0.2
        others = [team.robot("robot1"), team.robot("robot3")]
        assert all(math.hypot(r.x - r.start[0], r.y - r.start[1]) < 0.05 for r in others)
        team.sips_since()
        start = time.monotonic()
        begun = team.host.timing()
        # about a second of SIP slots: three robots at 10 Hz, counted by the robot host
        wait_until(lambda: sum(team.host.timing()[k] - begun[k] for k in ("sips", "skipped")) >= 30,
                   timeout=30, interval=0.05)
        sent, skipped = team.sips_since()
        slots = 3 * (time.monotonic() - start) / 0.1
        assert abs(sent + skipped - slots) <= 9 and skipped <= sent, (sent, skipped, slots)
    finally:
        team.stop()
    assert not any(a.alive for a in team.agents.values())


def test_a_robot_out_of_radio_range_is_lost_and_receives_no_traffic(tmp_path):
    team = make_team(tmp_path, 3)
    try:
        team.start(timeout=60)
        wait_until(lambda: all(p.up for p in team.peers().values()) and len(team.peers()) == 3, timeout=10)
        team.teleport("robot3", 40.0, 0.0)  # 40 m from everyone: R is 10 m
        wait_until(lambda: "robot3" not in team.status.reach[CONTROL], timeout=5)
        reach = team.status.reach
        assert reach["robot3"] == [] and "robot3" not in reach["robot1"]
        wait_until(lambda: not team.peers()["robot3"].up, timeout=10)
        assert team.peers()["robot1"].up and team.peers()["robot2"].up
        robot = team.robot("robot3")
        before = (robot.x, robot.y)
        # an absolute goal: the task may reach the robot just before the SIP that shows the jump
        # back, and a relative move would then measure the teleport as distance driven
        task = send(team, "robot3", "BotMotion", "goto", x=2.0, y=3.0, speed=0.5, tolerance=0.1)
        time.sleep(2.0)  # the task would have driven the robot within this time if delivered
        assert math.hypot(robot.x - before[0], robot.y - before[1]) < 0.01
        team.teleport("robot3", 2.0, 2.0)  # back in range: the queued task gets through
        result = final_result(team, task.uid, timeout=20)
        assert result.state is TaskState.SUCCEEDED, result.message
        assert math.hypot(robot.x - 2.0, robot.y - 3.0) < 0.2
        assert team.peers()["robot3"].up
    finally:
        team.stop()


def test_relayed_robot_stays_reachable_over_several_hops(tmp_path):
    team = Team(Scenario(robots={"count": 3}, radio={"comm_range": 4.0, "lossless_range": 3.0},
                         robot=[{"x": 0.0, "y": 1.0}, {"x": 0.0, "y": 4.0}, {"x": 0.0, "y": 7.0}],
                         control={"x": 0.0, "y": -2.0}),
                run_dir=tmp_path / "run", headless=True, control_port=0, transport=FAST,
                mission=False, ui=False)
    try:
        team.start(timeout=60)
        reach = team.status.reach
        truth = team.network.truth()
        assert frozenset((CONTROL, "robot3")) not in truth.links  # 9 m apart: no direct link
        assert "robot3" in reach[CONTROL]
        wait_until(lambda: team.peers().get("robot3") is not None and team.peers()["robot3"].up, timeout=10)
        team.teleport("robot2", 20.0, 4.0)  # the relay leaves: robot3 is cut off
        wait_until(lambda: "robot3" not in team.status.reach[CONTROL], timeout=5)
        wait_until(lambda: not team.peers()["robot3"].up, timeout=10)
    finally:
        team.stop()


def test_the_simulators_heap_is_frozen_while_the_team_runs_and_thawed_at_stop(tmp_path):
    """Full collections in the simulator's process skip what the team made at start (the world,
    the robots, the network); a stopped team gives it back, as experiments run team after team."""
    import gc

    team = Team(Scenario(robots={"count": 1}), run_dir=tmp_path / "run", headless=True, control_port=0,
                transport=FAST, mission=False, ui=False)
    assert gc.get_freeze_count() == 0
    try:
        team.start(timeout=60)
        assert gc.get_freeze_count() > 10_000
        assert not any(o is team for o in gc.get_objects())  # frozen: no collection scans the team
    finally:
        team.stop()
    assert gc.get_freeze_count() == 0


def test_agents_start_a_batch_at_a_time_so_the_simulator_keeps_its_robots_linked(tmp_path):
    """A launch waits while `launch_batch` robots' agents are still starting (their robot has no
    client yet): forty agents starting at once starve the simulator of the CPU its SIPs need."""
    team = Team(Scenario(robots={"count": 3, "spacing": 1.5}), run_dir=tmp_path / "run", headless=True,
                control_port=0, transport=FAST, mission=False, ui=False, launch_batch=1)
    starting_at_launch: list[int] = []
    spawn = team._spawn

    def spawn_and_count(agent, env):
        linked = team.host.connected()
        starting_at_launch.append(sum(1 for i, name in enumerate(team.names)
                                      if team.agents[name].proc is not None and not linked[i]))
        spawn(agent, env)

    team._spawn = spawn_and_count
    try:
        team.start(timeout=60)
    finally:
        team.stop()
    assert starting_at_launch == [0, 0, 0, 0]  # control, then each robot once the one before it connected
    with pytest.raises(TeamError, match="launch_batch: expected at least 1"):
        Team(Scenario(robots={"count": 1}), headless=True, control_port=0, launch_batch=0)


def test_a_temporary_run_directory_goes_with_the_team_unless_the_run_failed():
    """Experiments start a team per run (60 for `netaware --seeds 10`): a run directory the team
    made itself is removed when it stops; one whose run raised stays (the error names its logs),
    and so does one the caller named or asked to keep (`erni sim` prints where it is)."""
    import shutil

    def team(**kw) -> Team:
        return Team(Scenario(robots={"count": 1}), headless=True, control_port=0, transport=FAST,
                    mission=False, ui=False, **kw)

    with team() as ok:
        ok.start(timeout=60)
        assert (ok.run_dir / "logs" / "robot1.log").exists()
    assert not ok.run_dir.exists()
    never = team()
    assert never.run_dir.exists()
    never.stop()  # a team stopped before its start leaves nothing either
    assert not never.run_dir.exists()
    failed = team()
    try:
        with pytest.raises(RuntimeError, match="the experiment failed"):
            with failed:
                failed.start(timeout=60)
                raise RuntimeError("the experiment failed")
        assert (failed.run_dir / "logs" / "robot1.log").exists()
        kept = team(keep_run_dir=True)
        with kept:
            kept.start(timeout=60)
        assert (kept.run_dir / "logs" / "robot1.log").exists()
        shutil.rmtree(kept.run_dir)
    finally:
        shutil.rmtree(failed.run_dir, ignore_errors=True)


def test_a_control_port_taken_after_it_was_checked_gets_the_control_node_another(tmp_path):
    """Another program (or a team started at the same moment) binds the control node's port between
    the check and the control node's start: the team starts it again on a free port."""
    import socket

    from erni.sim.team import CONTROL_HOST, free_port

    port = free_port(CONTROL_HOST)
    team = Team(Scenario(robots={"count": 1}), run_dir=tmp_path / "run", headless=True, control_port=port,
                transport=FAST, mission=False, ui=False)
    assert team.control_port == port  # free when checked
    thief = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
    thief.bind((CONTROL_HOST, port))
    thief.listen()
    try:
        team.start(timeout=60)
        assert team.control_port != port and team.control_address == (CONTROL_HOST, team.control_port)
        assert wait_until(lambda: (p := team.peers(1.0).get("robot1")) is not None and p.up)
        first = (tmp_path / "run" / "logs" / f"{CONTROL}.log.1").read_text()
        assert f"cannot listen on {CONTROL_HOST}:{port} (TCP): Address already in use" in first
    finally:
        team.stop()
        thief.close()
