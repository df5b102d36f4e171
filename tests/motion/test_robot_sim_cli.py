"""`erni robot-sim` as a user runs it: a separate process that an ARCOS client connects to."""

from __future__ import annotations

import signal
import subprocess
import sys
from pathlib import Path

import pytest

from erni.blackboard import Agent
from erni.plugins.motion import ArcosDriver
from tests.motion.conftest import sim_only_because

pytestmark = sim_only_because("tests the `erni robot-sim` simulator itself")

ROOT = Path(__file__).resolve().parents[2]


def erni(*args: str) -> subprocess.Popen[str]:
    return subprocess.Popen([sys.executable, "-m", "erni", *args], cwd=ROOT, text=True,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE)


def test_robot_sim_serves_robots_from_a_world_file_until_interrupted():
    proc = erni("robot-sim", "--port", "0", "--robots", "2", "--world", "examples/world-corridor.toml",
                "--sip-period", "0.02", "--log-level", "WARNING")
    try:
        assert proc.stdout is not None
        lines = [proc.stdout.readline() for _ in range(2)]
        assert lines[0].startswith("robot1: socket://127.0.0.1:") and lines[1].startswith("robot2: socket://")
        driver = ArcosDriver(lines[1].split()[1], name="cli", sync_timeout=0.3)
        with driver:
            s = driver.wait_for_sip()
            assert s is not None and (s.x, s.y) == pytest.approx((0.0, -1.0), abs=1e-3)  # robot2's start
            driver.vel(0.3)
            assert driver.wait_for(lambda s: s.v > 0.2, 3.0)
    finally:
        proc.send_signal(signal.SIGINT)
        assert proc.wait(timeout=10) == 0


def test_robot_sim_serves_the_model_asked_for_and_logs_its_clients_at_debug():
    proc = erni("robot-sim", "--port", "0", "--model", "amigo", "--sip-period", "0.02", "--log-level", "DEBUG")
    try:
        assert proc.stdout is not None
        line = proc.stdout.readline()
        assert "(amigo," in line
        with ArcosDriver(line.split()[1], name="cli", sync_timeout=0.3) as driver:
            assert driver.info.subclass == "amigo" and driver.model.dist_conv == 0.5083
            driver.command(99, 1)  # nothing a robot knows
            driver.vel(0.2)
            assert driver.wait_for(lambda s: s.v > 0.15, 3.0)
    finally:
        proc.send_signal(signal.SIGINT)
        _, err = proc.communicate(timeout=10)
    assert proc.returncode == 0
    for needle in ("client 127.0.0.1:", "handshake done: robot1 Pioneer amigo", "CONFIG 1", "SETA -",
                   "VEL 200", "unknown command 99 ignored", "client closed the connection"):
        assert needle in err, needle


def test_robot_sim_pty_prints_the_device_path():
    proc = erni("robot-sim", "--pty", "--sip-period", "0.02", "--log-level", "WARNING")
    try:
        assert proc.stdout is not None
        path = proc.stdout.readline().split()[1]
        assert path.startswith("/dev/")
        with ArcosDriver(path, name="pty", sync_timeout=0.3) as driver:
            assert driver.wait_for_sip() is not None and driver.info.robot_class == "Pioneer"
    finally:
        proc.send_signal(signal.SIGINT)
        assert proc.wait(timeout=10) == 0


@pytest.mark.parametrize("args,needle", [
    (["--world", "missing.toml"], "missing.toml: no such world file"),
    (["--robots", "0"], "--robots: expected at least 1"),
    (["--port", "70000"], "--port: expected"),
    (["--model", "roomba"], "--model: unknown robot model 'roomba'; expected one of p3dx-sh, p3at-sh"),
    (["--sonar-cycle", "-1"], "--sonar-cycle: expected seconds >= 0"),
])
def test_robot_sim_bad_arguments_exit_2_with_one_clear_line(args, needle):
    proc = erni("robot-sim", *args)
    out, err = proc.communicate(timeout=60)  # a progress bound: start-up was over 20 s at load 19
    assert proc.returncode == 2 and needle in err and len(err.strip().splitlines()) == 1


def test_example_agent_config_loads():
    agent = Agent.from_config(ROOT / "examples" / "robot-motion.toml")
    plugin = agent.plugin("motion")
    assert plugin.settings.url == "socket://127.0.0.1:8101" and plugin.settings.avoid_distance == 0.4
