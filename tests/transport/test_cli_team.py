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
from erni.transport.endpoint import STREAM_BUFFER
from tests.transport.helpers import KEY, agent_config, free_port, identity

ROOT = Path(__file__).resolve().parents[2]

@pytest.fixture(scope="module")
def team(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("team")
    disc = free_port()
    env = {**os.environ, "ERNI_IDENTITY": identity("cli", "cli"), "ERNI_TEAM_KEY": KEY, "PYTHONUNBUFFERED": "1"}
    procs, ports = [], {}
    for name, echo in (("control", None), ("robot1", 0.2)):
        ports[name] = free_port()
        path = agent_config(tmp / f"{name}.toml", name, listen=f"127.0.0.1:{ports[name]}", discovery_port=disc,
                            echo=echo, task_ttl=2.0)
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
    assert out.returncode == 1 and out.stdout == ""
    assert out.stderr == "erni task: no agent ghost in the team: control knows robot1 (`erni peers` lists them)\n"


@pytest.mark.parametrize("command", [["peers"], ["task", "robot1", "BotMotion", "stop", "--wait"], ["watch"]])
def test_an_identity_of_another_authority_is_named_as_such_at_once(team, tmp_path, command):
    """An earlier run's keys: the control node answers the client's handshake with why it does not
    trust its certificate, and the client says so on one line instead of "no acknowledgement".

    "At once" is what the line itself shows, not a time: without the refusal the commands end
    otherwise, `task` with "no acknowledgement" after 6 s, `peers` with "no answer" after 5 s,
    and `watch` never (held by `cli`'s 30 s timeout)."""
    from erni.transport.identity import Authority

    earlier = Authority.create(tmp_path / "earlier", team="an earlier run")
    cli_pem = earlier.issue("cli", "cli", tmp_path / "cli.pem")
    env = {**team["env"], "ERNI_IDENTITY": str(cli_pem)}
    out = cli(env, command[0], "--via", team["via"], *command[1:])
    assert out.returncode == 1, out
    (line,) = out.stderr.splitlines()
    assert line.startswith(f"erni {command[0]}: control at {team['via']} refused this agent's certificate: "
                           "certificate not signed by this team's authority; control trusts the authority "
                           "'erni tests authority' (fingerprint "), line
    assert line.endswith("(an identity of another team or an earlier run? ERNI_IDENTITY or --identity must name "
                         "one issued by this team's authority, e.g. RUN/keys/cli.pem of this `erni sim`)"), line


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


@pytest.mark.parametrize("command", [["watch"], ["record", "{tmp}/out.jsonl"]])
def test_a_watch_of_an_address_where_nothing_answers_says_so(team, tmp_path, command):
    """Not silence: the first watch request goes unacknowledged and the command says so within seconds,
    goes on asking until --seconds ends, and a watch that no one ever answered exits 1."""
    command = [part.format(tmp=tmp_path) for part in command]
    out = subprocess.run([sys.executable, "-m", "erni", *command, "--via", f"127.0.0.1:{free_port()}",
                          "--seconds", "9"], capture_output=True, text=True, timeout=60, cwd=ROOT, env=team["env"])
    said = [ln for ln in out.stderr.splitlines() if "nothing answers at 127.0.0.1:" in ln]
    assert len(said) == 1 and said[0].startswith(f"erni {command[0]}: "), out.stderr
    assert "Traceback" not in out.stderr and out.stdout == ""
    if command[0] == "watch":
        assert out.returncode == 1 and out.stderr.splitlines()[-1].startswith("erni watch: nothing answered at")


def test_peers_table(team):
    out = cli(team["env"], "peers", "--via", team["via"])
    assert out.returncode == 0
    assert "robot1" in out.stdout and " up " in out.stdout
    assert "down after" in out.stdout.splitlines()[1] and "beacons" in out.stdout.splitlines()[1]
    row = next(line for line in out.stdout.splitlines() if line.startswith("robot1"))
    assert " 4.0s " in row  # peer_timeout: loopback loses no beacon, so the limit is not stretched
    rows = [json.loads(line) for line in cli(team["env"], "peers", "--via", team["via"], "--json").stdout.splitlines()]
    robot1 = next(r for r in rows if r["name"] == "robot1")
    assert robot1["down_after"] == 4.0 and robot1["beacons"] in (None, 1.0)


def udp_receive_buffer(pid: int) -> int:
    """The receive buffer of process `pid`'s one UDP socket, as the kernel reports it (`ss`)."""
    import re

    out = subprocess.run(["ss", "-uamp"], capture_output=True, text=True, check=True).stdout
    lines = out.splitlines()
    mine = [lines[i + 1] for i, ln in enumerate(lines[:-1]) if f"pid={pid}," in ln]
    assert len(mine) == 1, out
    return int(re.search(r"rb(\d+)", mine[0]).group(1))


def test_watch_streams_task_results(team):
    watch = subprocess.Popen([sys.executable, "-m", "erni", "watch", "--via", team["via"], "--json",
                              "--seconds", "8"], cwd=ROOT, env=team["env"], stdout=subprocess.PIPE,
                             text=True)
    try:
        first = json.loads(watch.stdout.readline())  # the current state arrives first
        assert first["agent"] == "control"
        # room for seconds of a team's stream: a watcher held back half a second loses nothing
        rmem_max = int(Path("/proc/sys/net/core/rmem_max").read_text())
        assert udp_receive_buffer(watch.pid) >= min(STREAM_BUFFER, rmem_max)
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


@pytest.mark.parametrize("params, message", [
    (["x=NaN", "y=1"], "erni task: goto: x: expected a finite number, got nan"),
    (["x=Infinity", "y=1"], "erni task: goto: x: expected a finite number, got inf"),
    (["x=true", "y=1"], "erni task: goto: x: expected a number, got True (a boolean)"),
    (["x=1", "y=" + "9" * 100_000], "erni task: goto: y: Input should be a finite number"),
    (["x=" + "a" * 100_000, "y=1"], "erni task: goto: x: Input should be a valid number"),
    (["x=" + "[" * 100_000, "y=1"], "erni task: parameter 'x': JSON nested deeper than 64 levels"),
    (["x=" + "[" * 1000 + "]" * 1000, "y=1"], "erni task: parameter 'x': JSON nested deeper than 64 levels"),
])
def test_bad_parameters_are_one_short_line_before_anything_is_sent(team, params, message):
    out = cli(team["env"], "task", "--via", team["via"], "robot1", "BotMotion", "goto", *params)
    assert out.returncode == 2
    (line,) = out.stderr.strip().splitlines()
    assert line.startswith(message) and len(line) < 300, line


@pytest.mark.parametrize("option", [["--timeout", "nan"], ["--timeout", "-1"], ["--link-deadline", "inf"]])
def test_bad_waiting_times_are_refused(team, option):
    out = cli(team["env"], "task", "--via", team["via"], "robot1", "BotMotion", "stop", "--wait", *option)
    assert out.returncode == 2
    (line,) = out.stderr.strip().splitlines()
    assert f"{option[0]}: expected a finite number of seconds > 0" in line


def test_check_refuses_absurd_timing_with_one_line(tmp_path):
    for setting, value, field in (("beacon_period", "1e-300", "beacon_period"),
                                  ("peer_timeout", "nan", "peer_timeout"),
                                  ("link_deadline", "inf", "link_deadline")):
        path = agent_config(tmp_path / "a.toml", "robot1", echo=None, **{setting: float(value)})
        out = cli(os.environ, "agent", str(path), "--check")
        assert out.returncode == 2, out.stdout
        (line,) = out.stderr.strip().splitlines()
        assert field in line and "Traceback" not in out.stderr


@pytest.fixture
def mortal_team(tmp_path):
    """A control node (link deadline 1.5 s) and a robot whose tasks take a minute; the test kills them."""
    env = {**os.environ, "ERNI_IDENTITY": identity("cli", "cli"), "ERNI_TEAM_KEY": KEY, "PYTHONUNBUFFERED": "1"}
    disc = free_port()
    procs, ports = {}, {}
    for name, echo in (("control", None), ("robot1", 60.0)):
        ports[name] = free_port()
        path = agent_config(tmp_path / f"{name}.toml", name, listen=f"127.0.0.1:{ports[name]}",
                            discovery_port=disc, echo=echo, link_deadline=1.5, peer_timeout=1.0)
        procs[name] = subprocess.Popen([sys.executable, "-m", "erni", "agent", str(path)], cwd=ROOT, env=env,
                                       stderr=subprocess.DEVNULL)
    via = f"127.0.0.1:{ports['control']}"

    def up() -> bool:
        out = cli(env, "peers", "--via", via, "--json")
        return out.returncode == 0 and any(json.loads(ln)["up"] for ln in out.stdout.splitlines())

    wait_until(up, timeout=15, interval=0.3)
    yield env, via, procs
    for p in procs.values():
        p.kill()
        p.wait(5)


def _wait_task(env, via: str, *extra: str) -> subprocess.Popen:
    proc = subprocess.Popen([sys.executable, "-m", "erni", "task", "--via", via, "robot1", "BotMotion", "forward",
                             "distance=1", "--wait", *extra], cwd=ROOT, env=env, stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True)
    for _ in range(5):
        if "running" in proc.stdout.readline():  # the robot took it
            return proc
    raise AssertionError("the task never ran")


def test_wait_ends_with_link_lost_when_the_robot_dies(mortal_team):
    env, via, procs = mortal_team
    waiting = _wait_task(env, via)
    procs["robot1"].kill()
    out, err = waiting.communicate(timeout=15)
    assert waiting.returncode == 1
    assert "failed" in out and "link lost: robot1 not heard for" in out


def test_wait_ends_with_link_lost_when_the_agent_it_goes_through_dies(mortal_team):
    env, via, procs = mortal_team
    waiting = _wait_task(env, via, "--link-deadline", "2")
    procs["control"].kill()
    out, err = waiting.communicate(timeout=15)
    assert waiting.returncode == 1
    assert f"erni task: link lost: no answer from {via}" in err


def test_no_warnings_when_a_command_line_client_leaves(caplog):
    """`erni task` without --wait exits once its task runs; the rest of the task's results find its
    port closed. They are dropped quietly, not retried with a burst of `Connection refused`."""
    import logging

    from tests.transport.helpers import make_agent, settled

    disc, port = free_port(), free_port()
    control = make_agent("control", disc, echo=False, listen=f"127.0.0.1:{port}")
    robot = make_agent("robot1", disc, start=False)
    robot.add_plugin("echo", settings={"verbs": ["NetWatch"], "delay": 0.5}, name="slow")
    robot.start()
    env = {**os.environ, "ERNI_IDENTITY": identity("cli", "cli")}
    try:
        wait_until(lambda: any(p.name == "robot1" and p.up for p in control.blackboard.query(
            lambda o: type(o).__name__ == "Peer")), timeout=10)
        with caplog.at_level(logging.DEBUG, logger="erni"):
            for _ in range(3):
                out = cli(env, "task", "--via", f"127.0.0.1:{port}", "robot1", "NetWatch", "neighbor_list")
                assert out.returncode == 0, out.stderr
            # the tasks end 0.5 s after they ran, and their results find the clients gone: dropped
            # quietly, where retries would go on for seconds with warnings
            endpoint = control.plugin("transport").endpoint
            wait_until(lambda: endpoint.counters.get("dropped.client_gone", 0) >= 3, timeout=30)
            settled(control)
    finally:
        robot.stop()
        control.stop()
    warnings = [r.getMessage() for r in caplog.records if r.levelno >= logging.WARNING and r.name.startswith("erni.control")]
    assert warnings == []
