"""Motion fixtures: a fast simulated robot, or the real robot named by ERNI_ROBOT_URL."""

from __future__ import annotations

import os
from collections.abc import Iterator

import pytest

from erni.sim.robot import SimRobotConfig
from erni.sim.robot_host import RobotHost
from erni.sim.world import World

REAL_URL = os.environ.get("ERNI_ROBOT_URL", "").strip()

sim_only = pytest.mark.skipif(bool(REAL_URL), reason="needs the simulator itself (ERNI_ROBOT_URL is set)")

FAST = dict(sip_period=0.02, accel=3.0, decel=3.0, max_v=2.0, rot_accel=720.0, max_rv=360.0)
FAST_MODEL = {"base": "pioneer3", "decel": 2.5, "rot_decel": 500.0, "max_rv": 300.0, "max_v": 2.0}


def fast_config(**kw: object) -> SimRobotConfig:
    """A simulated Pioneer that accelerates hard and reports every 20 ms."""
    return SimRobotConfig(**{**FAST, **kw})  # type: ignore[arg-type]


@pytest.fixture
def make_host() -> Iterator:
    """Factory of started RobotHosts (one robot each unless told), all stopped at teardown."""
    hosts: list[RobotHost] = []

    def make(world: World | None = None, pty: bool = False, **kw: object) -> RobotHost:
        host = RobotHost(world, physics_hz=200)
        host.add_robot(fast_config(**kw), pty=pty, port=None if pty else 0)
        hosts.append(host)
        return host.start()

    yield make
    for h in hosts:
        h.stop()


@pytest.fixture
def robot_url(make_host) -> str:
    """The robot under test: ERNI_ROBOT_URL if set, else a fast simulated robot over TCP."""
    if REAL_URL:
        return REAL_URL
    return make_host().url()
