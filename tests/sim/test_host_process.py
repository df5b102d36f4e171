"""The team's simulated robots in a process of their own: real ARCOS over TCP, the poses shared."""

from __future__ import annotations

import math
import os
import signal
import subprocess
import sys
from pathlib import Path

import pytest

from erni.blackboard.errors import NetworkError
from erni.blackboard.testing import wait_until
from erni.plugins.motion.driver import ArcosDriver
from erni.sim.host_process import HostProcess
from erni.sim.robot import SimRobotConfig
from erni.sim.world import World

ROOT = Path(__file__).resolve().parents[2]


def started(tmp_path: Path, count: int = 2) -> HostProcess:
    world = World.model_validate({"robot": [{"name": f"r{i}", "x": 2.0 * i, "y": 1.0, "heading": 90.0}
                                            for i in range(count)]})
    host = HostProcess(world, physics_hz=20.0)
    for i in range(count):
        host.add_robot(SimRobotConfig(name=f"r{i}"))
    return host.start(tmp_path / "robots.state", tmp_path / "robots.log")


def test_a_driver_drives_a_robot_of_the_child_and_the_parent_sees_it_move_teleport_and_lose_its_cable(tmp_path):
    host = started(tmp_path)
    driver = ArcosDriver(host.url(1), reconnect_delay=0.1)
    try:
        r = host.robots[1]
        assert (r.name, r.start) == ("r1", pytest.approx((2.0, 1.0, math.pi / 2)))
        assert (r.x, r.y) == pytest.approx((2.0, 1.0))
        driver.open(timeout=10)
        wait_until(lambda: host.connected()[1], timeout=5)
        assert not host.connected()[0]
        driver.vel(0.3)
        wait_until(lambda: r.y > 1.3, timeout=10)  # heading north
        assert r.v > 0 and r.commanded_v == pytest.approx(0.3) and r.energy > 0
        assert host.robots[0].y == pytest.approx(1.0)
        driver.vel(0.0)
        host.teleport(1, 5.0, -2.0, 0.0)
        wait_until(lambda: abs(r.x - 5.0) < 0.05 and abs(r.y + 2.0) < 0.05, timeout=5)
        before = host.timing()  # the host's counters: its steps and the SIPs its robots sent
        wait_until(lambda: host.timing()["sips"] >= before["sips"] + 5, timeout=5,
                   message="the host's SIP count does not grow while a driver is connected")
        after = host.timing()
        assert after["steps"] > before["steps"] and after["skipped"] >= 0
        assert driver.stats.sips >= after["sips"] - 10  # what it counts sent is what the driver got
        connects = driver.stats.connects
        host.cut(1)
        wait_until(lambda: driver.stats.link_losses >= 1, timeout=10)
        wait_until(lambda: driver.stats.connects > connects and host.connected()[1], timeout=15)
    finally:
        driver.close()
        host.stop()
    assert not (tmp_path / "robots.state").exists()


def test_a_bad_robot_config_is_one_line_from_the_child_and_nothing_is_left(tmp_path):
    host = HostProcess(World(), physics_hz=20.0)
    host.add_robot(SimRobotConfig(name="r0"))
    host.configs[0] = host.configs[0].model_copy(update={"radius": -1.0})  # past the model's own check
    with pytest.raises(NetworkError, match="the robot host did not start: ValidationError: 1 validation error"):
        host.start(tmp_path / "robots.state", tmp_path / "robots.log")
    assert host.pid is None and not (tmp_path / "robots.state").exists()


LAUNCHER = """
import signal, sys
from pathlib import Path
from erni.sim.host_process import HostProcess
from erni.sim.robot import SimRobotConfig
from erni.sim.world import World
host = HostProcess(World(), physics_hz=20.0)
host.add_robot(SimRobotConfig(name="r0"))
host.start(Path(sys.argv[1]) / "robots.state", Path(sys.argv[1]) / "robots.log")
print(host.pid, flush=True)
signal.pause()  # until the test kills it
"""


def test_the_robot_host_dies_with_the_simulator_however_it_goes(tmp_path):
    launcher = subprocess.Popen([sys.executable, "-c", LAUNCHER, str(tmp_path)], cwd=ROOT,
                                stdout=subprocess.PIPE, text=True)
    try:
        child = int(launcher.stdout.readline())
        os.kill(child, 0)  # running
        launcher.send_signal(signal.SIGKILL)
        launcher.wait(10)

        def gone() -> bool:
            try:
                os.kill(child, 0)
            except ProcessLookupError:
                return True
            return Path(f"/proc/{child}/stat").read_text().split()[2] == "Z"

        wait_until(gone, timeout=10)
    finally:
        if launcher.poll() is None:
            launcher.kill()
            launcher.wait()
