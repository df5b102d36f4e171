"""The behaviour stack on synthetic robot states: arbitration, avoidance, outcomes and failures."""

from __future__ import annotations

import itertools
import math

import pytest

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
from erni.plugins.motion.behaviours import (
    STOP,
    AvoidObstacles,
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
from erni.plugins.motion.driver import RobotState
from erni.plugins.motion.robots import MODELS

MODEL = MODELS["p3dx-sh"].model_copy(update=dict(max_v=1.2, max_rv=180.0, accel=0.5, decel=0.5, rot_accel=120.0,
                                                 rot_decel=120.0))
FREE = {i: 5.0 for i in range(16)}
_seq = itertools.count()


def state(x=0.0, y=0.0, theta=0.0, v=0.0, w=0.0, sonar=None, stalled=False, **kw) -> RobotState:
    """A robot state; each one a newer SIP than the last."""
    return RobotState(x=x, y=y, theta=theta, v=v, w=w, left=v, right=v, battery=12.5,
                      stall_left=stalled, stall_right=stalled, bumpers=0, motors_enabled=True,
                      moving=bool(v or w), sonar=dict(FREE if sonar is None else sonar), stamp=0.0,
                      seq=next(_seq), **kw)


def wall_ahead(distance: float) -> dict[int, float]:
    """Sonar readings of a wall `distance` m in front of the body (the front transducers 2-5 see it)."""
    ranges = dict(FREE)
    for i in (2, 3, 4, 5):
        sx, _, deg = MODEL.sonar[i]
        ranges[i] = (distance + MODEL.radius - sx) / math.cos(math.radians(deg))
    return ranges


def test_newest_motion_behaviour_drives_and_only_it():
    stack = BehaviourStack()
    old = Velocity(VelocityParams(v=0.1), "old")
    new = Velocity(VelocityParams(v=0.2, w=10), "new")
    stack.push(old)
    stack.push(new)
    result = stack.cycle(state(), 0.0, MODEL)
    assert result.winner is new and result.command == Command(0.2, 10)
    assert old.progress == 0 and old.state == TaskState.RUNNING  # it waits underneath
    stack.remove(new)
    assert stack.cycle(state(), 0.1, MODEL).winner is old


def test_stop_on_top_halts_within_one_cycle_and_removing_it_resumes():
    stack = BehaviourStack()
    stack.push(Velocity(VelocityParams(v=0.5), "v"))
    assert stack.cycle(state(), 0.0, MODEL).command.v == 0.5
    stop = Stop("s")
    stack.push(stop)
    assert stack.cycle(state(v=0.5), 0.05, MODEL).command == STOP  # the very next cycle
    stack.push(Velocity(VelocityParams(v=0.3), "later"))  # newer motion stays under the stop
    assert stack.cycle(state(), 0.1, MODEL).winner is stop
    assert stop.values["halted"] and stop.state == TaskState.RUNNING
    stack.remove(stop)
    assert stack.cycle(state(), 0.15, MODEL).command.v == 0.3


def test_avoidance_overrides_motion_towards_an_obstacle_only():
    stack = BehaviourStack(blocked_timeout=1.0)
    avoid = AvoidObstacles(AvoidParams(distance=0.5))
    fwd = Velocity(VelocityParams(v=0.3, w=5), "fwd")
    stack.push(avoid)
    stack.push(fwd)  # pushed later, but avoidance has priority
    assert stack.cycle(state(sonar=wall_ahead(2.0)), 0.0, MODEL).winner is fwd
    r = stack.cycle(state(sonar=wall_ahead(0.4)), 0.1, MODEL)
    assert r.winner is avoid and r.command == Command(0.0, 5)  # translation held, rotation kept
    assert avoid.values["obstacle"] == pytest.approx(0.4, abs=0.01)
    back = Velocity(VelocityParams(v=-0.3), "back")
    stack.push(back)  # backing away from the wall is allowed
    assert stack.cycle(state(sonar=wall_ahead(0.4)), 0.2, MODEL).winner is back


def test_avoidance_accounts_for_the_stopping_distance():
    stack = BehaviourStack()
    stack.push(AvoidObstacles(AvoidParams(distance=0.4)))
    stack.push(Velocity(VelocityParams(v=1.0), "fast"))
    # 0.6 m free: enough when standing, not at 1 m/s with 0.5 m/s^2 of braking
    assert stack.cycle(state(sonar=wall_ahead(0.6)), 0.0, MODEL).command.v == 1.0
    assert stack.cycle(state(v=1.0, sonar=wall_ahead(0.6)), 0.1, MODEL).command.v == 0.0


def test_a_task_held_by_avoidance_fails_as_blocked():
    stack = BehaviourStack(blocked_timeout=0.5)
    stack.push(AvoidObstacles(AvoidParams(distance=0.5)))
    fwd = Straight(DistanceParams(distance=3.0), 1, "fwd")
    stack.push(fwd)
    finished = []
    for i in range(10):
        finished += stack.cycle(state(sonar=wall_ahead(0.3)), i * 0.1, MODEL).finished
    assert finished == [fwd] and fwd.state == TaskState.FAILED
    assert fwd.message.startswith("blocked by an obstacle 0.30 m away")


def test_stalled_wheels_fail_the_driving_task():
    stack = BehaviourStack(stall_timeout=0.3)
    fwd = Straight(DistanceParams(distance=3.0), 1, "fwd")
    stack.push(fwd)
    for i in range(6):
        stack.cycle(state(stalled=True), i * 0.1, MODEL)
    assert fwd.state == TaskState.FAILED and fwd.message.startswith("stalled")


def test_goto_steers_then_arrives_within_tolerance():
    g = GoTo(GotoParams(x=0.0, y=2.0, tolerance=0.1), "g")
    stack = BehaviourStack()
    stack.push(g)
    first = stack.cycle(state(), 0.0, MODEL).command
    assert first.v == 0.0 and first.w > 0  # goal at 90 degrees left: turn first
    assert g.values["distance_remaining"] == pytest.approx(2.0)
    mid = stack.cycle(state(y=1.0, theta=math.pi / 2), 0.1, MODEL)
    assert mid.command.v > 0 and g.progress == pytest.approx(0.5, abs=0.01)
    near = stack.cycle(state(y=1.96, theta=math.pi / 2, v=0.05), 0.2, MODEL)
    assert near.command == STOP and g.state == TaskState.RUNNING  # halting; success only once it stands
    done = stack.cycle(state(y=1.97, theta=math.pi / 2), 0.3, MODEL)
    assert done.command == STOP and done.finished == [g] and g.state == TaskState.SUCCEEDED
    assert g.values["distance_remaining"] == pytest.approx(0.03)


def test_goto_times_out():
    g = GoTo(GotoParams(x=5, y=0, timeout=1.0), "g")
    stack = BehaviourStack()
    stack.push(g)
    stack.cycle(state(), 0.0, MODEL)
    stack.cycle(state(), 1.5, MODEL)
    assert g.state == TaskState.FAILED and g.message == "timed out after 1 s"


def test_turn_counts_rotation_through_the_wrap():
    t = Turn(TurnParams(angle=-270, rate=90), "t")
    stack = BehaviourStack()
    stack.push(t)
    heading, w = 0.0, 0.0
    for i in range(200):
        cmd = stack.cycle(state(theta=math.remainder(heading, 2 * math.pi), w=w), i * 0.05, MODEL).command
        if t.state.done:
            break
        w = math.radians(cmd.w)
        heading += w * 0.05
    assert t.state == TaskState.SUCCEEDED and t.values["turned"] == pytest.approx(-270, abs=2.0)


def test_forward_and_backward_measure_along_the_start_heading():
    for direction in (1, -1):
        b = Straight(DistanceParams(distance=1.0, speed=0.5), direction, "b")
        stack = BehaviourStack()
        stack.push(b)
        c = stack.cycle(state(theta=math.pi / 2), 0.0, MODEL).command
        assert c.v == pytest.approx(0.5 * direction)
        stack.cycle(state(y=0.5 * direction, theta=math.pi / 2), 0.1, MODEL)
        assert b.values["distance_remaining"] == pytest.approx(0.5)
        assert stack.cycle(state(y=0.997 * direction, theta=math.pi / 2, v=0.02 * direction), 0.2, MODEL).command == STOP
        assert b.state == TaskState.RUNNING  # still rolling
        stack.cycle(state(y=0.999 * direction, theta=math.pi / 2), 0.3, MODEL)
        assert b.state == TaskState.SUCCEEDED and b.values["travelled"] == pytest.approx(0.999)


def test_straight_brakes_early_by_the_latency_and_corrects_from_a_standstill():
    b = Straight(DistanceParams(distance=1.0, speed=0.8), 1, "b")
    stack = BehaviourStack()
    stack.push(b)
    stack.cycle(state(), 0.0, MODEL)
    # 0.7 m done at 0.5 m/s (0.25 m to brake): without latency it may drive on; 0.3 s of lead (0.15 m)
    # at the speed last asked for leaves too little room: halt now
    assert stack.cycle(state(x=0.7, v=0.5), 0.05, MODEL, lead=0.0, commanded=(0.5, 0)).command.v > 0
    assert stack.cycle(state(x=0.7, v=0.5), 0.1, MODEL, lead=0.3, commanded=(0.5, 0)).command == STOP
    stack.cycle(state(x=0.95, v=0.0), 0.2, MODEL, lead=0.3)  # stopped 5 cm short: drive again
    assert b.state == TaskState.RUNNING and b.phase == "drive" and b.corrections == 1
    assert 0 < stack.cycle(state(x=0.95), 0.3, MODEL).command.v < 0.3
    stack.cycle(state(x=1.04, v=0.02), 0.4, MODEL)  # overshot by 4 cm: halt, then back up
    stack.cycle(state(x=1.04), 0.5, MODEL)
    assert stack.cycle(state(x=1.04), 0.6, MODEL).command.v < 0
    stack.cycle(state(x=1.01, v=-0.01), 0.7, MODEL)
    assert stack.cycle(state(x=1.005), 0.8, MODEL).command == STOP  # on the mark: halt ...
    stack.cycle(state(x=1.005), 0.9, MODEL)  # ... and a later SIP shows it standing
    assert b.state == TaskState.SUCCEEDED and b.values["corrections"] == 2


def test_turn_plans_its_stop_ahead_by_the_latency():
    t = Turn(TurnParams(angle=90, rate=90, tolerance=2), "t")
    stack = BehaviourStack()
    stack.push(t)
    stack.cycle(state(theta=0.0), 0.0, MODEL)
    # 70 degrees turned at 90 deg/s: 0.25 s of lead covers 22.5 degrees, past the mark: halt now
    assert stack.cycle(state(theta=math.radians(70), w=math.radians(90)), 0.1, MODEL, lead=0.25).command == STOP
    stack.cycle(state(theta=math.radians(89)), 0.2, MODEL, lead=0.25)
    assert t.state == TaskState.SUCCEEDED and t.values["angle_remaining"] == pytest.approx(1.0, abs=0.01)


def test_velocity_with_duration_and_teleport_confirmation():
    v = Velocity(VelocityParams(v=0.2, duration=1.0), "v")
    stack = BehaviourStack()
    stack.push(v)
    stack.cycle(state(), 0.0, MODEL)
    stack.cycle(state(), 0.5, MODEL)
    assert v.progress == pytest.approx(0.5)
    assert stack.cycle(state(), 1.0, MODEL).command == STOP and v.state == TaskState.SUCCEEDED
    tp = Teleport(TeleportParams(x=1, y=2, heading=90), "tp")
    stack.push(tp)
    assert stack.cycle(state(), 2.0, MODEL).command.teleport == (1, 2, 90)
    tp.performed("sim", 2.0)
    stack.cycle(state(x=1, y=2, theta=math.pi / 2), 2.1, MODEL)
    assert tp.state == TaskState.RUNNING  # odometry reads the target, the simulator has not confirmed
    stack.cycle(state(x=1, y=2, theta=math.pi / 2, sim_pose=(5.0, 5.0, 0.0), sim_stamp=2.15), 2.2, MODEL)
    assert tp.state == TaskState.RUNNING  # the simulator put it elsewhere
    stack.cycle(state(x=1, y=2, theta=math.pi / 2, sim_pose=(1.0, 2.01, 1.57), sim_stamp=2.25), 2.3, MODEL)
    assert tp.state == TaskState.SUCCEEDED and tp.values["moved"] is True


def test_teleport_on_a_real_robot_says_it_only_relocalised():
    tp = Teleport(TeleportParams(x=1, y=2), "tp")
    stack = BehaviourStack()
    stack.push(tp)
    stack.cycle(state(), 0.0, MODEL)
    tp.performed("odometry", 0.0)
    stack.cycle(state(x=1, y=2), 0.1, MODEL)
    assert tp.state == TaskState.SUCCEEDED and tp.values["moved"] is False
    assert "cannot be moved by software" in tp.message


def test_teleport_without_simstat_is_confirmed_by_the_sips_and_a_wrong_pose_times_out():
    tp = Teleport(TeleportParams(x=1, y=2), "tp", confirm=0.5)
    stack = BehaviourStack()
    stack.push(tp)
    stack.cycle(state(), 0.0, MODEL)
    tp.performed("sim", 0.0)
    stack.cycle(state(x=1, y=2), 0.2, MODEL)
    assert tp.state == TaskState.RUNNING
    stack.cycle(state(x=1, y=2), 0.6, MODEL)
    assert tp.state == TaskState.SUCCEEDED and "no SIMSTAT" in tp.message
    lost = Teleport(TeleportParams(x=1, y=2), "lost", timeout=1.0)
    stack.push(lost)
    stack.cycle(state(), 1.0, MODEL)
    lost.performed("sim", 1.0)
    stack.cycle(state(x=1, y=2, sim_pose=(0.0, 0.0, 0.0), sim_stamp=1.1), 2.5, MODEL)
    assert lost.state == TaskState.FAILED and "simulator reports it at (0.00, 0.00" in lost.message


def test_randomwalk_is_repeatable_turns_away_from_walls_and_ends():
    def walk(seed: int) -> list[Command]:
        rw = RandomWalk(RandomWalkParams(speed=0.4, duration=5.0, seed=seed), "rw")
        stack = BehaviourStack()
        stack.push(rw)
        return [stack.cycle(state(), i * 0.5, MODEL).command for i in range(8)]

    assert walk(3) == walk(3) and walk(3) != walk(4)
    rw = RandomWalk(RandomWalkParams(speed=0.4, duration=2.0, seed=1), "rw")
    stack = BehaviourStack()
    stack.push(rw)
    near = wall_ahead(0.3)
    near.update({0: 0.3, 1: 0.4})  # left side is also crowded: turn right
    cmd = stack.cycle(state(sonar=near), 0.0, MODEL).command
    assert cmd.v == 0 and cmd.w < 0
    stack.cycle(state(), 2.5, MODEL)
    assert rw.state == TaskState.SUCCEEDED


def test_version_changes_only_on_significant_news():
    g = GoTo(GotoParams(x=10, y=0), "g")
    stack = BehaviourStack()
    stack.push(g)
    stack.cycle(state(), 0.0, MODEL)
    v0 = g.version
    stack.cycle(state(x=0.0001), 0.05, MODEL)
    assert g.version == v0
    stack.cycle(state(x=1.0), 0.1, MODEL)
    assert g.version > v0
