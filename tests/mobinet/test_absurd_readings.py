"""MobiNet against a hostile SNMP agent: absurd rows are dropped, named once a minute, and degrade only
the reading they belong to; `path_cost` matches a destination by the longest covering prefix."""

from __future__ import annotations

import asyncio
import ipaddress
import logging
import socket
import threading
from collections.abc import Iterator
from typing import Any

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from pyasn1.codec.ber import decoder, encoder
from pysnmp.proto import api
from pysnmp.proto.api import v2c

from erni.blackboard import Agent, NetInfo, Route, Task
from erni.blackboard.testing import wait_until
from erni.plugins.mobinet.babel import build_view, parse_dump
from erni.plugins.mobinet.control import routes_to
from erni.plugins.mobinet.resource import NEIGHBORS, PARTS, POSITIONS, ROUTES, TOPOLOGY, MobiNetResource
from erni.plugins.mobinet.sanity import MAX_HOPS, WORLD_BOUND, Limits
from erni.plugins.mobinet.snmp import SnmpSource

OID = tuple[int, ...]
ERNI = (1, 3, 6, 1, 4, 1, 32473, 1)
NHDP = (1, 3, 6, 1, 2, 1, 213, 1)
OLSRV2 = (1, 3, 6, 1, 2, 1, 219, 1)
INT32_MIN = -(2**31)
UINT32_MAX = 2**32 - 1


def ipv4(text: str) -> OID:
    return (1, 4, *ipaddress.IPv4Address(text).packed)


def route_index(dest: str, prefix: int) -> OID:
    return (*ipv4(dest), prefix)


def hostile_mib() -> dict[OID, Any]:
    """A node 'hostile' (10.0.0.1) with three other nodes; one good row and absurd rows in each table
    but the topology, which is all good."""
    mib: dict[OID, Any] = {
        (1, 3, 6, 1, 2, 1, 1, 5, 0): v2c.OctetString(b"hostile"),
        ERNI + (1, 1, 0): v2c.OctetString(b"hostile"),
        ERNI + (1, 3, 0): v2c.IpAddress("10.0.0.1"),
        ERNI + (1, 9, 0): v2c.Counter32(7),          # the change counters stand still: reads reuse walks
        ERNI + (1, 10, 0): v2c.Counter32(9),
        NHDP + (2, 1, 0): v2c.TimeTicks(100),
        OLSRV2 + (2, 6, 0): v2c.Unsigned32(1),
    }
    for i in (1, 2, 3, 4):
        mib[ERNI + (2, 1, 1, 2, i)] = v2c.OctetString(f"robot{i}".encode())
        mib[ERNI + (2, 1, 1, 3, i)] = v2c.IpAddress(f"10.0.0.{i}")
    positions = {1: (12500, -3000, 9000), 2: (INT32_MIN, 0, 0), 3: (1000, 2000, INT32_MIN),
                 4: (4000, 5000, 0)}
    for i, (x, y, h) in positions.items():
        mib[ERNI + (2, 2, 1, 1, i)] = v2c.Integer32(x)
        mib[ERNI + (2, 2, 1, 2, i)] = v2c.Integer32(y)
        mib[ERNI + (2, 2, 1, 3, i)] = (v2c.Integer32(h) if i != 4 else v2c.OctetString(b"north"))
    for i in (2, 3, 4):                             # neighbours: router and interface index = i
        mib[NHDP + (2, 3, 1, 2, i)] = v2c.Unsigned32(i)
        mib[NHDP + (2, 3, 1, 3, i)] = v2c.Unsigned32(i)
        mib[NHDP + (2, 3, 1, 4, i)] = v2c.Integer32(1)
        mib[NHDP + (2, 3, 1, 5, i)] = v2c.OctetString(ipaddress.IPv4Address(f"10.0.0.{i}").packed)
        mib[NHDP + (2, 6, 1, 1, i)] = v2c.Integer32(1)
        mib[OLSRV2 + (2, 5, 1, 2, i)] = v2c.OctetString(ipaddress.IPv4Address(f"10.0.0.{i}").packed)
        mib[OLSRV2 + (2, 5, 1, 3, i)] = v2c.Unsigned32(1600)
        mib[OLSRV2 + (2, 5, 1, 4, i)] = v2c.Unsigned32(1600)
    mib[ERNI + (3, 1, 1, 3, 2)] = v2c.Gauge32(800)
    mib[ERNI + (3, 1, 1, 3, 3)] = v2c.Gauge32(UINT32_MAX)
    mib[ERNI + (3, 1, 1, 3, 4)] = v2c.OctetString(b"good")
    routes = {("10.0.0.2", 32): (1, 1600), ("10.0.0.3", 32): (0, 1600), ("10.0.0.4", 32): (UINT32_MAX, 3200),
              ("192.0.2.0", 24): (2, 3200), ("192.0.0.0", 16): (3, 4800)}
    for (dest, prefix), (dist, metric) in routes.items():
        idx = route_index(dest, prefix)
        mib[OLSRV2 + (2, 11, 1, 4) + idx] = v2c.Integer32(1)
        mib[OLSRV2 + (2, 11, 1, 5) + idx] = v2c.OctetString(ipaddress.IPv4Address("10.0.0.2").packed)
        mib[OLSRV2 + (2, 11, 1, 8) + idx] = v2c.Unsigned32(dist)
        mib[OLSRV2 + (2, 11, 1, 9) + idx] = v2c.Unsigned32(metric)
    mib[OLSRV2 + (2, 8, 1, 6) + ipv4("10.0.0.2") + ipv4("10.0.0.3")] = v2c.Unsigned32(2048)
    return mib


class TableAgent:
    """A real UDP SNMPv2c agent (pysnmp's message layer) serving a fixed table of OIDs: GET, GETNEXT
    and GETBULK as RFC 3416 says; `mib` may be changed between requests."""

    def __init__(self, mib: dict[OID, Any]) -> None:
        self.mib = mib
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.bind(("127.0.0.1", 0))
        self.sock.settimeout(0.05)
        self.address: tuple[str, int] = self.sock.getsockname()
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="table-agent", daemon=True)
        self._thread.start()

    def _run(self) -> None:
        while not self._stop.is_set():
            try:
                data, peer = self.sock.recvfrom(65535)
            except TimeoutError:
                continue
            except OSError:
                return
            self.sock.sendto(self._reply(data), peer)

    def _next(self, keys: list[OID], oid: OID) -> tuple[OID, Any]:
        after = next((k for k in keys if k > oid), None)
        return (after, self.mib[after]) if after is not None else (oid, v2c.EndOfMibView(""))

    def _reply(self, data: bytes) -> bytes:
        p_mod = api.PROTOCOL_MODULES[api.SNMP_VERSION_2C]
        msg, _ = decoder.decode(data, asn1Spec=p_mod.Message())
        rsp_msg = p_mod.apiMessage.get_response(msg)
        rsp = p_mod.apiMessage.get_pdu(rsp_msg)
        req = p_mod.apiMessage.get_pdu(msg)
        asked = [tuple(oid) for oid, _ in p_mod.apiPDU.get_varbinds(req)]
        keys = sorted(self.mib)
        binds: list[tuple[OID, Any]] = []
        if req.isSameTypeWith(p_mod.GetRequestPDU()):
            binds = [(oid, self.mib.get(oid, v2c.NoSuchObject(""))) for oid in asked]
        elif req.isSameTypeWith(p_mod.GetNextRequestPDU()):
            binds = [self._next(keys, oid) for oid in asked]
        else:
            fixed = int(p_mod.apiBulkPDU.get_non_repeaters(req))
            reps = int(p_mod.apiBulkPDU.get_max_repetitions(req))
            binds = [self._next(keys, oid) for oid in asked[:fixed]]
            cursors = list(asked[fixed:])
            for _ in range(reps):
                row = [self._next(keys, oid) for oid in cursors]
                binds += row
                cursors = [oid for oid, _ in row]
        p_mod.apiPDU.set_varbinds(rsp, binds)
        return bytes(encoder.encode(rsp_msg))

    def close(self) -> None:
        self._stop.set()
        self._thread.join(2.0)
        self.sock.close()


@pytest.fixture
def hostile() -> Iterator[TableAgent]:
    agent = TableAgent(hostile_mib())
    yield agent
    agent.close()


def read(address: tuple[str, int], parts: frozenset[str] = PARTS, **kw: Any):
    async def go():
        # no answer is expected to be late here: a generous timeout keeps a loaded machine from failing it
        src = SnmpSource(*address, timeout=5.0, **kw)
        try:
            first = await src.read(parts)
            again = await src.read(parts)    # from the cache: the change counters stood still
            return first, again, src.requests
        finally:
            await src.aclose()
    return asyncio.run(go())


def test_absurd_rows_are_dropped_with_the_agent_the_oid_and_the_value(hostile):
    view, again, _ = read(hostile.address)
    where = f"snmp 127.0.0.1:{hostile.address[1]}"
    assert set(view.positions) == {"robot1"}
    assert (view.positions["robot1"].x, view.positions["robot1"].y, view.positions["robot1"].heading) \
        == (12.5, -3.0, 90.0)
    assert [(n.name, n.quality) for n in view.neighbors] == [("robot2", 0.8)]
    assert {r.destination: r.hops for r in view.routes} == {"robot2": 1, "192.0.2.0/24": 2, "192.0.0.0/16": 3}
    assert {(l.a, l.b) for l in view.links} == {("robot2", "robot3"), ("hostile", "robot2"),
                                               ("hostile", "robot3"), ("hostile", "robot4")}
    dropped = {(d.part, d.column): d for d in view.dropped}
    assert all(d.agent == where for d in view.dropped)
    assert set(dropped) == {
        (POSITIONS, "erniPositionX"), (POSITIONS, "erniPositionHeading"), (NEIGHBORS, "erniLinkQuality"),
        (ROUTES, "olsrv2TibRoutingSetDist")}
    assert len(view.dropped) == 7   # three positions, two link qualities, two routes
    messages = sorted(str(d) for d in view.dropped)
    assert messages == sorted(f"{where}: dropped {m}" for m in [
        "erniPositionX.2 (1.3.6.1.4.1.32473.1.2.2.1.1.2) = -2147483.648 m: beyond the world bound of ±10000 m "
        "(MobiNet setting world_bound)",
        "erniPositionHeading.3 (1.3.6.1.4.1.32473.1.2.2.1.3.3) = -21474836.48 deg: outside one turn (-360..360 deg)",
        "erniPositionHeading.4 (1.3.6.1.4.1.32473.1.2.2.1.3.4): expected Integer32, got OctetString 'north'",
        f"erniLinkQuality.3 (1.3.6.1.4.1.32473.1.3.1.1.3.3) = {UINT32_MAX}: a link quality outside 0..1 "
        "(0..1000 thousandths)",
        "erniLinkQuality.4 (1.3.6.1.4.1.32473.1.3.1.1.3.4): expected Unsigned32/Gauge32, got OctetString 'good'",
        "olsrv2TibRoutingSetDist.1.4.10.0.0.3.32 (1.3.6.1.2.1.219.1.2.11.1.8.1.4.10.0.0.3.32) = 0: a route to "
        "another node has at least 1 hop",
        f"olsrv2TibRoutingSetDist.1.4.10.0.0.4.32 (1.3.6.1.2.1.219.1.2.11.1.8.1.4.10.0.0.4.32) = {UINT32_MAX}: "
        "more hops than the 64 allowed (MobiNet setting max_hops)"])
    # a reading answered from the cached walks still says what it left out
    assert again.positions == view.positions and again.routes == view.routes
    assert sorted(map(str, again.dropped)) == messages


def test_the_world_bound_and_max_hops_are_limits_of_the_source(hostile):
    view, _, _ = read(hostile.address, frozenset({POSITIONS, ROUTES}), limits=Limits(world_bound=12.0, max_hops=2))
    assert view.positions == {}   # robot1 stands 12.5 m out
    assert {r.destination for r in view.routes} == {"robot2", "192.0.2.0/24"}   # the 3-hop route is too long
    messages = [str(d) for d in view.dropped]
    assert any("erniPositionX.1 " in m and "= 12.5 m: beyond the world bound of ±12 m" in m for m in messages)
    assert any("olsrv2TibRoutingSetDist.1.4.192.0.0.0.16" in m and "= 3: more hops than the 2 allowed" in m
               for m in messages)
    view, _, _ = read(hostile.address, frozenset({POSITIONS}), limits=Limits(world_bound=12.5))
    assert set(view.positions) == {"robot1"}   # on the bound is inside it


# -- the range checks, over the wire, on structured input ----------------------------------

@pytest.fixture(scope="module")
def table() -> Iterator[TableAgent]:
    agent = TableAgent(hostile_mib())
    yield agent
    agent.close()


@settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(x=st.integers(INT32_MIN, 2**31 - 1), y=st.integers(-20_000_000, 20_000_000),
       heading=st.integers(-40_000, 40_000) | st.integers(INT32_MIN, 2**31 - 1),
       quality=st.integers(0, 2_000) | st.integers(0, UINT32_MAX),
       dist=st.integers(0, 100) | st.integers(0, UINT32_MAX), metric=st.integers(0, UINT32_MAX))
def test_a_row_is_kept_exactly_when_it_is_physically_plausible(table, x, y, heading, quality, dist, metric):
    mib = hostile_mib()
    mib[ERNI + (2, 2, 1, 1, 1)], mib[ERNI + (2, 2, 1, 2, 1)] = v2c.Integer32(x), v2c.Integer32(y)
    mib[ERNI + (2, 2, 1, 3, 1)] = v2c.Integer32(heading)
    mib[ERNI + (3, 1, 1, 3, 2)] = v2c.Gauge32(quality)
    idx = route_index("10.0.0.2", 32)
    mib[OLSRV2 + (2, 11, 1, 8) + idx] = v2c.Unsigned32(dist)
    mib[OLSRV2 + (2, 11, 1, 9) + idx] = v2c.Unsigned32(metric)
    table.mib = mib
    view, _, _ = read(table.address, frozenset({POSITIONS, NEIGHBORS, ROUTES}))
    placed = abs(x) <= WORLD_BOUND * 1000 and abs(y) <= WORLD_BOUND * 1000 and abs(heading) <= 36_000
    assert ("robot1" in view.positions) == placed
    if placed:
        p = view.positions["robot1"]
        assert (p.x, p.y, p.heading) == (x / 1000, y / 1000, heading / 100)
    heard = {n.name: n.quality for n in view.neighbors}
    assert ("robot2" in heard) == (quality <= 1000)
    if quality <= 1000:
        assert heard["robot2"] == quality / 1000
    routed = {r.destination: r for r in view.routes}
    plausible = 1 <= dist <= MAX_HOPS and dist <= metric <= dist * 16776960
    assert ("robot2" in routed) == plausible
    if plausible:
        assert (routed["robot2"].hops, routed["robot2"].cost) == (dist, metric / 1024)
    # one dropped row each; the other rows stand
    assert len(view.dropped) == 7 + (not placed) + (quality > 1000) + (not plausible)
    assert "192.0.2.0/24" in routed


# -- only the reading with bad rows is degraded; one warning a minute per agent and column -------

def watch(agent: Agent, preposition: str, **params: Any) -> Task:
    task = Task(verb="NetWatch", preposition=preposition, params={"rate_hz": 20, **params}, source="test")
    with agent.transaction() as tx:
        tx.add(task)
    return task


def info_of(agent: Agent, task: Task) -> NetInfo | None:
    found = agent.query(NetInfo, where=lambda i: i.task == task.uid and bool(i.provenance))
    return found[0] if found else None


def test_only_the_kind_of_reading_with_absurd_rows_is_degraded_and_keeps_its_good_rows(hostile, caplog):
    caplog.set_level(logging.WARNING)
    agent = Agent("hostile", workers=2)
    plugin = agent.add_plugin("erni.plugins.mobinet:MobiNetControl", name="mobinet",
                              settings={"host": "127.0.0.1", "port": hostile.address[1], "timeout": 1.0,
                                        "write_pose": False})
    agent.start()
    try:
        tasks = {kind: watch(agent, kind) for kind in ("node_position", "link_quality", "network_topology")}
        tasks["path_cost"] = watch(agent, "path_cost", destination="192.0.2.1")
        infos = {kind: wait_until(lambda t=task: info_of(agent, t), timeout=10) for kind, task in tasks.items()}
        wait_until(lambda: plugin.resource.stats["reads"] >= 10, timeout=10)
    finally:
        agent.stop()
    where = f"snmp 127.0.0.1:{hostile.address[1]}"
    assert not infos["network_topology"].degraded and len(infos["network_topology"].links) == 4
    positions = infos["node_position"]
    assert positions.degraded and set(positions.positions) == {"robot1"}
    assert positions.message.startswith(f"{where}: dropped erniPosition")
    assert positions.message.endswith(" and 2 more")
    quality = infos["link_quality"]
    assert quality.degraded and [n.name for n in quality.neighbors] == ["robot2"]
    paths = infos["path_cost"]   # the longest prefix covering 192.0.2.1, not the /16
    assert [r.destination for r in paths.routes] == ["192.0.2.0/24"]
    assert paths.degraded and "olsrv2TibRoutingSetDist" in paths.message
    warned = [r.getMessage() for r in caplog.records if "dropped" in r.getMessage()]
    columns = ["erniPositionX", "erniPositionHeading", "erniLinkQuality", "olsrv2TibRoutingSetDist"]
    assert sorted(next(c for c in columns if f"dropped {c}." in m) for m in warned) == sorted(columns), warned
    assert all(m.startswith(f"{where}: dropped ") for m in warned)


def test_the_warning_comes_again_after_a_minute_counting_what_it_held_back(hostile, caplog):
    from erni.testing import ManualClock

    caplog.set_level(logging.WARNING)
    clock = ManualClock()  # times the watch and the warnings' minute
    log = logging.getLogger("test.absurd")
    delivered: list[Any] = []
    resource = MobiNetResource(lambda: SnmpSource(*hostile.address, timeout=1.0),
                               lambda key, view, error: delivered.append(view), log, clock=clock)

    def reads(n: int) -> None:  # n more reads of the 50 Hz watch, a period of the clock each
        for _ in range(n):
            count = len(delivered)
            clock.advance(0.02)
            wait_until(lambda count=count: len(delivered) > count, timeout=10,
                       message=f"no read of the watch due after {count} reads")

    resource.start()
    try:
        resource.watch("w", frozenset({POSITIONS}), 50.0)
        reads(5)
        first = [r.getMessage() for r in caplog.records if "erniPositionX" in r.getMessage()]
        clock.advance(58.0)
        reads(3)
        within = [r.getMessage() for r in caplog.records if "erniPositionX" in r.getMessage()]
        clock.advance(2.0)
        reads(2)
        after = [r.getMessage() for r in caplog.records if "erniPositionX" in r.getMessage()]
    finally:
        resource.close()
    assert len(first) == 1 and len(within) == 1
    assert len(after) == 2 and "similar message(s) suppressed" in after[1]
    assert resource.stats["dropped"] >= 2 * len(delivered) - 2


# -- longest-prefix match ------------------------------------------------------------------

def test_a_destination_is_matched_by_the_longest_covering_prefix():
    routes = [Route(destination="0.0.0.0/0", next_hop="gw"), Route(destination="192.0.0.0/16", next_hop="a"),
              Route(destination="192.0.2.0/24", next_hop="b"), Route(destination="robot5", next_hop="c"),
              Route(destination="2001:db8::/32", next_hop="d")]
    names = {"10.0.0.5": "robot5", "192.0.2.9": "robot9"}
    assert [r.next_hop for r in routes_to(routes, "192.0.2.1", names)] == ["b"]
    assert [r.next_hop for r in routes_to(routes, "192.0.3.1", names)] == ["a"]
    assert [r.next_hop for r in routes_to(routes, "198.51.100.1", names)] == ["gw"]
    assert [r.next_hop for r in routes_to(routes, "2001:db8::1", names)] == ["d"]
    assert [r.next_hop for r in routes_to(routes, "10.0.0.5", names)] == ["c"]     # the host route names it
    assert [r.next_hop for r in routes_to(routes, "robot9", names)] == ["b"]       # a name, by its address
    assert routes_to(routes, "robot7", names) == []
    assert routes_to(routes[1:], "2001:db9::1", names) == []


@given(st.lists(st.tuples(st.integers(0, 2**32 - 1), st.integers(0, 32)), min_size=1, max_size=12),
       st.integers(0, 2**32 - 1))
def test_the_longest_prefix_wins_among_any_set_of_network_routes(prefixes, address):
    routes = [Route(destination=str(ipaddress.IPv4Network((a, n), strict=False)), next_hop=f"h{i}")
              for i, (a, n) in enumerate(prefixes)]
    target = ipaddress.IPv4Address(address)
    covering = [(int(r.destination.split("/")[1]), r) for r in routes
                if target in ipaddress.IPv4Network(r.destination)]
    longest = max((n for n, _ in covering), default=None)
    expected = [r for n, r in covering if n == longest]
    got = routes_to(routes, str(target), {})
    exact = [r for r in routes if r.destination == str(target)]
    assert got == (exact or expected)


# -- babeld ---------------------------------------------------------------------------------

DUMP = """\
add interface wlan0 up true ipv6 fe80::1 ipv4 10.0.0.1
add neighbour 1 address fe80::2 if wlan0 reach ffff ureach 0000 rxcost 256 txcost 256 rtt 0.000 rttcost 0 cost 256
add neighbour 2 address fe80::3 if wlan0 reach ffff ureach 0000 rxcost 0 txcost 256 rtt 0.000 rttcost 0 cost 96
add xroute 10.0.0.1/32-0.0.0.0/0 prefix 10.0.0.1/32 from 0.0.0.0/0 metric 0
add route 11 prefix 10.0.0.2/32 from 0.0.0.0/0 installed yes id 02:02 metric 256 refmetric 0 via fe80::2 if wlan0
add route 12 prefix 10.0.0.3/32 from 0.0.0.0/0 installed yes id 03:03 metric 96 refmetric 0 via fe80::3 if wlan0
add route 13 prefix 10.0.0.4/32 from 0.0.0.0/0 installed yes id 04:04 metric 0 refmetric 0 via fe80::2 if wlan0
add route 14 prefix 10.0.0.5/32 from 0.0.0.0/0 installed yes id 05:05 metric 300 refmetric 512 via fe80::2 if wlan0
"""


def test_babel_lines_babeld_cannot_have_computed_are_dropped_and_named():
    view = build_view(parse_dump(DUMP.splitlines()), PARTS, node="robot1", where="babel [::1]:33123")
    assert [(n.address, n.quality) for n in view.neighbors] == [("10.0.0.2", 1.0)]
    assert {r.destination for r in view.routes} == {"10.0.0.2", "10.0.0.3"}
    assert {(l.a, l.b) for l in view.links} == {("10.0.0.2", "robot1")}
    parts = sorted((d.part, d.column) for d in view.dropped)
    assert parts == [(NEIGHBORS, "neighbour"), (ROUTES, "route"), (ROUTES, "route"),
                     (TOPOLOGY, "neighbour"), (TOPOLOGY, "route"), (TOPOLOGY, "route")]
    messages = {str(d) for d in view.dropped if d.part != TOPOLOGY}
    assert ("babel [::1]:33123: dropped neighbour fe80::3 on wlan0: finite cost 96 with rxcost 0 txcost 256 "
            "(a cost of 0 is no link)") in messages
    assert any("route 10.0.0.4/32 via fe80::2: metric 0 with refmetric 0" in m for m in messages)
    assert any("route 10.0.0.5/32 via fe80::2: metric 300 with refmetric 512" in m for m in messages)
