"""A team across hosts, without starting one: where each robot's agent runs, the radio feed's
handshake and lines over a real socket, an agent host's bundle and its refusals, the configs."""

from __future__ import annotations

import json
import socket
import threading
import time
import tomllib
from pathlib import Path

import pytest
from hypothesis import given
from hypothesis import strategies as st

from erni.blackboard.errors import UsageError
from erni.blackboard.testing import wait_until
from erni.sim import agent_hosts
from erni.sim.agent_hosts import (
    JOIN_FILE,
    MAX_LINE,
    AgentHost,
    Placement,
    RadioFeed,
    _mac,
    broadcast_of,
    bundle_dir,
    write_join_file,
)
from erni.sim.scenario import Scenario
from erni.sim.team import Team, TeamError
from erni.sim.team_configs import AgentConfigs
from erni.sim.world import World

WORLD = "127.0.0.1"


def placement(names: list[str], hosts: list[str]) -> Placement:
    return Placement.plan(names, WORLD, hosts)


@given(st.integers(2, 240), st.integers(1, 6))
def test_every_robot_runs_on_one_host_in_even_contiguous_shares(n, others):
    names = [f"robot{i + 1}" for i in range(n)]
    hosts = [f"127.0.0.{k + 2}" for k in range(others)]
    if n < 1 + others:
        with pytest.raises(UsageError, match="at least one robot per host"):
            placement(names, hosts)
        return
    p = placement(names, hosts)
    shares = [p.names_of(k) for k in range(1, 2 + others)]
    assert sum(shares, []) == names  # each once, in order: host 1 (this one) first
    assert max(map(len, shares)) - min(map(len, shares)) <= 1
    for k, share in enumerate(shares, start=1):
        for name in share:
            assert p.remote(name) is (k != 1)
            assert p.address(name) == (WORLD if k == 1 else hosts[k - 2])
    assert p.address("control") == WORLD and not p.remote("control")


@given(st.integers(3, 200), st.integers(1, 4), st.data())
def test_a_world_host_given_fewer_agents_runs_that_many_and_the_rest_share_evenly(n, others, data):
    names = [f"robot{i + 1}" for i in range(n)]
    hosts = [f"127.0.0.{k + 2}" for k in range(others)]
    if n < 1 + others:
        return
    here = data.draw(st.integers(0, n - others))
    p = Placement.plan(names, WORLD, hosts, here)
    assert p.names_of(1) == names[:here]
    rest = [p.names_of(k) for k in range(2, 2 + others)]
    assert sum(rest, []) == names[here:] and min(map(len, rest)) >= 1 and max(map(len, rest)) - min(map(len, rest)) <= 1


@pytest.mark.parametrize("here", [-1, 4])
def test_a_world_share_that_leaves_an_agent_host_empty_is_refused(here):
    with pytest.raises(UsageError, match=r"--agents-here .*: expected 0 to 3 \(of 4 robots"):
        Placement.plan(["robot1", "robot2", "robot3", "robot4"], WORLD, ["127.0.0.2"], here)


def test_the_loopback_broadcast_is_the_one_beacons_reach():
    assert broadcast_of("127.0.0.1") == "127.255.255.255"
    assert placement(["robot1", "robot2"], ["127.0.0.2"]).broadcast == "127.255.255.255"


@pytest.mark.parametrize("world,hosts,message", [
    ("192.0.2.77", ["127.0.0.2"], "no interface of this host has that address"),
    ("robot-base", ["127.0.0.2"], "expected an IPv4 address of this host"),
    (WORLD, ["hostB"], "expected the IPv4 address of an agent host"),
    (WORLD, [WORLD], "not this one"),
    (WORLD, ["127.0.0.2", "127.0.0.2"], "every host once"),
])
def test_a_placement_that_cannot_be_is_one_line(world, hosts, message):
    with pytest.raises(UsageError, match=message) as err:
        Placement.plan(["robot1", "robot2", "robot3"], world, hosts)
    assert "\n" not in str(err.value)


@pytest.mark.parametrize("kw,message", [
    (dict(agent_hosts=["127.0.0.2"]), "with --listen ADDR"),
    (dict(listen=WORLD), "--listen: for a team across hosts"),
    (dict(agents_here=1), "--agents-here: for a team across hosts"),
    (dict(listen=WORLD, agent_hosts=["127.0.0.2"], netns=True), "loopback tier only"),
])
def test_the_team_refuses_what_cannot_be_placed(tmp_path, kw, message):
    with pytest.raises(TeamError, match=message):
        Team(Scenario().with_robots(2), run_dir=tmp_path / "run", headless=True, **kw)


# -- the radio feed, over a real socket -------------------------------------------------------------

class Reach:
    """What the world host's radio model says each agent hears now."""

    def __init__(self) -> None:
        self.now: dict[str, list[str] | None] = {"robot3": ["robot1"], "robot4": None}

    def __call__(self, name: str) -> list[str] | None:
        return self.now.get(name)


@pytest.fixture
def feed():
    f = RadioFeed(placement(["robot1", "robot2", "robot3", "robot4"], ["127.0.0.2"]), Reach())
    yield f
    f.close()


def answer(feed: RadioFeed, host: int, secret: str) -> tuple[socket.socket, object]:
    """Connect to the feed as agent host `host` proving `secret`; return the socket and its reader."""
    sock = socket.create_connection(feed.address, timeout=5)
    reader = sock.makefile("rb")
    nonce = json.loads(reader.readline())["nonce"]
    sock.sendall((json.dumps({"host": host, "mac": _mac(secret, nonce, host), "nonce": "c0ffee"}) + "\n").encode())
    assert json.loads(reader.readline()) == {"proof": _mac(secret, "c0ffee", "world")}  # the world proves itself too
    return sock, reader


def lines(reader, count: int) -> list[dict]:
    return [json.loads(reader.readline()) for _ in range(count)]


def test_a_joining_host_hears_its_agents_reach_now_then_each_change(feed):
    assert feed.placement.names_of(2) == ["robot3", "robot4"]
    sock, reader = answer(feed, 2, feed.secrets[2])
    with sock:
        first = lines(reader, 2)
        assert {line["agent"]: line["hears"] for line in first} == {"robot3": ["robot1"], "robot4": None}
        wait_until(lambda: feed.joined() == {2}, timeout=5, message="the host did not join")
        feed.tell("robot1", ["robot2"])  # an agent of this host: not this host's to hear
        feed.tell("robot4", ["robot2"])
        assert lines(reader, 1) == [{"agent": "robot4", "hears": ["robot2"]}]
        feed.fail("robot3")
        assert lines(reader, 1) == [{"agent": "robot3", "fail": True}]
        feed.close()
        assert reader.readline() == b""  # the run ended: the host stops its agents


@pytest.mark.parametrize("how", ["wrong secret", "another host's number", "not json", "no answer"])
def test_a_host_that_cannot_prove_it_is_of_the_run_is_refused(feed, how):
    sock = socket.create_connection(feed.address, timeout=10)
    reader = sock.makefile("rb")
    nonce = json.loads(reader.readline())["nonce"]
    stranger = "ab" * 32
    t0 = time.monotonic()
    if how == "wrong secret":
        sock.sendall((json.dumps({"host": 2, "mac": _mac(stranger, nonce, 2)}) + "\n").encode())
    elif how == "another host's number":
        sock.sendall((json.dumps({"host": 3, "mac": _mac(feed.secrets[2], nonce, 3)}) + "\n").encode())
    elif how == "not json":
        sock.sendall(b"hello\n")
    with sock:
        rest = reader.read()  # the feed closes: no reach of any agent is ever sent
    assert b'"agent"' not in rest
    if how in ("wrong secret", "another host's number"):
        assert b"not an agent host of this run" in rest
    if how == "no answer":
        assert time.monotonic() - t0 >= 4.0  # the handshake's deadline, not at once and not forever
    assert feed.joined() == set()


# -- an agent host's bundle -------------------------------------------------------------------------

def bundle(tmp_path: Path, **join) -> Path:
    folder = tmp_path / "host-2"
    (folder / "agents").mkdir(parents=True)
    for name in ("robot3", "robot4"):
        (folder / "agents" / f"{name}.toml").write_text("")
    write_join_file(folder, **{"world": (WORLD, 1), "host": 2, "secret": "cd" * 32, "agents": ["robot3", "robot4"],
                               "log_level": "WARNING", **join})
    return folder


def test_a_bundle_names_the_world_host_and_its_agents(tmp_path):
    host = AgentHost(bundle(tmp_path))
    assert (host.world, host.host, host.names) == ((WORLD, 1), 2, ["robot3", "robot4"])
    assert oct((host.dir / JOIN_FILE).stat().st_mode & 0o777) == "0o600"  # it holds the secret


@pytest.mark.parametrize("damage,message", [
    (lambda b: (b / JOIN_FILE).unlink(), "expected the bundle"),
    (lambda b: (b / JOIN_FILE).write_text("{not json"), "JSONDecodeError"),
    (lambda b: (b / JOIN_FILE).write_text('{"world": ["127.0.0.1", 1], "host": 2}'), "KeyError"),
    (lambda b: (b / JOIN_FILE).write_text(
        '{"world": ["127.0.0.1", 1], "host": 2, "secret": "zz", "agents": []}'), "ValueError"),
    (lambda b: (b / "agents" / "robot4.toml").unlink(), r"agent config\(s\) missing"),
    (lambda b: (b / JOIN_FILE).write_text(
        '{"world": ["127.0.0.1", 1], "host": 2, "secret": "cd", "agents": []}'), "names no agent"),
])
def test_a_damaged_bundle_is_one_line(tmp_path, damage, message):
    folder = bundle(tmp_path)
    damage(folder)
    with pytest.raises(UsageError, match=message) as err:
        AgentHost(folder)
    assert "\n" not in str(err.value)


def test_an_agent_host_whose_world_does_not_answer_says_so(tmp_path):
    with socket.socket() as s:
        s.bind((WORLD, 0))
        port = s.getsockname()[1]  # bound, never listening: refused
        host = AgentHost(bundle(tmp_path, world=(WORLD, port)))
        with pytest.raises(UsageError, match="does not answer"):
            host.connect(timeout=0.5)


def test_an_agent_host_of_the_run_joins_and_relays_until_the_run_ends(feed, tmp_path):
    folder = bundle(tmp_path, world=feed.address, secret=feed.secrets[2])
    host = AgentHost(folder)
    host.connect(timeout=5)
    heard: list[tuple[str, object]] = []
    original = agent_hosts.tell_pipe
    agent_hosts.tell_pipe = lambda agent, names: heard.append((agent.name, names))  # no agent processes here
    try:
        why: list[str] = []
        relay = threading.Thread(target=lambda: why.append(host.relay()))
        relay.start()
        wait_until(lambda: len(heard) >= 2, timeout=5, message="no reach relayed")
        feed.tell("robot3", ["robot1", "robot4"])
        wait_until(lambda: ("robot3", ["robot1", "robot4"]) in heard, timeout=5, message="a change was not relayed")
        feed.close()
        relay.join(5)
    finally:
        agent_hosts.tell_pipe = original
    assert why == ["the world host ended the run"]
    assert sorted(heard[:2], key=lambda h: h[0]) == [("robot3", ["robot1"]), ("robot4", None)]


def test_a_bundle_for_another_run_is_refused_by_the_world(feed, tmp_path):
    host = AgentHost(bundle(tmp_path, world=feed.address, secret="ef" * 32))
    with pytest.raises(UsageError, match="refused this host: not an agent host of this run"):
        host.connect(timeout=5)
    assert feed.joined() == set()


@pytest.mark.parametrize("proof", ["a wrong proof", "no proof"])
def test_an_agent_host_takes_no_line_from_a_world_that_cannot_prove_it_is_its_run(tmp_path, proof):
    """Someone else at the world's address (or in the path to it) neither fails agents nor cuts their radio."""
    with socket.create_server((WORLD, 0)) as server:
        def impostor() -> None:
            conn, _ = server.accept()
            with conn:
                conn.sendall(b'{"nonce": "1234"}\n')
                conn.makefile("rb").readline()
                conn.sendall(b'{"proof": "' + b"00" * 32 + b'"}\n' if proof == "a wrong proof" else b'{"agent": "robot3"}\n')
                conn.sendall(b'{"agent": "robot3", "fail": true}\n')

        thread = threading.Thread(target=impostor)
        thread.start()
        host = AgentHost(bundle(tmp_path, world=server.getsockname()[:2]))
        with pytest.raises(UsageError, match="did not prove it is the world host|did not greet as `erni sim` does"):
            host.connect(timeout=5)
        thread.join(5)
    assert host._sock is None  # no feed: relay() has nothing to take lines from


def test_a_line_longer_than_the_feed_reads_is_refused_not_buffered(feed):
    sock = socket.create_connection(feed.address, timeout=10)
    with sock:
        sock.makefile("rb").readline()
        try:
            sock.sendall(b"x" * (MAX_LINE + 10))
        except OSError:
            pass
        assert sock.makefile("rb").read() == b""
    assert feed.joined() == set()


# -- the configs a placed team writes ---------------------------------------------------------------

def test_the_configs_of_an_agent_host_live_in_its_bundle_with_paths_inside_it(tmp_path):
    scenario = Scenario().with_robots(3)
    names = scenario.robot_names()
    run = tmp_path / "run"
    for sub in ("agents", "logs", "journal", "keys"):
        (run / sub).mkdir(parents=True)
    configs = AgentConfigs(scenario, run, names, World(), keys_dir=run / "keys",
                           robot_url=lambda i: f"socket://{WORLD}:{9000 + i}", discovery_port=47001, transport={},
                           mission=False, ui=False, mobinet="snmp", mission_extra={}, gui_listen=None, gui_token="t",
                           mesh=None, placement=placement(names, ["127.0.0.2"]))
    configs.write({n: 16100 + i for i, n in enumerate(names)}, {n: "w" for n in names}, 47100, 0)
    assert configs.placement is not None and configs.placement.names_of(2) == ["robot3"]
    bundle = bundle_dir(run, 2)
    assert not (run / "agents" / "robot3.toml").exists()
    there = tomllib.loads((bundle / "agents" / "robot3.toml").read_text())
    plugins = {p["class"]: p["settings"] for p in there["plugin"]}
    assert plugins["transport"]["listen"] == "127.0.0.2:0"
    assert plugins["transport"]["identity"] == "keys/robot3.pem"  # relative: the bundle is copied to its host
    assert plugins["transport"]["revocations"] == "keys/revoked.crl"
    assert plugins["transport"]["beacon_to"] == ["127.255.255.255"]
    assert plugins["mobinet"]["host"] == WORLD  # its SNMP node is the world host's
    assert plugins["motion"]["url"] == f"socket://{WORLD}:9002"
    assert there["agent"]["journal"] == "journal/robot3.sqlite"
    assert configs.agents["robot3"].log == bundle / "logs" / "robot3.log"
    here = {p["class"]: p["settings"] for p in tomllib.loads((run / "agents" / "robot1.toml").read_text())["plugin"]}
    assert here["transport"]["listen"] == f"{WORLD}:0" and Path(here["transport"]["identity"]).is_absolute()
    control = {p["class"]: p["settings"] for p in tomllib.loads((run / "agents" / "control.toml").read_text())["plugin"]}
    assert control["transport"]["listen"] == f"{WORLD}:47100"  # where the agent hosts' agents reach it
    for folder in (run / "hosts", bundle, *(bundle / d for d in ("agents", "logs", "journal", "keys"))):
        assert folder.stat().st_mode & 0o777 == 0o700, folder
