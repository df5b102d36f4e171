"""`erni stop` against an `erni sim` team, as an operator runs it from another terminal.

Robots are set moving with `erni task --wait` (a RemoteBotMotion forward that MissionControl
runs, a BotMotion turn straight to the robot); `erni stop` (every robot, or the ones named)
says on one line which robots took the stop, the tasks it stopped end `cancelled`, and the
robots stand, as the control node's watch shows them.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from collections.abc import Iterator
from typing import Any

import pytest

from erni.blackboard.testing import wait_until
from tests.sim.test_sim_cli import ROOT, SimProcess

HALTED_V, HALTED_W = 0.01, 0.02  # m/s, rad/s: a robot standing


@pytest.fixture(scope="module")
def team(tmp_path_factory: pytest.TempPathFactory) -> Iterator[dict[str, Any]]:
    run = tmp_path_factory.mktemp("stop") / "run"
    sim = SimProcess(run, "--robots", "2", "--control-port", "0")
    try:
        sim.wait_for("Ctrl-C stops the team", timeout=120)
        via = sim.wait_for("erni peers --via", timeout=1).split("--via")[1].strip()
        yield {"via": via, "env": {**os.environ, "ERNI_IDENTITY": str(run / "keys" / "cli.pem"),
                                   "PYTHONUNBUFFERED": "1"}}
    finally:
        sim.cleanup()


def erni(team: dict[str, Any], *args: str, via: bool = True, timeout: float = 60) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, "-m", "erni", args[0], *(["--via", team["via"]] if via else []), *args[1:]],
                          cwd=ROOT, env=team["env"], capture_output=True, text=True, timeout=timeout)


def moving(team: dict[str, Any], robot: str, *task: str) -> subprocess.Popen[str]:
    """`erni task --wait` of a motion, returned once the robot runs it."""
    proc = subprocess.Popen([sys.executable, "-m", "erni", "task", "--via", team["via"], robot, *task, "--wait"],
                            cwd=ROOT, env=team["env"], stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    assert proc.stdout is not None
    for line in proc.stdout:
        if " running " in line:
            return proc
    raise AssertionError(f"{robot} never ran {task}: exit {proc.wait(10)}")


def poses(team: dict[str, Any], seconds: float) -> dict[str, dict[str, Any]]:
    """Each robot's last Pose the control node streams within `seconds`."""
    out = subprocess.run([sys.executable, "-m", "erni", "watch", "--via", team["via"], "--json", "--seconds",
                          str(seconds)], cwd=ROOT, env=team["env"], capture_output=True, text=True, timeout=60)
    last: dict[str, dict[str, Any]] = {}
    for line in out.stdout.splitlines():
        event = json.loads(line)
        if event.get("type") == "Pose":
            last[event["data"]["robot"]] = event["data"]
    return last


def ended(proc: subprocess.Popen[str]) -> tuple[int, str]:
    out, _ = proc.communicate(timeout=30)
    return proc.returncode, out.strip().splitlines()[-1]


def test_stop_without_names_stops_every_robot_and_their_tasks_end_cancelled(team):
    forward = moving(team, "robot1", "RemoteBotMotion", "forward", "distance=20")
    turn = moving(team, "robot2", "BotMotion", "turn", "angle=3600")
    out = erni(team, "stop")
    assert out.returncode == 0, out.stderr
    (line,) = out.stdout.splitlines()
    assert line.startswith(f"stop taken by 2 of 2 robots through {team['via']}: robot1 "), line
    assert ", robot2 " in line and out.stderr == ""
    for proc in (forward, turn):
        code, last = ended(proc)
        assert code == 1 and " cancelled " in last, last
    wait_until(lambda: all(abs(p["v"]) < HALTED_V and abs(p["w"]) < HALTED_W
                           for p in poses(team, 1.5).values()), timeout=10, interval=0.1,
               message="a robot still moves after the stop")


def test_stop_of_named_robots_in_the_botmotion_tier(team):
    turn = moving(team, "robot1", "BotMotion", "turn", "angle=3600")
    out = erni(team, "stop", "--verb", "BotMotion", "robot1", "--json")
    assert out.returncode == 0, out.stderr
    (said,) = [json.loads(line) for line in out.stdout.splitlines()]
    assert said["taken"] == said["asked"] == 1 and said["verb"] == "BotMotion"
    assert said["robots"]["robot1"]["state"] in ("succeeded", "running")
    code, last = ended(turn)
    assert code == 1 and " cancelled " in last, last


def test_a_name_not_in_the_team_is_said_and_exits_1_but_the_others_are_stopped(team):
    out = erni(team, "stop", "robot2", "ghost")
    assert out.returncode == 1 and out.stdout == ""
    (line,) = out.stderr.splitlines()
    assert line.startswith(f"erni stop: stop taken by 1 of 2 robots through {team['via']}: robot2 "), line
    assert line.endswith(", ghost not in the team"), line


def test_nothing_answering_exits_1_on_one_line(team):
    out = erni(team, "stop", "--via", "127.0.0.1:9", via=False)
    assert out.returncode == 1 and out.stdout == ""
    assert out.stderr.startswith("erni stop: ") and len(out.stderr.splitlines()) == 1, out.stderr


@pytest.mark.parametrize("args, said", [
    (["bad name!"], "erni stop: ROBOT 'bad name!': expected a name"),
    (["--via", "nohost", "robot1"], "expected HOST:PORT"),
])
def test_bad_arguments_exit_2_on_one_line(team, args, said):
    out = erni(team, "stop", *args, via="--via" not in args)
    assert out.returncode == 2 and out.stdout == ""
    assert said in out.stderr and len(out.stderr.splitlines()) == 1, out.stderr


def test_a_stop_imports_neither_the_agent_nor_the_simulator_nor_a_plugin(team):
    """The whole run of `erni stop`, its answers read: every module it imported, as -X importtime lists them."""
    out = subprocess.run([sys.executable, "-X", "importtime", "-m", "erni", "stop", "--via", team["via"], "robot1"],
                         cwd=ROOT, env=team["env"], capture_output=True, text=True, timeout=60)
    assert out.returncode == 0, out.stderr
    imported = {line.split("|")[-1].strip() for line in out.stderr.splitlines() if line.startswith("import time:")}
    heavy = ("erni.blackboard.agent", "erni.blackboard.schemas", "erni.transport.plugin", "erni.sim", "erni.plugins",
             "numpy", "aiohttp", "zenoh")
    assert sorted(m for m in imported if m.startswith(heavy)) == []
    assert "erni.transport.client" in imported  # it did send, through the client

