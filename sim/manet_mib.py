"""The MIB a simulated MANET node serves: NHDP/OLSRv2/IP-FORWARD subsets and the ERNI subtree.

`build_table(view)` turns a node's `NodeView` into a sorted list of `(oid, value)` pairs
(`oid` a tuple of ints, `value` a `Value`); `WRITABLE` lists the scalars an SNMP SET may
change. OIDs and units are documented in the README's MobiNet section; the client side
(plugins/mobinet/snmp.py) keeps its own copy, and a test checks both agree.
"""

from __future__ import annotations

import functools
import ipaddress
import time
from typing import Literal, NamedTuple

from erni.sim.manet import NodeView

OID = tuple[int, ...]

# standard MIB roots (numeric; see /reference/manet-snmp.md)
NHDP = (1, 3, 6, 1, 2, 1, 213, 1)
NHDP_DISC_IF = NHDP + (2, 3, 1)          # index: neighbour router index
NHDP_NIB_NEIGHBOR = NHDP + (2, 6, 1)     # index: neighbour router index
NHDP_DISC_IF_PERF = NHDP + (3, 2, 1)     # index: neighbour router index
OLSRV2 = (1, 3, 6, 1, 2, 1, 219, 1)
OLSRV2_IIB_LINK = OLSRV2 + (2, 1, 1)     # index: ifIndex, neighbour router index
OLSRV2_NIB_NEIGHBOR = OLSRV2 + (2, 5, 1)  # index: neighbour router index
OLSRV2_TOPOLOGY = OLSRV2 + (2, 8, 1)     # index: from router index, to router index
OLSRV2_ROUTING = OLSRV2 + (2, 11, 1)     # index: addrType, len, addr..., prefixLen
INET_CIDR_ROUTE = (1, 3, 6, 1, 2, 1, 4, 24, 7, 1)

# the product's subtree: 1.3.6.1.4.1.32473 is IANA's enterprise number for documentation
# (RFC 5612); a deployment with its own PEN changes ERNI_ROOT here and in the client.
ERNI_ROOT = (1, 3, 6, 1, 4, 1, 32473)
ERNI = ERNI_ROOT + (1,)                  # erniMobiNet
ERNI_NODE_NAME = ERNI + (1, 1, 0)
ERNI_NODE_INDEX = ERNI + (1, 2, 0)
ERNI_NODE_ADDRESS = ERNI + (1, 3, 0)
ERNI_POS_X = ERNI + (1, 4, 0)            # mm, read-write
ERNI_POS_Y = ERNI + (1, 5, 0)            # mm, read-write
ERNI_POS_HEADING = ERNI + (1, 6, 0)      # centidegrees, read-write
ERNI_POS_UPDATES = ERNI + (1, 7, 0)      # accepted position reports of this node
ERNI_COMM_RANGE = ERNI + (1, 8, 0)       # mm
ERNI_TOPOLOGY_VERSION = ERNI + (1, 9, 0)  # changes whenever links, metrics or routes may have
ERNI_STATE_VERSION = ERNI + (1, 10, 0)   # changes whenever anything served may have
ERNI_NODE_TABLE = ERNI + (2, 1)          # index: router index
ERNI_LINK_TABLE = ERNI + (3, 1)          # index: neighbour router index

WRITABLE: dict[OID, str] = {ERNI_POS_X: "x", ERNI_POS_Y: "y", ERNI_POS_HEADING: "heading"}
INT32 = (-(2**31), 2**31 - 1)
UINT32_MAX = 2**32 - 1
PERF_WINDOW = 1000  # NHDP perf counters describe the last PERF_WINDOW HELLOs
TRUE, FALSE = 1, 2  # SNMPv2-TC TruthValue

Kind = Literal["int", "str", "ip", "gauge", "counter", "ticks", "uns", "age"]


class Value(NamedTuple):
    """A typed SNMP value; kind `age` is a TimeTicks computed when it is read."""

    kind: Kind
    value: int | str | bytes | float

    def resolve(self) -> Value:
        """Return the value as served now (ages become TimeTicks since the report)."""
        if self.kind == "age":
            ticks = int(max(0.0, time.monotonic() - float(self.value)) * 100)
            return Value("ticks", min(ticks, UINT32_MAX))
        return self


@functools.lru_cache(maxsize=4096)
def _addr(address: str) -> bytes:
    return ipaddress.IPv4Address(address).packed


def _mm(metres: float) -> int:
    return max(INT32[0], min(INT32[1], round(metres * 1000)))


def _cdeg(degrees: float) -> int:
    return round(((degrees + 180.0) % 360.0 - 180.0) * 100)


def topology_rows(view: NodeView) -> list[tuple[OID, Value]]:
    """The OLSRv2 router topology set of the node's component, sorted (same for every member)."""
    index = {n.name: n for n in view.known_nodes}
    rows: list[tuple[OID, Value]] = []
    add = rows.append
    for a, b, metric in view.topology:
        ia, ib = index[a], index[b]
        idx = (ia.index, ib.index)
        add((OLSRV2_TOPOLOGY + (1,) + idx, Value("int", 1)))
        add((OLSRV2_TOPOLOGY + (2,) + idx, Value("str", _addr(ia.address))))
        add((OLSRV2_TOPOLOGY + (3,) + idx, Value("int", 1)))
        add((OLSRV2_TOPOLOGY + (4,) + idx, Value("str", _addr(ib.address))))
        add((OLSRV2_TOPOLOGY + (6,) + idx, Value("uns", metric)))
    rows.sort(key=lambda r: r[0])
    return rows


def build_table(view: NodeView, comm_range: float,
                with_topology: bool = True) -> list[tuple[OID, Value]]:
    """Every OID the node serves, sorted, with its value (without the topology set if asked)."""
    rows: list[tuple[OID, Value]] = []
    add = rows.append
    me = view.node
    own = view.positions.get(me.name)
    add((ERNI_NODE_NAME, Value("str", me.name)))
    add((ERNI_NODE_INDEX, Value("int", me.index)))
    add((ERNI_NODE_ADDRESS, Value("ip", me.address)))
    add((ERNI_POS_X, Value("int", _mm(own.x) if own else 0)))
    add((ERNI_POS_Y, Value("int", _mm(own.y) if own else 0)))
    add((ERNI_POS_HEADING, Value("int", _cdeg(own.heading) if own else 0)))
    add((ERNI_POS_UPDATES, Value("counter", view.position_updates)))
    add((ERNI_COMM_RANGE, Value("int", _mm(comm_range))))
    add((ERNI_TOPOLOGY_VERSION, Value("counter", view.topology_version % 2**32)))
    add((ERNI_STATE_VERSION, Value("counter", view.version % 2**32)))
    idx: tuple[int, ...]
    for node in view.known_nodes:
        idx = (node.index,)
        add((ERNI_NODE_TABLE + (2,) + idx, Value("str", node.name)))
        add((ERNI_NODE_TABLE + (3,) + idx, Value("ip", node.address)))
        pos = view.positions.get(node.name)
        if pos is not None:
            add((ERNI_NODE_TABLE + (4,) + idx, Value("int", _mm(pos.x))))
            add((ERNI_NODE_TABLE + (5,) + idx, Value("int", _mm(pos.y))))
            add((ERNI_NODE_TABLE + (6,) + idx, Value("int", _cdeg(pos.heading))))
            add((ERNI_NODE_TABLE + (7,) + idx, Value("age", pos.reported)))
    for nb in view.neighbors:
        idx = (nb.index,)
        truth = TRUE if nb.symmetric else FALSE
        add((ERNI_LINK_TABLE + (2,) + idx, Value("ip", nb.address)))
        add((ERNI_LINK_TABLE + (3,) + idx, Value("gauge", round(nb.quality * 1000))))
        add((ERNI_LINK_TABLE + (4,) + idx, Value("int", truth)))
        add((NHDP_DISC_IF + (2,) + idx, Value("int", nb.index)))
        add((NHDP_DISC_IF + (3,) + idx, Value("int", 1)))
        add((NHDP_DISC_IF + (4,) + idx, Value("str", _addr(nb.address))))
        add((NHDP_DISC_IF + (5,) + idx, Value("uns", 32)))
        add((NHDP_NIB_NEIGHBOR + (1,) + idx, Value("int", truth)))
        add((NHDP_DISC_IF_PERF + (1,) + idx, Value("counter", round(nb.quality * PERF_WINDOW))))
        add((NHDP_DISC_IF_PERF + (2,) + idx, Value("counter", PERF_WINDOW)))
        add((OLSRV2_IIB_LINK + (1, 1) + idx, Value("uns", nb.metric)))
        add((OLSRV2_IIB_LINK + (2, 1) + idx, Value("uns", nb.metric)))
        if nb.symmetric:
            add((OLSRV2_NIB_NEIGHBOR + (1,) + idx, Value("int", 1)))
            add((OLSRV2_NIB_NEIGHBOR + (2,) + idx, Value("str", _addr(nb.address))))
            add((OLSRV2_NIB_NEIGHBOR + (3,) + idx, Value("uns", nb.metric)))
            add((OLSRV2_NIB_NEIGHBOR + (4,) + idx, Value("uns", nb.metric)))
    index = {n.name: n for n in view.known_nodes}
    if with_topology:
        rows.extend(topology_rows(view))
    for dest, route in view.routes.items():
        d, hop = index[dest], index[route.next_hop]
        dest_addr: tuple[int, ...] = tuple(_addr(d.address))
        idx = (1, 4) + dest_addr + (32,)
        cost = min(UINT32_MAX, round(route.cost))
        add((OLSRV2_ROUTING + (5,) + idx, Value("str", _addr(hop.address))))
        add((OLSRV2_ROUTING + (8,) + idx, Value("uns", route.hops)))
        add((OLSRV2_ROUTING + (9,) + idx, Value("uns", cost)))
        cidr = (1, 4) + dest_addr + (32, 2, 0, 0, 1, 4) + tuple(_addr(hop.address))
        add((INET_CIDR_ROUTE + (7,) + cidr, Value("int", 1)))
        add((INET_CIDR_ROUTE + (8,) + cidr, Value("int", 4)))       # remote
        add((INET_CIDR_ROUTE + (9,) + cidr, Value("int", 1)))       # other (MANET)
        add((INET_CIDR_ROUTE + (12,) + cidr, Value("int", min(INT32[1], cost))))
    rows.sort(key=lambda r: r[0])
    return rows


def parse_position_write(current: tuple[float, float, float],
                         writes: dict[str, int]) -> tuple[float, float, float]:
    """Apply SET values (mm, mm, centidegrees) to the current (x m, y m, heading deg)."""
    x, y, heading = current
    if "x" in writes:
        x = writes["x"] / 1000.0
    if "y" in writes:
        y = writes["y"] / 1000.0
    if "heading" in writes:
        heading = writes["heading"] / 100.0
    return x, y, heading
