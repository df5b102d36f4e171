"""SnmpSource against the simulated agent over real UDP, and against misbehaving agents."""

from __future__ import annotations

import asyncio
import time

import pytest

from erni.blackboard import Position
from erni.blackboard.testing import wait_until
from erni.plugins.mobinet.resource import PARTS, NetworkSource, SourceError
from erni.plugins.mobinet.snmp import SnmpDecoder, SnmpSource, articulation_points
from erni.sim.manet import METRIC_UNIT, ManetNetwork, RadioModel
from erni.sim.snmp_agent import ManetSnmpAgent
from tests.mobinet.conftest import SYS_NAME as SYS_NAME_OID
from tests.mobinet.conftest import WRITE


def run(coro):
    return asyncio.run(coro)


ANSWER_WAIT = 10.0  # how long a test's SnmpSource waits for an answer unless the test is about that


def source(host: str, port: int, **kw) -> SnmpSource:
    """An SnmpSource that waits up to ANSWER_WAIT s for each answer, unless given a timeout: the
    default 0.5 s is a robot's, and the simulated agents answering here run in the test's own
    process, which a loaded machine may leave waiting longer than that."""
    kw.setdefault("timeout", ANSWER_WAIT)
    return SnmpSource(host, port, **kw)


async def _read(address, parts=PARTS, modules=None, **kw):
    src = source(*address, modules=modules, **kw)
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
    assert view.missing == {}
    assert view.sources["routes"].endswith("OLSRv2-MIB olsrv2TibRoutingSetTable")
    assert view.sources["neighbors"].startswith(f"snmp 127.0.0.1:{served['robot3'][1]} NHDP-MIB")


def test_large_tables_take_several_bulk_requests():
    net = ManetNetwork(RadioModel(100.0, 50.0))
    for i in range(30):   # a dense 30-node cluster: 435 links
        net.add_node(f"n{i}", (i % 6) * 8.0, (i // 6) * 8.0)
    with ManetSnmpAgent(net) as agent:
        address = agent.serve("n0")

        async def go():
            src = source(*address, max_repetitions=25)
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
        src = source(*served["robot1"], write_community=WRITE)
        try:
            await src.write_position(Position(x=-3.25, y=7.5, heading=270.0))
        finally:
            await src.aclose()
    run(go())
    known = net.view("robot5").positions["robot1"]
    assert (known.x, known.y, known.heading) == (-3.25, 7.5, -90.0)


def test_writes_need_the_write_community(served, net):
    async def go(**kw):
        src = source(*served["robot1"], **kw)
        try:
            await src.write_position(Position(x=5.0, y=5.0))
        finally:
            await src.aclose()
    with pytest.raises(SourceError, match="no write community configured"):
        run(go())
    with pytest.raises(SourceError, match=r"SNMP SET to .*: agent answered noAccess at erniPosX"):
        run(go(write_community="public"))          # the read community, used to write
    with pytest.raises(SourceError, match="timeout"):
        run(go(write_community="guessed", timeout=0.2))   # unknown: dropped, never answered
    assert net.view("robot1").positions["robot1"].x == 0.0


def test_silent_agent_times_out_with_a_clear_message(bad_agent):
    agent = bad_agent("silent")
    t0 = time.monotonic()
    with pytest.raises(SourceError, match=r"SNMP GET.*to 127\.0\.0\.1:\d+: .*timeout.*0\.2 s, 0 retries"):
        run(_read(agent.address, timeout=0.2))
    assert time.monotonic() - t0 < 30.0  # a progress bound: it gave up (the tries are counted below)
    wait_until(lambda: agent.received >= 1, timeout=30)
    assert agent.received == 1  # one request, no retry, then the error


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


def test_an_agent_without_any_identity_is_refused(bad_agent):
    agent = bad_agent("nothing")
    with pytest.raises(SourceError, match="serves neither sysName"):
        run(_read(agent.address, {"routes"}, timeout=0.5))


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
        src = source(*served["robot3"], cache_seconds=60.0)
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


def test_a_position_report_rereads_positions_without_decoding_the_topology_again(served, net, monkeypatch):
    """Robots report positions twice a second: each report changes the state version, so the
    positions are walked again, but the topology (N^2 links in a team of N) is the same walk with the
    same names and is not decoded again; a topology change is."""
    decoded = []
    original = SnmpDecoder._decode_topology
    monkeypatch.setattr(SnmpDecoder, "_decode_topology",
                        lambda self, view, cols: (decoded.append(1), original(self, view, cols))[1])

    async def go():
        src = source(*served["robot3"], cache_seconds=60.0)
        try:
            first = await src.read(PARTS)
            net.set_position("robot5", 241.5, 2.0, 90.0)
            reported = await src.read(PARTS)
            net.move("robot5", 150.0, 40.0)
            moved = await src.read(PARTS)
            return first, reported, moved
        finally:
            await src.aclose()
    first, reported, moved = run(go())
    assert reported.positions["robot5"] == Position(x=241.5, y=2.0, heading=90.0)
    assert reported.links == first.links and reported.routes == first.routes
    symmetric = {frozenset((a, b)) for a, nbs in net.truth().symmetric.items() for b in nbs}
    assert {frozenset((l.a, l.b)) for l in moved.links} == symmetric != {frozenset((l.a, l.b)) for l in first.links}
    assert len(decoded) == 2                 # the first read and the move, not the report


def test_a_position_report_costs_a_read_without_positions_only_the_change_counters(served, net):
    """A network-aware robot watches topology and link quality twice a second while every robot of
    its team reports its position: each report moves the state version, not the topology version,
    so those reads stay one GET (the nodes' names follow the topology version); a read with
    positions walks them again, and a topology change is walked by both."""
    async def go():
        plain = source(*served["robot3"], cache_seconds=60.0)
        placed = source(*served["robot3"], cache_seconds=60.0)
        try:
            parts = frozenset({"topology", "neighbors"})
            first = await plain.read(parts)
            await placed.read(PARTS)
            net.set_position("robot5", 241.5, 2.0, 90.0)
            r0, p0 = plain.requests, placed.requests
            reported = await plain.read(parts)
            with_positions = await placed.read(PARTS)
            costs = (plain.requests - r0, placed.requests - p0)
            net.move("robot5", 150.0, 40.0)
            r1 = plain.requests
            moved = await plain.read(parts)
            return first, reported, with_positions, costs, plain.requests - r1, moved
        finally:
            await plain.aclose()
            await placed.aclose()
    first, reported, with_positions, (plain, placed), after_move, moved = run(go())
    assert plain == 1 and placed > 1
    assert reported.links == first.links and reported.neighbors == first.neighbors
    assert with_positions.positions["robot5"] == Position(x=241.5, y=2.0, heading=90.0)
    assert after_move > 1 and moved.links != first.links


def test_a_position_report_reads_the_identity_scalars_once(served, net, monkeypatch):
    """A read after robots moved (the state version, not the topology version) takes the node's
    identity from the change-counter check and the last read: one GET, then one walk of the node and
    position tables together; a topology change reads the identity again."""
    gets: list[int] = []
    original = SnmpSource.get

    async def counted(self, oids, optional=frozenset()):
        oids = list(oids)
        gets.append(len(oids))
        return await original(self, oids, optional)
    monkeypatch.setattr(SnmpSource, "get", counted)

    async def go():
        src = source(*served["robot3"], cache_seconds=60.0)
        try:
            first = await src.read(PARTS)
            g0, r0 = len(gets), src.requests
            net.set_position("robot5", 241.5, 2.0, 90.0)
            reported = await src.read(PARTS)
            g1, requests = len(gets), src.requests - r0
            net.move("robot5", 150.0, 40.0)
            moved = await src.read(PARTS)
            return first, reported, gets[g0:g1], gets[g1:], moved, requests
        finally:
            await src.aclose()
    first, reported, after_report, after_move, moved, requests = run(go())
    assert len(after_report) == 1 and len(after_move) == 2 and after_move[1] > after_move[0]
    assert requests == 2  # the check, then the node and position tables walked in one GETBULK
    assert (reported.node, reported.address, reported.sources["node"]) == (first.node, first.address,
                                                                         first.sources["node"])
    assert reported.positions["robot5"] == Position(x=241.5, y=2.0, heading=90.0)
    assert "robot5" in {n.name for n in moved.neighbors}


def test_cache_can_be_turned_off(served):
    async def go():
        src = source(*served["robot3"], cache_seconds=0.0)
        try:
            await src.read(PARTS)
            r0 = src.requests
            await src.read(PARTS)
            return src.requests - r0
        finally:
            await src.aclose()
    assert run(go()) > 1


def test_without_erni_names_the_standard_tables_still_give_the_topology_by_address(served, net):
    view = run(_read(served["robot2"], {"topology", "routes", "neighbors", "positions"},
                     modules=frozenset({"NHDP-MIB", "OLSRv2-MIB"})))
    truth = net.truth()
    address = {name: net.info(name).address for name in net.names()}
    assert view.node == "robot2" and view.address == "10.0.0.2"        # sysName, olsrv2OrigIpAddr
    assert view.sources["node"].endswith("SNMPv2-MIB sysName")
    assert {frozenset((l.a, l.b)) for l in view.links} == {
        frozenset(address[n] if n != "robot2" else "robot2" for n in key) for key in truth.links}
    assert {r.destination: r.next_hop for r in view.routes} == {
        "10.0.0.1": "10.0.0.1", "10.0.0.3": "10.0.0.3", "10.0.0.4": "10.0.0.3", "10.0.0.5": "10.0.0.3"}
    assert view.missing == {"positions": f"ERNI-MOBINET-MIB not served by 127.0.0.1:{served['robot2'][1]}"}
    # without erniLinkQuality, the first reading's quality is the HELLO ratio so far
    assert all(0.0 <= n.quality <= 1.0 for n in view.neighbors) and len(view.neighbors) == 2


def test_routes_from_ip_forward_match_the_olsrv2_routing_set(served, net):
    olsr = run(_read(served["robot1"], {"routes"}))
    cidr = run(_read(served["robot1"], {"routes"}, modules=frozenset({"IP-FORWARD-MIB", "ERNI-MOBINET-MIB"})))
    assert cidr.sources["routes"].split(" ", 2)[2].startswith("IP-FORWARD-MIB inetCidrRouteTable")
    assert {r.destination: r.next_hop for r in cidr.routes} == {r.destination: r.next_hop for r in olsr.routes}
    assert {r.destination: r.cost for r in cidr.routes} == {r.destination: r.cost * METRIC_UNIT
                                                           for r in olsr.routes}
    assert {r.destination: r.hops for r in cidr.routes} == {"robot2": 1, "robot3": 0, "robot4": 0, "robot5": 0}


def test_hello_counters_give_the_link_quality_between_readings():
    class Clock:
        t = 0.0

        def __call__(self) -> float:
            return self.t
    clock = Clock()
    net = ManetNetwork(RadioModel(100.0, 50.0, 0.1), clock=clock)
    net.add_node("a", 0.0, 0.0)
    net.add_node("b", 60.0, 0.0)                                   # quality 0.8
    with ManetSnmpAgent(net) as agent:
        address = agent.serve("a")

        async def go():
            src = source(*address, modules=frozenset({"NHDP-MIB", "OLSRv2-MIB"}))
            qualities = []
            try:
                for step in range(8):
                    clock.t += 10.0
                    if step == 4:
                        net.move("b", 75.0, 0.0)                     # quality 0.5 from now on
                    view = await src.read(frozenset({"neighbors"}))
                    qualities.append(view.neighbors[0].quality)
            finally:
                await src.aclose()
            return qualities, view
        qualities, view = run(go())
    assert "nhdpDiscIfSetPerfTable" in view.sources["neighbors"]
    assert qualities[0] == pytest.approx(0.8, abs=0.05)
    assert qualities[-1] == pytest.approx(0.5, abs=0.1)   # the window follows the change
    assert view.neighbors[0].metric == round(1024 / 0.25)


def test_a_steady_refresh_asks_only_the_node_name_its_change_counters_and_its_uptime(served, net):
    async def go():
        src = source(*served["robot3"], cache_seconds=60.0)
        asked: list[list[tuple[int, ...]]] = []
        get = src.get

        async def recording(oids, optional=frozenset()):
            oids = list(oids)
            asked.append(oids)
            return await get(oids, optional)
        src.get = recording
        try:
            first = await src.read(PARTS)
            asked.clear()
            again = await src.read(PARTS)
            steady = list(asked)
            asked.clear()
            net.move("robot5", 150.0, 40.0)
            moved = await src.read(PARTS)
            return first, again, steady, moved, list(asked)
        finally:
            await src.aclose()
    first, again, steady, moved, after = run(go())
    assert [len(oids) for oids in steady] == [4]
    assert again.neighbors == first.neighbors and again.links == first.links
    assert len(after) == 2 and len(after[1]) > 3     # the short check, then the full identity GET
    assert "robot5" in {n.name for n in moved.neighbors}


def test_an_agent_that_restarted_is_walked_again_though_its_change_counters_read_the_same(snmp_agent, net):
    """The change counters count from zero when an agent restarts, so a counter that reads what it
    read before proves nothing across a restart: sysUpTime going back tells one, and every walk
    cached before it is dropped. Without a restart, equal counters keep the cached walk (that is
    what they are for), however long the cache may keep it."""
    address = snmp_agent.addresses()["robot3"]
    node = snmp_agent.node("robot3")
    node.started = net.clock() - 100.0  # up for 100 s

    async def go():
        src = source(*address, cache_seconds=3600.0)
        try:
            first = await src.read(PARTS)
            version = net._topo_version
            net.move("robot5", 150.0, 40.0)   # robot5 becomes robot3's neighbour ...
            net._topo_version = version         # ... and the counter reads as before
            kept = await src.read(PARTS)
            node.started = net.clock()        # robot3's agent restarts: uptime from 0, nothing encoded yet
            snmp_agent._blocks.clear()
            fresh = await src.read(PARTS)
            return first, kept, fresh
        finally:
            await src.aclose()
    first, kept, fresh = run(go())
    assert "robot5" not in {n.name for n in first.neighbors}
    assert kept.neighbors == first.neighbors and kept.links == first.links
    assert "robot5" in {n.name for n in fresh.neighbors}


def test_a_timeout_is_noticed_on_time_and_every_request_is_answered_in_one_round_trip(served, bad_agent):
    async def go() -> tuple[int, float]:
        src = source(*served["robot1"])
        try:
            await src.read(frozenset(PARTS))
            before = src.requests
            await src.get([SYS_NAME_OID])
            asked = src.requests - before
        finally:
            await src.aclose()
        silent = SnmpSource(*nobody.address, timeout=0.5, retries=1)
        t0 = time.monotonic()
        try:
            with pytest.raises(SourceError, match=r"timeout 0\.5 s, 1 retry"):
                await silent.read(frozenset(PARTS))
        finally:
            await silent.aclose()
        return asked, time.monotonic() - t0

    nobody = bad_agent("silent")
    asked, took = run(go())
    assert asked == 1
    # two tries of 0.5 s each waited out, then the error: at least their time, exactly two requests
    # (a third try would be a third request), and a generous progress bound
    assert 0.95 <= took < 30.0
    wait_until(lambda: nobody.received >= 2, timeout=30)
    assert nobody.received == 2


@pytest.mark.parametrize("status", [-1, -200, 19, 2**31 - 1])
def test_an_error_status_outside_the_standard_list_is_named_by_its_number_not_a_crash(status):
    from erni.plugins.mobinet import ber

    src = SnmpSource("127.0.0.1", 9, timeout=0.1, retries=0)
    answer = ber.Response(1, b"public", 7, status, 1, [((1, 3, 6, 1), None)])
    with pytest.raises(SourceError, match=f"agent answered error-status {status} at "):
        src._checked("GET", answer)
