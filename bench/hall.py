"""The team the scale benchmarks start: N robots on a 3 m grid in a hall that the radio spans."""

from __future__ import annotations

import math
import time

from erni.sim.scenario import Scenario
from erni.sim.team import Team


def start_hall_team(name: str, n: int, *, walk: bool, settle: float) -> tuple[Team, float]:
    """Start the team as `erni sim` does, random-walk every robot unless told not to, wait `settle`
    seconds; return the started team (the caller stops it) and its start-up time (s)."""
    side = max(1, math.ceil(math.sqrt(n))) * 3.0
    scenario = Scenario(name=name, robots={"count": n, "layout": "grid", "spacing": 3.0,
                                           "origin": [0.0, 0.0], "heading": "random"},
                        radio={"comm_range": 1000.0, "lossless_range": 1000.0},
                        world={"name": "hall", "bounds": [-side / 2 - 3, -3.0, side / 2 + 3, side + 3]})
    team = Team(scenario, headless=True, control_port=0, ui=False)  # robots run what a robot runs
    t0 = time.monotonic()
    try:
        team.start(timeout=60 + 3 * n)
        startup = time.monotonic() - t0
        if walk:
            for robot in team.names:
                team.send_task(robot, "BotMotion", "randomwalk", speed=0.3, seed=1)
        time.sleep(settle)
    except BaseException:
        team.stop()
        raise
    return team, startup
