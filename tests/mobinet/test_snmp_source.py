"""SnmpSource against the simulated agent over real UDP, and against misbehaving agents."""

from __future__ import annotations

import asyncio
import time

import pytest

from erni.blackboard import Position
from erni.plugins.mobinet.resource import PARTS, NetworkSource, SourceError
from erni.plugins.mobinet.snmp import SnmpSource, articulation_points
from erni.sim.manet import METRIC_UNIT


def run(coro):
    return asyncio.run(coro)


async def _read(address, parts=PARTS, **kw):
    src = SnmpSource(*address, **kw)
    try:
        return await src.read(frozenset(parts))
    finally:
        await src.aclose()


def test_snmp_source_is_a_network_source():
    assert isinstance(SnmpSource("127.0.0.1", 1161), NetworkSource)


def test_read_matches_the_simulators_ground_truth(served, net):
    view = run(_read(served["robot3"]))
    truth = net.truth()
    assert (view.node, view.address) == ("robot3", "10.0.0.3")
    assert {n.name for n in view.neighbors} == {"robot2", "robot4"}
    assert all(n.quality == pytest.approx(0.8) and n.symmetric for n in view.neighbors)
    assert {frozenset((l.a, l.b)) for l in view.links} == set(truth.links)
    assert set(articulation_points(view.links)) == truth.articulation_points
    expected = truth.routes("robot3")
    assert {r.destination: (r.next_hop, r.hops, r.cost) for r in view.routes} == {
        d: (e.next_hop, e.hops, e.cost / METRIC_UNIT) for d, e in expected.items()}
    assert view.positions["robot5"] == Position(x=240.0, y=0.0, heading=0.0)


def test_large_tables_take_several_bulk_requests():
    from erni.sim.manet import ManetNetwork, RadioModel
    from erni.sim.snmp_agent import ManetSnmpAgent
    net = ManetNetwork(RadioModel(100.0, 50.0))
    for i in range(30):   # a dense 30-node cluster: 435 links
        net.add_node(f"n{i}", (i % 6) * 8.0, (i // 6) * 8.0)
    with ManetSnmpAgent(net) as agent:
        address = agent.serve("n0")

        async def go():
            src = SnmpSource(*address, max_repetitions=25)
            try:
                first = await src.read(frozenset({"topology", "routes"}))
                requests = src.requests
                return first, requests
            finally:
                await src.aclose()
        view, requests = run(go())
    assert len(view.links) == 435
    assert len(view.routes) == 29
    assert requests > 3


def test_write_position_reaches_every_node(served, net):
    async def go():
        src = SnmpSource(*served["robot1"])
        try:
            await src.write_position(Position(x=-3.25, y=7.5, heading=270.0))
        finally:
            await src.aclose()
    run(go())
    known = net.view("robot5").positions["robot1"]
    assert (known.x, known.y, known.heading) == (-3.25, 7.5, -90.0)


def test_silent_agent_times_out_with_a_clear_message(bad_agent):
    agent = bad_agent("silent")
    t0 = time.monotonic()
    with pytest.raises(SourceError, match=r"SNMP GET.*to 127\.0\.0\.1:\d+: .*timeout.*0\.2 s"):
        run(_read(agent.address, timeout=0.2))
    assert time.monotonic() - t0 < 3.0
    assert agent.received >= 1


def test_garbage_answers_are_a_timeout_not_a_crash(bad_agent):
    agent = bad_agent("garbage")
    with pytest.raises(SourceError, match="timeout"):
        run(_read(agent.address, {"neighbors"}, timeout=0.2))
    assert agent.received >= 1


def test_wrong_types_are_named(bad_agent):
    agent = bad_agent("wrongtype")
    with pytest.raises(SourceError, match=r"erniNodeName \(1\.3\.6\.1\.4\.1\.32473\.1\.1\.1\.0\): "
                                          r"expected OCTET STRING, got Integer .7."):
        run(_read(agent.address, {"positions"}, timeout=0.5))


def test_an_agent_that_never_advances_is_caught(bad_agent):
    agent = bad_agent("loop")
    with pytest.raises(SourceError, match="OID not increasing at erniNodesName"):
        run(_read(agent.address, {"positions"}, timeout=0.5))
    assert agent.received < 10


def test_unknown_host_is_a_source_error():
    with pytest.raises(SourceError, match="cannot resolve"):
        run(_read(("no-such-host.invalid", 1161), timeout=0.2))


def test_unchanged_network_is_read_with_one_get_and_changes_are_walked(served, net):
    async def go():
        src = SnmpSource(*served["robot3"], cache_seconds=60.0)
        try:
            first = await src.read(PARTS)
            r0 = src.requests
            again = await src.read(PARTS)
            steady = src.requests - r0
            net.move("robot5", 150.0, 40.0)
            r1 = src.requests
            moved = await src.read(PARTS)
            after_move = src.requests - r1
            return first, again, steady, moved, after_move
        finally:
            await src.aclose()
    first, again, steady, moved, after_move = run(go())
    assert steady == 1                       # only the identity and change counters
    assert again.links == first.links and again.routes == first.routes
    assert after_move > 1
    assert "robot5" in {n.name for n in moved.neighbors}
    assert set(articulation_points(moved.links)) == {"robot2", "robot3"}


def test_cache_can_be_turned_off(served):
    async def go():
        src = SnmpSource(*served["robot3"], cache_seconds=0.0)
        try:
            await src.read(PARTS)
            r0 = src.requests
            await src.read(PARTS)
            return src.requests - r0
        finally:
            await src.aclose()
    assert run(go()) > 1


def test_topology_of_routers_missing_from_the_node_table_is_read_by_address(served, net):
    class NoNodeTable(SnmpSource):
        def _decode_nodes(self, view, cols, positions):
            super()._decode_nodes(view, cols, positions)
            return {}          # as if the agent listed no routers: fall back to address columns
    async def go():
        src = NoNodeTable(*served["robot2"])
        try:
            return await src.read(frozenset({"topology"}))
        finally:
            await src.aclose()
    view = run(go())
    assert {frozenset((l.a, l.b)) for l in view.links} == set(net.truth().links)
