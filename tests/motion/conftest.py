"""Motion fixtures: a fast simulated robot, or the real robot named by ERNI_ROBOT_URL.

With `ERNI_ROBOT_URL` set (a serial device, or `socket://host:8101` for MobileSim/AMRISim) every
test that drives a robot drives that one; a test that needs ERNI's own simulator (its walls,
its internals) is skipped with the reason, never run on the simulator instead.
"""

from __future__ import annotations

import os
from collections.abc import Iterator

import pytest

from erni.plugins.motion.driver import ArcosDriver, LinkError
from erni.sim.robot import SimRobotConfig
from erni.sim.robot_host import RobotHost
from erni.sim.world import World

REAL_URL = os.environ.get("ERNI_ROBOT_URL", "").strip()
SIM_REASON = "needs ERNI's own simulator, and ERNI_ROBOT_URL names the robot every test must drive"

sim_only = pytest.mark.skipif(bool(REAL_URL), reason=SIM_REASON)


def sim_only_because(why: str) -> pytest.MarkDecorator:
    """Skip in the real-robot mode, saying what the test needs from ERNI's simulator."""
    return pytest.mark.skipif(bool(REAL_URL), reason=f"{why}: {SIM_REASON}")


FAST = dict(sip_period=0.02, accel=3.0, decel=3.0, max_v=2.0, rot_accel=720.0, max_rv=360.0)
FAST_MODEL = {"base": "pioneer3", "decel": 2.5, "rot_decel": 500.0, "max_rv": 300.0, "max_v": 2.0}


def fast_config(**kw: object) -> SimRobotConfig:
    """A simulated Pioneer that accelerates hard and reports every 20 ms."""
    return SimRobotConfig(**{**FAST, **kw})  # type: ignore[arg-type]


@pytest.fixture
def sim_hosts() -> Iterator[list[RobotHost]]:
    """The simulated robots a test started; stopped at teardown."""
    hosts: list[RobotHost] = []
    yield hosts
    for h in hosts:
        h.stop()


def _start(hosts: list[RobotHost], world: World | None = None, pty: bool = False, **kw: object) -> RobotHost:
    host = RobotHost(world, physics_hz=200)
    host.add_robot(fast_config(**kw), pty=pty, port=None if pty else 0)
    hosts.append(host)
    return host.start()


@pytest.fixture
def make_host(sim_hosts):
    """Factory of started RobotHosts (one robot each unless told); skips the test in the real-robot mode."""
    if REAL_URL:
        pytest.skip(SIM_REASON)
    return lambda world=None, pty=False, **kw: _start(sim_hosts, world, pty, **kw)


@pytest.fixture
def robot_url(sim_hosts) -> str:
    """The robot under test: ERNI_ROBOT_URL if set, else a fast simulated robot over TCP."""
    if REAL_URL:
        return REAL_URL
    return _start(sim_hosts).url()


@pytest.fixture(scope="session")
def real_robot() -> ArcosDriver | None:
    """What the robot under test says about itself (SYNC2 and CONFIG), asked once; None without ERNI_ROBOT_URL."""
    if not REAL_URL:
        return None
    driver = ArcosDriver(REAL_URL, name="probe", reconnect=False)
    try:
        driver.open()
    except LinkError as err:
        pytest.fail(f"ERNI_ROBOT_URL={REAL_URL}: {err}")
    driver.close()
    return driver


def skip_on_simulators_without_watchdog(driver: ArcosDriver | None) -> None:
    """MobileSim and AMRISim only warn when their watchdog expires; they keep the robot moving."""
    cfg = driver.robot_config if driver is not None else None
    if cfg is not None and cfg.simulator and (cfg.name or "").lower() in ("amrisim", "mobilesim"):
        pytest.skip(f"{cfg.name} only warns when its watchdog expires and keeps driving (its EmulatePioneer "
                    "takes no action), so a stop on silence cannot be checked on it")
