"""No robot of a spread run moves faster than its robot model allows (paper 001 in the kinematic mode)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from erni.sim.experiments import spread
from erni.sim.scenario import find_scenario, load_scenario


def _scenario(name: str, robots: int, seconds: float, **strategy: object):
    sc = load_scenario(find_scenario(name)).with_robots(robots)
    return sc.model_copy(update={"duration": seconds, "strategy": {**sc.strategy, "sample": 0.2, **strategy}})


@pytest.mark.parametrize("variant", ["holonomic/delaunay", "nonholonomic/delaunay", "holonomic/physical"])
def test_no_robot_outruns_its_model_while_a_packed_team_spreads(variant):
    sc = _scenario("spread-corridor", 40, 12.0)
    vmax, wmax = spread.robot_limits(sc)
    assert vmax == 1.5 and math.isclose(wmax, math.radians(300))  # the simulator's Pioneer (SimRobotConfig)
    run = spread._kinematic(sc, lambda *a: None, variant, variant)
    assert run.speed.max() <= vmax + 1e-9
    moved = np.hypot(*np.diff(run.pos, axis=0).transpose(2, 0, 1))  # (T-1, N) metres between samples
    rate = moved / np.diff(run.t)[:, None]
    assert rate.max() <= vmax + 1e-9
    assert rate.max() > 0.9 * vmax  # the packed start's springs do push at the limit: the cap is what holds them
    turned = np.abs((np.diff(run.th, axis=0) + math.pi) % (2 * math.pi) - math.pi) / np.diff(run.t)[:, None]
    assert turned.max() <= wmax + 1e-9


def test_an_amigobot_team_is_held_to_the_amigobots_top_speed():
    sc = _scenario("spread-open", 30, 6.0)
    sc = sc.model_copy(update={"robots": sc.robots.model_copy(update={"model": "amigobot"})})
    vmax, _ = spread.robot_limits(sc)
    assert vmax == 0.75
    run = spread._kinematic(sc, lambda *a: None, "holonomic/delaunay", "")
    assert run.speed.max() <= vmax + 1e-9
