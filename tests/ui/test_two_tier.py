"""The two-tier design end to end: the GUI sends RemoteBotMotion tasks, each robot's
MissionControl expands them into BotMotion, and the results come back to the page."""

from __future__ import annotations

import asyncio
import math
from collections.abc import Iterator

import pytest

from erni.blackboard import Task
from erni.blackboard.testing import wait_until
from tests.ui.team import Team, start_team
from tests.ui.test_server import of, talk

MISSION = {"network_aware": False, "audio": False}


@pytest.fixture
def team() -> Iterator[Team]:
    team = start_team(2, mission=MISSION)
    yield team
    team.stop()


def say(team: Team, text: str) -> dict:
    url = f"ws://127.0.0.1:{team.ui.server.port}/ws?token={team.ui.server.token}"
    msgs = asyncio.run(talk(url, [{"type": "say", "text": text, "selection": []}], lambda m: of(m, "reply")))
    return of(msgs, "reply")[0]


def test_spoken_goto_travels_as_remotebotmotion_and_the_robot_arrives(team):
    assert say(team, "robot 2 go to 3 2")["text"] == "Roger: robot 2, go to x 3, y 2"
    remote = wait_until(lambda: [t for t in team.control.query(Task) if t.verb == "RemoteBotMotion"], timeout=20)[0]
    assert (remote.preposition, remote.destination, remote.params.x, remote.params.y) == ("goto", "robot2", 3.0, 2.0)
    sub = wait_until(lambda: [t for t in team.robots[1].query(Task) if t.verb == "BotMotion" and t.parent == remote.uid],
                     timeout=20)
    assert sub, "MissionControl did not expand the remote task"
    done = wait_until(lambda: (t := next(t for t in team.control.query(Task) if t.uid == remote.uid)).done and t,
                      timeout=20, message="the remote goto did not finish")
    assert done.state.value == "succeeded"
    p = team.pose("robot2")
    assert p is not None and math.hypot(p.x - 3.0, p.y - 2.0) < 0.3
    row = wait_until(lambda: [r for r in team.ui.server.state()["tasks"] if r["uid"] == remote.uid
                              and r["state"] == "succeeded"], timeout=20)
    assert row[0]["verb"] == "RemoteBotMotion"


def test_stop_cancels_the_remote_task_and_halts_the_robot(team):
    assert say(team, "robot 1 random walk")["text"] == "Roger: robot 1, random walk"
    wait_until(lambda: (p := team.pose("robot1")) is not None and p.v > 0.1, timeout=20)
    assert say(team, "stop")["text"] == "Roger: robot 1, stop"  # the last target, robot1
    cancel = wait_until(lambda: [t for t in team.control.query(Task) if t.preposition == "cancel"], timeout=20)[0]
    assert (cancel.verb, cancel.destination) == ("RemoteBotMotion", "robot1")
    wait_until(lambda: abs(team.pose("robot1").v) < 0.01, timeout=20, message="robot1 did not halt")
    walk = wait_until(lambda: [t for t in team.control.query(Task) if t.preposition == "randomwalk" and t.done],
                      timeout=20, message="the random walk was not reported finished")[0]
    assert walk.state.value in ("cancelled", "failed")


def test_cancel_that_and_cruise_speed_in_the_two_tier_design(team):
    p0 = team.pose("robot1")
    assert p0 is not None
    for text, said in [("robot 1 avoid obstacles", "Roger: robot 1, avoid obstacles"),
                       ("robot 1 set speed 0.2", "Roger: robot 1, cruise speed 0.2 metres per second"),
                       ("robot 1 go forward 3 metres", "Roger: robot 1, go forward 3 metres at 0.2 metres per second")]:
        assert say(team, text)["text"] == said
    remote = wait_until(lambda: [t for t in team.control.query(Task) if t.verb == "RemoteBotMotion"
                                 and t.preposition == "forward"], timeout=20)[0]
    assert remote.params.speed == 0.2
    wait_until(lambda: (p := team.pose("robot1")) is not None and p.v > 0.1, timeout=20)
    assert say(team, "robot 2 where are you")["text"].startswith("Robot 2 is at")
    assert say(team, "cancel that")["text"] == "Roger: cancelled robot 1, go forward 3 metres at 0.2 metres per second"
    wait_until(lambda: abs(team.pose("robot1").v) < 0.01, timeout=20, message="robot1 did not halt")
    p1 = team.pose("robot1")
    assert p1 is not None and math.hypot(p1.x - p0.x, p1.y - p0.y) < 1.5
    avoid = [t for t in team.robots[0].query(Task) if t.preposition == "avoid_obstacles"]
    assert [t.done for t in avoid] == [False]  # still on
