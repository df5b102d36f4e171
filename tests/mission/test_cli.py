"""From a control node, `erni task` starts every RemoteBotMotion preposition and every Deploy strategy."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
from pathlib import Path

import pytest

from erni.blackboard.testing import wait_until
from tests.transport.helpers import KEY, free_port

ROOT = Path(__file__).resolve().parents[2]

TRANSPORT = """
[agent]
name = "{name}"
[[plugin]]
class = "transport"
[plugin.settings]
listen = "127.0.0.1:{port}"
discovery_port = {disc}
beacon_period = 0.2
role = "{role}"
"""

ROBOT = """
[[plugin]]
class = "motion"
name = "motion"
[plugin.settings]
url = "simrobot://?sip_period=0.05"
model = { base = "pioneer3", max_v = 1.5 }
avoid_distance = 0.0
[[plugin]]
class = "mission"
name = "mission"
[plugin.settings]
network_aware = false
audio = false
speed = 1.0
report_period = 1.0
relay_period = 0.5
"""


def cli(env, *args: str, timeout: float = 40):
    return subprocess.run([sys.executable, "-m", "erni", *args], capture_output=True, text=True,
                          timeout=timeout, cwd=ROOT, env=env, check=False)


@pytest.fixture(scope="module")
def team(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("mission-team")
    disc = free_port()
    env = {**os.environ, "ERNI_TEAM_KEY": KEY, "PYTHONUNBUFFERED": "1"}
    procs, ports = [], {}
    for name, role, extra in (("control", "control", ""), ("robot1", "robot", ROBOT)):
        ports[name] = free_port()
        path = tmp / f"{name}.toml"
        path.write_text(TRANSPORT.format(name=name, port=ports[name], disc=disc, role=role) + extra)
        procs.append(subprocess.Popen([sys.executable, "-m", "erni", "agent", str(path)], cwd=ROOT,
                                      env=env, stderr=subprocess.PIPE, text=True))
    via = f"127.0.0.1:{ports['control']}"

    def robot_up() -> bool:
        out = cli(env, "peers", "--via", via, "--json")
        return out.returncode == 0 and any(json.loads(ln)["name"] == "robot1" and json.loads(ln)["up"]
                                           for ln in out.stdout.splitlines())

    logs = []
    try:
        wait_until(robot_up, timeout=20, interval=0.3)
        yield {"env": env, "via": via}
    finally:
        for p in procs:
            p.send_signal(signal.SIGINT)
        for p in procs:
            logs.append(p.stderr.read())
            assert p.wait(timeout=10) == 0
        assert all("Traceback" not in log for log in logs), logs


def task(team, *words: str, timeout: float | None = None):
    extra = ["--timeout", str(timeout)] if timeout else []
    return cli(team["env"], "task", "--via", team["via"], "robot1", *words, "--wait", "--json", *extra)


def results(out) -> list[dict]:
    return [json.loads(line) for line in out.stdout.splitlines() if line.startswith("{")]


def test_every_remote_bot_motion_preposition(team):
    for words in (["goto", "x=0.8", "y=0.3", "speed=1.0"], ["forward", "distance=0.4", "speed=1.0"],
                  ["teleport", "x=1", "y=1", "heading=0"], ["randomwalk", "speed=0.5", "duration=1"],
                  ["cancel"]):
        out = task(team, "RemoteBotMotion", *words)
        assert out.returncode == 0, (words, out.stdout, out.stderr)
        updates = results(out)
        assert updates[-1]["state"] == "succeeded", updates
        assert len(updates) <= 8, updates  # significant changes only


def test_every_deploy_strategy_starts(team):
    out = task(team, "RemoteBotMotion", "teleport", "x=0", "y=0")
    assert out.returncode == 0, out.stderr
    out = task(team, "Deploy", "widep", "x=1.2", "y=0", "range=4.5", "tolerance=0.3", "period=0.5")
    assert out.returncode == 0, (out.stdout, out.stderr)
    last = results(out)[-1]
    assert last["state"] == "succeeded" and last["values"]["covered_by"] == "robot1"
    assert last["values"]["energy_j"] > 0 and last["values"]["distance_m"] > 0.5
    out = task(team, "Deploy", "spread", "distance=2", "duration=1")
    assert out.returncode == 0, (out.stdout, out.stderr)
    assert results(out)[-1]["values"]["energy_j"] >= 8.568 * 0.9  # one second, standing or moving
    # relay and patrol run until cancelled: they start, report, and are cancelled by the timeout
    out = task(team, "Deploy", "relay", "source=control", "destination=robot9", timeout=2.5)
    assert out.returncode == 1 and "cancelling" in out.stderr
    assert any(u["state"] == "running" and "waiting for the position" in u["message"] for u in results(out))
    out = task(team, "Deploy", "patrol", "xmin=0", "ymin=0", "xmax=2", "ymax=2", "heartbeat=0.5", timeout=2.5)
    assert out.returncode == 1
    assert any(u["state"] == "running" and u["message"] == "patrolling" for u in results(out))
