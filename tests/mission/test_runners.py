"""Deploy runners: WiDep decides on settled positions, never drives a step too short to move, and says when it
is stuck; a relay that cannot move says so too.

The runner is driven here through its small `Ops` interface (what MissionControl gives it), so
every decision can be checked round by round with a clock the test controls.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
import pytest

from erni.blackboard import Params, Pose, Task, TaskState
from erni.blackboard.clock import SYSTEM
from erni.plugins.mission.deploy import RelayRunner, WidepRunner
from erni.plugins.mission.plugin import MissionSettings
from erni.plugins.mission.team import TeamView, Territory
from erni.strategies.potential import SpreadConfig, forces
from erni.strategies.widep import auxiliary_poi, segment_hits, widep_step


class FakeOps:
    """Records what the runner issues and reports; positions come from a TeamView the test fills."""

    def __init__(self, me: str = "robot1") -> None:
        self.agent_name = me
        self.clock = SYSTEM
        self.team = TeamView(me, timeout=5.0)
        self.issued: list[tuple[str, Params]] = []
        self.reports: list[tuple[TaskState, str]] = []
        self.tasks: dict[str, Task] = {}

    def issue(self, parent: str | None, preposition: str, params: Params) -> str:
        task = Task(verb="BotMotion", preposition=preposition, params=params, source=self.agent_name, parent=parent)
        self.tasks[task.uid] = task.with_result(TaskState.SUCCEEDED)  # done at once: the next round may step
        self.issued.append((preposition, params))
        return task.uid

    def withdraw(self, uid: str | None) -> None:
        pass

    def sub(self, uid: str | None) -> Task | None:
        return self.tasks.get(uid) if uid else None

    def report(self, uid: str, state: TaskState, message: str = "", **_: Any) -> None:
        self.reports.append((state, message))

    qualities: dict[str, float] | None = None

    def link_qualities(self) -> dict[str, float] | None:
        return self.qualities

    def publish_territory(self, territory: Territory) -> None:
        pass

    def at(self, t: float, where: dict[str, tuple[float, float]]) -> None:
        """Everyone is seen at `where` at time t."""
        for name, (x, y) in where.items():
            self.team.pose(Pose(robot=name, x=x, y=y, stamp=t))


def runner(ops: FakeOps, t: float, **settings: Any) -> WidepRunner:
    task = Task(verb="Deploy", preposition="widep", params={"x": 0.0, "y": 20.0, "range": 4.5, "period": 4.0},
                source="control", destination=ops.agent_name)
    return WidepRunner(task, ops, MissionSettings(**{"speed": 0.5, **settings}), t)


def test_a_team_view_knows_when_a_robot_came_to_rest():
    view = TeamView("robot1", timeout=5.0)
    for k in range(5):  # moving 0.1 m every 0.2 s
        view.pose(Pose(robot="robot2", x=0.1 * k, y=0.0, stamp=100.0 + 0.2 * k))
    assert not view.settled("robot2", fresh_after=100.0, still_for=0.4)
    for k in range(5, 9):  # standing still from t = 100.8
        view.pose(Pose(robot="robot2", x=0.4, y=0.0, stamp=100.0 + 0.2 * k))
    assert view.settled("robot2", fresh_after=101.0, still_for=0.4)
    assert not view.settled("robot2", fresh_after=102.0, still_for=0.4)  # no reading that fresh


def test_a_step_is_decided_only_on_settled_positions_and_is_the_plain_widep_bound():
    ops = FakeOps()
    layout = {"robot1": (0.0, 4.0), "robot2": (0.0, 0.0)}
    for k in range(6):  # robot2 still moving during the previous round
        ops.at(96.0 + 0.3 * k, {"robot1": layout["robot1"], "robot2": (0.0, 0.05 * k)})
    r = runner(ops, 96.0)
    r.tick(100.0)
    assert ops.issued == []  # waits for robot2 to be seen at rest
    assert r.tick(100.1) == pytest.approx(0.2)
    r.tick(101.1)  # past the first quarter of the round: sits it out
    assert ops.issued == [] and "not seen at rest" in ops.reports[-1][1]
    for k in range(6):  # at rest through the second half of that round
        ops.at(102.0 + 0.3 * k, {"robot1": layout["robot1"], "robot2": (0.0, 0.25)})
    r.tick(104.0)
    assert len(ops.issued) == 1
    goto = ops.issued[0][1]
    # plain WiDep: (R - slack - d+) / 2 with d+ = 3.75, capped at 0.4 round at 0.5 m/s = 0.8 m
    bound = (4.5 - 0.2 - 3.75) / 2
    assert math.hypot(goto.x - 0.0, goto.y - 4.0) == pytest.approx(bound, abs=1e-3)


def test_a_step_shorter_than_a_goto_can_drive_is_held_and_a_stall_fails_saying_why():
    ops = FakeOps()
    # robot1 at the end of a stretched link: WiDep allows it only a few centimetres
    layout = {"robot1": (0.0, 4.22), "robot2": (0.0, 0.0)}
    r = runner(ops, 0.0, widep_stall_rounds=4)
    t = 0.0
    for k in range(8):
        t = 4.0 * (k + 1)
        for j in range(4):
            ops.at(t - 1.5 + 0.4 * j, layout)
        r.tick(t)
        if r.done:
            break
    assert ops.issued == [], "a goto shorter than widep_min_step would 'arrive' without moving"
    holding = [m for s, m in ops.reports if m.startswith("holding: the connectivity bound allows")]
    assert holding, ops.reports
    state, message = ops.reports[-1]
    assert r.done and state == TaskState.FAILED
    assert message.startswith("no progress toward the PoI for 4 rounds") and "bound allows" in message


def test_progress_of_the_team_keeps_a_waiting_robot_going():
    ops = FakeOps()
    r = runner(ops, 0.0, widep_stall_rounds=3)
    front = 4.22
    for k in range(8):  # robot1 is held, but robot2 (ahead) comes closer to the PoI every round
        t = 4.0 * (k + 1)
        front += 0.3
        for j in range(4):
            ops.at(t - 1.5 + 0.4 * j, {"robot1": (0.0, 0.0), "robot2": (0.0, front), "robot3": (0.0, -4.22)})
        r.tick(t)
    assert not r.done


def test_an_auxiliary_poi_reached_within_a_goto_tolerance_leaves_a_clear_way_on():
    obstacle = np.array([[0.0, 5.5, 0.8]])
    start, poi = np.array([0.3, 0.5]), np.array([0.0, 11.0])
    aux = auxiliary_poi(start, poi, obstacle, margin=0.4)
    assert aux is not None
    for angle in np.linspace(0, 2 * math.pi, 16, endpoint=False):  # stopped anywhere within 5 cm of it
        here = aux + 0.05 * np.array([math.cos(angle), math.sin(angle)])
        assert not segment_hits(here, poi, obstacle, 0.4).any()
        step = widep_step(np.array([here, [0.0, 12.0]]), 0, poi, 4.5, obstacles=obstacle, margin=0.4)
        assert not step.auxiliary and step.length > 0.5


@pytest.mark.parametrize("weight, pinned", [(1.0, True), (None, False)])
def test_a_crowd_pins_a_robot_to_a_wall_only_when_the_wall_weighs_as_one_robot(weight, pinned):
    # robot 0 is 0.3 m from the wall y = 0, six robots 3 m above push it toward the wall
    crowd = [[x, 3.3] for x in (-2.5, -1.5, -0.5, 0.5, 1.5, 2.5)]
    pos = np.array([[0.0, 0.3], *crowd])
    cfg = SpreadConfig(distance=5.0, range=6.0, wall_distance=2.5, obstacle_weight=weight, chi=0.0)
    f, _ = forces(pos, np.zeros(len(pos)), cfg, walls=np.array([[-50.0, 0.0, 50.0, 0.0]]))
    assert (f[0, 1] < 0) == pinned  # toward the wall: pinned; away from it: held off


def test_a_relay_that_cannot_move_says_it_is_stalled():
    ops = FakeOps()
    ops.qualities = {"src": 1.0, "dst": 0.2}  # the destination link is worse: it should move toward it
    task = Task(verb="Deploy", preposition="relay", params={"source": "src", "destination": "dst"},
                source="control", destination="robot1")
    r = RelayRunner(task, ops, MissionSettings(), 0.0)
    for k in range(7):  # its gotos "succeed" but the robot is never seen anywhere else (blocked)
        t = 2.0 * (k + 1)
        ops.at(t - 0.1, {"robot1": (2.0, 0.0), "src": (0.0, 0.0), "dst": (10.0, 0.0)})
        r.tick(t)
    assert ops.issued and ops.issued[0][0] == "goto"
    messages = [m for _, m in ops.reports]
    assert messages[0] == "moving toward dst" and messages[-1].startswith("stalled: links unbalanced")
    assert r.values()["stalled"] is True
