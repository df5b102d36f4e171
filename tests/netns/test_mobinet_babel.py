"""MobiNetControl with `source = "babel"` in a real agent, reading a babeld local interface over TCP.

The peer serves babeld 1.12.1's own header and dump (node b of vectors/README.md); the real
daemon is read the same way by the team tests of this tier.
"""

from __future__ import annotations

import socketserver
import threading
from collections.abc import Iterator

import pytest

from erni.blackboard import Agent, NetInfo, Pose, Task
from erni.blackboard.errors import ConfigError
from erni.blackboard.schemas import Peer
from erni.blackboard.testing import wait_until
from tests.netns.test_babel_source import dump_of


class _Handler(socketserver.StreamRequestHandler):
    def handle(self) -> None:
        lines = dump_of("b")
        split = lines.index("ok") + 1
        self.wfile.write(("\n".join(lines[:split]) + "\n").encode())
        for line in self.rfile:
            if line.strip() == b"dump":
                self.wfile.write(("\n".join(lines[split:]) + "\n").encode())


@pytest.fixture
def babeld() -> Iterator[str]:
    server = socketserver.ThreadingTCPServer(("127.0.0.1", 0), _Handler)
    server.daemon_threads = True
    thread = threading.Thread(target=server.serve_forever, name="fake-babeld")
    thread.start()
    try:
        yield f"127.0.0.1:{server.server_address[1]}"
    finally:
        server.shutdown()
        server.server_close()
        thread.join(5)


@pytest.fixture
def agent(babeld: str) -> Iterator[Agent]:
    agent = Agent("b", workers=2)
    agent.add_plugin("erni.plugins.mobinet:MobiNetControl", name="mobinet",
                     settings={"source": "babel", "babel": babeld, "watch": ["path_cost"], "watch_rate_hz": 20})
    agent.start()
    try:
        yield agent
    finally:
        agent.stop()


def watch(agent: Agent, preposition: str) -> Task:
    task = Task(verb="NetWatch", preposition=preposition, params={"rate_hz": 20}, source="test")
    with agent.transaction() as tx:
        tx.add(task)
    return task


def info(agent: Agent, uid: str, check=lambda i: True) -> NetInfo:
    def ok():
        found = agent.query(NetInfo, where=lambda i: i.uid == uid)
        return found[0] if found and found[0].stamp and "waiting" not in found[0].message and check(found[0]) else None
    return wait_until(ok, timeout=5.0)


def test_every_part_names_babeld_as_its_provenance_and_positions_are_missing(agent, babeld):
    where = f"babel {babeld}"
    topo = info(agent, f"netinfo:{watch(agent, 'network_topology').uid}", lambda i: i.links)
    assert topo.provenance["node"].startswith(f"{where} (babeld-1.12.1, my-id 48:de:c4:a5:d8:81:f4:2f)")
    assert topo.provenance["links"].startswith(f"{where} neighbour table")
    assert topo.articulation_points == ["b"] and not topo.degraded  # b holds a (vectors/README.md)
    quality = info(agent, f"netinfo:{watch(agent, 'link_quality').uid}", lambda i: i.neighbors)
    assert "256/sqrt(rxcost*txcost)" in quality.provenance["neighbors"]
    position = info(agent, f"netinfo:{watch(agent, 'node_position').uid}", lambda i: i.degraded)
    assert position.provenance["positions"].startswith("missing: babeld carries no positions")
    assert "no positions" in position.message


def test_addresses_are_named_by_the_team_directory_once_agents_are_heard(agent):
    task = watch(agent, "neighbor_list")
    first = info(agent, f"netinfo:{task.uid}", lambda i: i.neighbors)
    assert {n.name for n in first.neighbors} == {"10.231.0.1", "10.231.0.3", "10.231.0.4"}
    with agent.transaction() as tx:  # what the transport publishes when it hears their beacons
        for name, address in (("alpha", "10.231.0.1"), ("gamma", "10.231.0.3"), ("delta", "10.231.0.4")):
            tx.add(Peer(uid=f"peer:{name}", name=name, address=f"{address}:47123", up=True))
    named = info(agent, f"netinfo:{task.uid}", lambda i: {n.name for n in i.neighbors} == {"alpha", "gamma", "delta"})
    assert {n.name: n.address for n in named.neighbors}["gamma"] == "10.231.0.3"


def test_a_standing_watch_publishes_routes_without_a_task_and_no_pose_is_written(agent):
    standing = info(agent, "netinfo:b:path_cost", lambda i: i.routes)
    assert standing.task is None and standing.kind == "path_cost"
    assert {r.destination: r.next_hop for r in standing.routes} == {
        "10.231.0.1": "10.231.0.1", "10.231.0.3": "10.231.0.4", "10.231.0.4": "10.231.0.4"}
    with agent.transaction() as tx:
        tx.add(Pose(robot="b", x=1.0, y=2.0, theta=0.0))
    plugin = next(p for p in agent.plugins if p.name == "mobinet")
    wait_until(lambda: plugin.resource.stats["reads"] > 3, timeout=5)
    assert plugin.resource.stats["writes"] == 0


def test_a_fixed_position_is_published_as_this_nodes_pose_with_a_fresh_stamp(babeld):
    agent = Agent("base", workers=2)
    agent.add_plugin("erni.plugins.mobinet:MobiNetControl", name="mobinet",
                     settings={"source": "babel", "babel": babeld, "position": [-13.75, 0.0]})
    agent.start()
    try:
        pose = wait_until(lambda: next(iter(agent.query(Pose)), None))
        assert (pose.robot, pose.x, pose.y) == ("base", -13.75, 0.0)
        later = wait_until(lambda: (p := agent.query(Pose)[0]).stamp > pose.stamp + 0.5 and p, timeout=5)
        assert (later.x, later.y) == (-13.75, 0.0)
    finally:
        agent.stop()


@pytest.mark.parametrize("settings, expected", [
    ({"source": "babel", "babel": "::1"}, "expected HOST:PORT"),
    ({"source": "babel", "babel": "[::1]:99999"}, "outside 1..65535"),
    ({"source": "olsr"}, "source"),
    ({"watch": ["topology"]}, "unknown NetWatch preposition"),
])
def test_bad_settings_are_refused_with_one_line(settings, expected):
    agent = Agent("x", workers=1)
    with pytest.raises(ConfigError) as err:
        agent.add_plugin("erni.plugins.mobinet:MobiNetControl", name="mobinet", settings=settings)
    assert expected in str(err.value)
