"""Commands mean what an operator means, on a running team: obstacle avoidance stays on until
turned off, "cancel that" cancels the last command carried out, "set speed" and "faster" /
"slower" set the cruise speed of later moves, "go to robot 2" drives to that robot and stops
short. Typed through `erni console` and the page; the control node's own robots are simulated."""

from __future__ import annotations

import asyncio
import math
import os
import subprocess
import sys
from collections.abc import Iterator
from functools import partial

import pytest

from erni.blackboard import Agent, Pose, Task
from erni.blackboard.testing import wait_until
from tests.ui.team import KEY, Team, start_team
from tests.ui.test_console import ROOT, console
from tests.ui.test_server import of, talk


@pytest.fixture(scope="module")
def team() -> Iterator[Team]:
    team = start_team(2)
    yield team
    team.stop()


def robot(team: Team, name: str) -> Agent:
    return next(a for a in team.robots if a.name == name)


def tasks_on(team: Team, name: str, preposition: str) -> list[Task]:
    """The tasks of a kind the robot's own agent holds."""
    return [t for t in robot(team, name).query(Task) if t.preposition == preposition]


def apart(team: Team, a: str, b: str) -> float:
    pa, pb = team.pose(a), team.pose(b)
    assert pa is not None and pb is not None
    return math.hypot(pa.x - pb.x, pa.y - pb.y)


def halted(team: Team, name: str) -> None:
    wait_until(lambda: (p := team.pose(name)) is not None and abs(p.v) < 0.01 and abs(p.w) < 0.01, timeout=15,
               message=f"{name} did not come to a halt")


def console_sampling(team: Team, lines: str, name: str) -> tuple[subprocess.CompletedProcess[str], float]:
    """Run `erni console` and sample the robot's speed while it runs, at each Pose it publishes: the output
    and the top speed (m/s)."""
    env = {**os.environ, "ERNI_TEAM_KEY": KEY}
    proc = subprocess.Popen([sys.executable, "-m", "erni", "console", "--via", team.via, "--verb", "BotMotion",
                             "--timeout", "20"], stdin=subprocess.PIPE, stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True, env=env, cwd=ROOT)
    assert proc.stdin is not None
    proc.stdin.write(lines)
    proc.stdin.close()
    top = 0.0
    seen: Pose | None = None

    def moved_on(last: Pose | None) -> bool:
        """The console ended, or the robot published a Pose after `last`."""
        return proc.poll() is not None or team.pose(name) != last

    while proc.poll() is None:
        wait_until(partial(moved_on, seen), timeout=60,
                   message="the console neither ended nor did the robot publish a Pose")
        seen = team.pose(name)
        if seen is not None:
            top = max(top, abs(seen.v))
    assert proc.stdout is not None and proc.stderr is not None
    out = subprocess.CompletedProcess(proc.args, proc.returncode, proc.stdout.read(), proc.stderr.read())
    return out, top


def typed(team: Team, *texts: str) -> list[str]:
    """Type lines on the page, one at a time; return the replies."""
    url = f"ws://127.0.0.1:{team.ui.server.port}/ws?token={team.ui.server.token}"
    said = []
    for text in texts:
        msgs = asyncio.run(talk(url, [{"type": "say", "text": text, "selection": []}], lambda m: of(m, "reply")))
        said.append(of(msgs, "reply")[0]["text"])
    return said


def log_lines(team: Team) -> list[str]:
    return [line["text"] for line in team.ui.server.state()["log"]]


# -- obstacle avoidance ----------------------------------------------------------------------


def test_obstacle_avoidance_from_the_console_stays_on_through_later_moves(team):
    out = console(team, "robot 1 avoid obstacles within 40 centimetres\nrobot 1 go forward 0.3 metres\n")
    assert out.returncode == 0, out.stdout + out.stderr
    assert "Roger: robot 1, avoid obstacles at 0.4 metres" in out.stdout
    assert "robot1: forward succeeded" in out.stdout
    assert "avoid_obstacles cancelled" not in out.stdout  # a move does not turn avoidance off
    assert "not finished within" not in out.stdout  # and the console does not wait for it to end
    avoid = tasks_on(team, "robot1", "avoid_obstacles")
    assert [(t.done, t.params.distance) for t in avoid] == [(False, 0.4)]
    out = console(team, "robot 1 stop avoiding obstacles\n")  # turned off explicitly: then it ends
    assert "Roger: robot 1, stop avoiding obstacles" in out.stdout
    wait_until(lambda: all(t.done for t in tasks_on(team, "robot1", "avoid_obstacles")
                           if t.uid == avoid[0].uid), timeout=10, message="avoidance was not turned off")


def test_obstacle_avoidance_from_the_page_stays_on_through_later_moves(team):
    assert typed(team, "robot 2 avoid obstacles", "robot 2 go forward 0.2 metres", "robot 2 turn left 10 degrees") == [
        "Roger: robot 2, avoid obstacles", "Roger: robot 2, go forward 0.2 metres", "Roger: robot 2, turn left 10 degrees"]
    turn = wait_until(lambda: [t for t in tasks_on(team, "robot2", "turn") if t.done], timeout=15)[0]
    assert turn.state.value == "succeeded"
    avoid = [t for t in tasks_on(team, "robot2", "avoid_obstacles") if not t.done]
    assert len(avoid) == 1
    assert not any("robot2: avoid_obstacles cancelled" in line for line in log_lines(team)), log_lines(team)
    # the control node hears the turn's end a moment after robot 2's own board holds it
    wait_until(lambda: [r for r in team.ui.server.state()["tasks"] if r["preposition"] == "turn"
                        and r["robot"] == "robot2" and r["state"] == "succeeded"], timeout=10)
    assert typed(team, "what is robot 2 doing") == ["Robot 2 is idle"]  # avoiding obstacles is not a task in hand
    assert typed(team, "robot 2 avoid obstacles off") == ["Roger: robot 2, stop avoiding obstacles"]
    wait_until(lambda: not [t for t in tasks_on(team, "robot2", "avoid_obstacles") if not t.done], timeout=10)


# -- cancel that -----------------------------------------------------------------------------


def test_cancel_that_cancels_the_last_command_carried_out_not_the_last_robot_named(team):
    p0 = team.pose("robot1")
    assert p0 is not None
    out = console(team, "robot 1 go forward 3 metres\nrobot 2 fly\nrobot 2 status\ncancel that\ncancel that\n")
    lines = out.stdout.splitlines()
    assert "Roger: cancelled robot 1, go forward 3 metres" in lines
    assert "Nothing to cancel: no command carried out yet; to halt a robot say robot 1 stop" in lines
    assert any(line.endswith("robot1: forward cancelled \u2014 cancelled by the operator") for line in lines), lines
    assert "robot1: forward succeeded" not in out.stdout
    assert not any(line.startswith("Roger: robot 2") for line in lines)  # robot 2 was only asked about
    halted(team, "robot1")
    p1 = team.pose("robot1")
    assert p1 is not None and math.hypot(p1.x - p0.x, p1.y - p0.y) < 1.0


def test_cancel_that_on_the_page_withdraws_the_last_command(team):
    p0 = team.pose("robot1")
    assert p0 is not None
    said = typed(team, "robot 1 turn left 270 degrees", "robot 2 where are you", "cancel that")
    assert said[0] == "Roger: robot 1, turn left 270 degrees" and said[1].startswith("Robot 2 is at x ")
    assert said[2] == "Roger: cancelled robot 1, turn left 270 degrees"
    row = wait_until(lambda: [r for r in team.ui.server.state()["tasks"] if r["preposition"] == "turn"
                              and r["state"] == "cancelled" and r["message"] == "cancelled by the operator"],
                     timeout=10)
    assert row[0]["robot"] == "robot1"
    halted(team, "robot1")
    p1 = team.pose("robot1")
    assert p1 is not None and abs(math.degrees(math.remainder(p1.theta - p0.theta, 2 * math.pi))) < 150
    assert not [t for t in tasks_on(team, "robot2", "clear") + tasks_on(team, "robot2", "stop")]


# -- cruise speed ----------------------------------------------------------------------------


def test_set_velocity_sets_the_speed_of_later_moves_and_drives_nothing(team):
    p0 = team.pose("robot1")
    assert p0 is not None
    out, top = console_sampling(team, "robot 1 turn around\nrobot one set velocity 0.2\n", "robot1")
    assert "Roger: robot 1, cruise speed 0.2 metres per second" in out.stdout
    assert top < 0.05  # nothing drove: a turn in place and a setting
    p1 = team.pose("robot1")
    assert p1 is not None and math.hypot(p1.x - p0.x, p1.y - p0.y) < 0.05
    out, top = console_sampling(team, "robot 1 set speed 0.2\nrobot 1 go forward 0.8 metres\n", "robot1")
    assert "Roger: robot 1, go forward 0.8 metres at 0.2 metres per second" in out.stdout
    assert "robot1: forward succeeded" in out.stdout
    assert 0.15 < top < 0.24  # the default cruise speed is 0.3 m/s
    out, top = console_sampling(team, "robot 1 set speed 0.2\nfaster\nrobot 1 go back 0.8 metres\n", "robot1")
    assert "Roger: robot 1, faster, cruise speed 0.3 metres per second" in out.stdout
    assert "robot1: backward succeeded" in out.stdout
    assert 0.25 < top < 0.34


def test_slow_down_re_sends_a_running_go_to_at_the_new_speed(team):
    p0 = team.pose("robot1")
    assert p0 is not None
    x, y = round(p0.x + 1.0 * math.cos(p0.theta), 2), round(p0.y + 1.0 * math.sin(p0.theta), 2)
    out = console(team, f"robot 1 go to {x} {y}\nslow down\nslower\n")
    lines = out.stdout.splitlines()
    assert "Roger: robot 1, slower, cruise speed 0.2 metres per second (the running go to x " \
           f"{x:g}, y {y:g} of robot 1 too)" in lines
    assert "Roger: robot 1, slower, cruise speed 0.13 metres per second (the running go to x " \
           f"{x:g}, y {y:g} of robot 1 too)" in lines
    assert sum(1 for line in lines if line.endswith("goto cancelled \u2014 re-sent at a new speed")) == 2
    assert sum(1 for line in lines if "robot1: goto succeeded" in line) == 1
    goto = [t for t in tasks_on(team, "robot1", "goto") if t.state.value == "succeeded"]
    assert goto and goto[-1].params.speed == 0.13
    p1 = team.pose("robot1")
    assert p1 is not None and math.hypot(p1.x - x, p1.y - y) < 0.2


# -- go to a robot ---------------------------------------------------------------------------


def test_go_to_robot_two_and_come_to_robot_one_stop_short_of_that_robot(team):
    out = console(team, "robot 1 go to robot 2\n")
    assert out.returncode == 0, out.stdout + out.stderr
    assert any(line.startswith("Roger: robot 1, go to robot 2 (x ") for line in out.stdout.splitlines())
    assert "robot1: goto succeeded" in out.stdout
    assert apart(team, "robot1", "robot2") == pytest.approx(1.0, abs=0.2)
    console(team, "robot 1 go back 1 metre\n")
    assert apart(team, "robot1", "robot2") > 1.5
    out = console(team, "robot 2 come to robot one\n")
    assert "robot2: goto succeeded" in out.stdout, out.stdout
    assert apart(team, "robot1", "robot2") == pytest.approx(1.0, abs=0.2)


def test_go_to_an_unknown_robot_is_refused_and_nothing_moves(team):
    out = console(team, "robot 1 go to robot 7\nrobot 2 go to robot 2\n")
    lines = out.stdout.splitlines()
    assert "I don't know robot 7; I know robots 1 and 2" in lines
    assert "Robot 2 is already there; name another robot to go to it" in lines
    assert out.returncode == 1 and "goto" not in out.stdout
