"""The team the scale benchmarks start: N robots on a 3 m grid in a hall that the radio spans."""

from __future__ import annotations

import math
import sys
import time
from typing import Any

from erni.blackboard.schemas import ResultUpdate
from erni.blackboard.tasks import TaskState
from erni.sim.scenario import Scenario
from erni.sim.team import Team

WALK_TRIES = 4  # a walk that fails (its robot's link lost under the start-up's load) is sent again


def start_hall_team(name: str, n: int, *, walk: bool, settle: float, **team: Any) -> tuple[Team, float]:
    """Start the team as `erni sim` does, random-walk every robot unless told not to, wait `settle`
    seconds; return the started team (the caller stops it) and its start-up time (s).

    Every walk must be running before this returns: a robot whose walk failed would stand, and a
    standing robot's Pose goes out when it changes (the others' echoes in its sonar) or once a
    second, not every period. Such a walk is sent again, and a robot that will not walk stops the
    benchmark with its reason. `team` goes to `Team` (where the agents run: `listen`, `agent_hosts`)."""
    side = max(1, math.ceil(math.sqrt(n))) * 3.0
    scenario = Scenario(name=name, robots={"count": n, "layout": "grid", "spacing": 3.0,
                                           "origin": [0.0, 0.0], "heading": "random"},
                        radio={"comm_range": 1000.0, "lossless_range": 1000.0},
                        world={"name": "hall", "bounds": [-side / 2 - 3, -3.0, side / 2 + 3, side + 3]})
    team = Team(scenario, headless=True, control_port=0, ui=False, **team)  # robots run what a robot runs
    t0 = time.monotonic()
    try:
        team.start(timeout=60 + 3 * n)
        startup = time.monotonic() - t0
        if walk:
            walking(team, settle)
        else:
            time.sleep(settle)
    except BaseException:
        team.stop()
        raise
    return team, startup


def walking(team: Team, settle: float) -> None:
    """Random-walk every robot; return once every walk has run for `settle` seconds without failing."""
    def send(robot: str) -> str:
        return str(team.send_task(robot, "BotMotion", "randomwalk", speed=0.3, seed=1).uid)

    walks = {send(robot): robot for robot in team.names}
    tries = dict.fromkeys(team.names, 1)
    running: set[str] = set()
    client = team.client()
    quiet_since = time.monotonic()
    deadline = time.monotonic() + 60 + settle
    while len(running) < len(walks) or time.monotonic() - quiet_since < settle:
        if time.monotonic() > deadline:
            late = sorted(r for uid, r in walks.items() if uid not in running)
            raise SystemExit(f"hall: {len(late)} robots did not start walking within 60 s: {', '.join(late)}")
        msg = client.receive(0.1)
        if msg is None or msg.kind != "task.result" or not isinstance(msg.body, ResultUpdate):
            continue
        uid, result = msg.body.uid, msg.body.result
        robot = walks.get(uid)
        if robot is None:
            continue
        if result.state is TaskState.RUNNING:
            running.add(uid)
        elif result.state.done:
            del walks[uid]
            running.discard(uid)
            if tries[robot] >= WALK_TRIES:
                raise SystemExit(f"hall: {robot}'s walk ended {result.state.value} {tries[robot]} times; "
                                 f"the last: {result.message}")
            print(f"hall: {robot}'s walk {result.state.value} ({result.message}); sent again",
                  file=sys.stderr, flush=True)
            tries[robot] += 1
            walks[send(robot)] = robot
            quiet_since = time.monotonic()
