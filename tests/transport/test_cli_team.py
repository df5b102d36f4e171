"""`erni task`, `erni peers` and `erni watch` against agents started with `erni agent`."""

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

CONFIG = """
[agent]
name = "{name}"
[[plugin]]
class = "transport"
[plugin.settings]
listen = "127.0.0.1:{port}"
discovery_port = {disc}
beacon_period = 0.2
task_ttl = 2.0
{extra}
"""

ECHO = """
[[plugin]]
class = "echo"
name = "motion"
[plugin.settings]
verbs = ["BotMotion"]
delay = 0.2
"""


@pytest.fixture(scope="module")
def team(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("team")
    disc = free_port()
    env = {**os.environ, "ERNI_TEAM_KEY": KEY, "PYTHONUNBUFFERED": "1"}
    procs, ports = [], {}
    for name, extra in (("control", ""), ("robot1", ECHO)):
        ports[name] = free_port()
        path = tmp / f"{name}.toml"
        path.write_text(CONFIG.format(name=name, port=ports[name], disc=disc, extra=extra))
        procs.append(subprocess.Popen([sys.executable, "-m", "erni", "agent", str(path)], cwd=ROOT,
                                      env=env, stderr=subprocess.PIPE, text=True))
    logs = []

    def peers_up() -> bool:
        out = cli(env, "peers", "--via", f"127.0.0.1:{ports['control']}", "--json")
        return out.returncode == 0 and any(json.loads(ln)["up"] for ln in out.stdout.splitlines())

    try:
        wait_until(peers_up, timeout=15, interval=0.3)
        yield {"env": env, "via": f"127.0.0.1:{ports['control']}", "disc": str(disc)}
    finally:
        for p in procs:
            p.send_signal(signal.SIGINT)
        for p in procs:
            logs.append(p.stderr.read())
            assert p.wait(timeout=10) == 0
        assert all("Traceback" not in log for log in logs), logs


def cli(env, *args: str):
    return subprocess.run([sys.executable, "-m", "erni", *args], capture_output=True, text=True,
                          timeout=30, cwd=ROOT, env=env)


def test_task_through_the_control_node_waits_for_success(team):
    out = cli(team["env"], "task", "--via", team["via"], "robot1", "BotMotion", "forward", "distance=2",
              "--wait")
    assert out.returncode == 0, out.stderr
    lines = out.stdout.strip().splitlines()
    assert "running" in lines[-2] or "pending" in lines[0]
    assert "succeeded" in lines[-1] and "distance" in lines[-1]


def test_task_found_by_beacons_with_json_output(team):
    out = cli(team["env"], "task", "--discovery-port", team["disc"], "robot1", "BotMotion", "goto",
              "x=1", "y=-2.5", "--wait", "--json")
    assert out.returncode == 0, out.stderr
    last = json.loads(out.stdout.strip().splitlines()[-1])
    assert last["state"] == "succeeded" and last["values"]["params"]["y"] == -2.5


def test_failed_task_exits_1(team):
    out = cli(team["env"], "task", "--via", team["via"], "ghost", "BotMotion", "stop", "--wait")
    assert out.returncode == 1
    assert "failed" in out.stdout and "unknown agent ghost" in out.stdout


def test_bad_arguments_exit_2(team):
    out = cli(team["env"], "task", "--via", team["via"], "robot1", "BotMotion", "goto", "x=1")
    assert out.returncode == 2 and out.stderr.strip() == "erni task: goto: missing 'y'"
    out = cli(team["env"], "task", "--via", "nohost", "robot1", "BotMotion", "stop")
    assert out.returncode == 2 and "expected HOST:PORT" in out.stderr
    out = cli(team["env"], "task", "--via", team["via"], "robot1", "BotMotion", "stop", "speed")
    assert out.returncode == 2 and "expected KEY=VALUE" in out.stderr


def test_unreachable_via_exits_1(team):
    out = cli(team["env"], "task", "--via", f"127.0.0.1:{free_port()}", "robot1", "BotMotion", "stop")
    assert out.returncode == 1 and "could not reach the agent" in out.stderr


def test_peers_table(team):
    out = cli(team["env"], "peers", "--via", team["via"])
    assert out.returncode == 0
    assert "robot1" in out.stdout and " up " in out.stdout


def test_watch_streams_task_results(team):
    watch = subprocess.Popen([sys.executable, "-m", "erni", "watch", "--via", team["via"], "--json",
                              "--seconds", "8"], cwd=ROOT, env=team["env"], stdout=subprocess.PIPE,
                             text=True)
    try:
        first = json.loads(watch.stdout.readline())  # the current state arrives first
        assert first["agent"] == "control"
        out = cli(team["env"], "task", "--via", team["via"], "robot1", "BotMotion", "stop", "--wait")
        assert out.returncode == 0
        events = []
        while True:
            line = watch.stdout.readline()
            if not line:
                break
            events.append(json.loads(line))
            if any(e["type"] == "Task" and (e["data"].get("result") or {}).get("state") == "succeeded"
                   and e["data"]["preposition"] == "stop" for e in events):
                break
        assert any(e["type"] == "Task" and e["data"]["preposition"] == "stop" for e in events)
    finally:
        watch.terminate()
        watch.wait(timeout=5)
