"""`SnmpSource`: the network subsystem read and written over SNMPv2c (asyncio UDP, `ber` messages)
or SNMPv3 with USM authPriv (`usm`, through pysnmp).

The source reads the standard MIB modules by their standard layout and works with any
agent: one GET asks for the node's identity (SNMPv2-MIB sysName, ERNI-MOBINET-MIB's
erniNodeName and address when served) and for one scalar of each module it may use —
nhdpUpTime (NHDP-MIB, RFC 7939), olsrv2NibNeighborSetTableAnsn (OLSRv2-MIB, RFC 7184),
inetCidrRouteNumber (IP-FORWARD-MIB, RFC 4292), erniNodeName — so it knows which modules
the agent implements. Each requested part comes from the first module that provides it:

- neighbours: NHDP-MIB nhdpDiscIfSetTable and nhdpNibNeighborSetTable; the link metric from
  OLSRv2-MIB olsrv2NibNeighborSetTable; the link quality from erniLinkTable, else from the
  HELLOs received/expected (nhdpDiscIfSetPerfTable) since the previous reading;
- topology: OLSRv2-MIB olsrv2TibRouterTopologySetTable plus the node's own advertised links
  (olsrv2NibNeighborSetTable);
- routes: OLSRv2-MIB olsrv2TibRoutingSetTable, else IP-FORWARD-MIB inetCidrRouteTable (next
  hop and inetCidrRouteMetric1, in the agent's routing protocol's units);
- positions: ERNI-MOBINET-MIB erniPositionTable.

A part no served module provides is listed in `NetView.missing` (e.g. a Debian snmpd serves
routes but neither NHDP nor OLSRv2), never an error; `NetView.sources` names the table each
filled part came from. Each table is walked with GETBULK over its columns at once; the
parts of one read run concurrently. When the agent serves the ERNI change counters
(erniTopologyVersion, erniStateVersion), a part whose counter has not moved is answered from
the last walk (for at most `cache_seconds`), so a steady network costs one GET per read.
Positions follow the state version; the other parts, and the names of the nodes, the topology
version, so robots that move without changing a link cost a topology reader one GET.
Every value is type-checked and every table row checked against physical limits (`sanity`):
a position beyond the world bound, a heading outside one turn, a link quality outside 0..1, a
route of 0 hops or more than `max_hops`, a metric outside its MIB range, a wrong type or a
malformed value drops that row alone, recorded in `NetView.dropped` with the OID and the value;
the other rows stand. A missing answer, an error status, or a wrong type in the node's identity
raises `SourceError` naming the OID and what was expected. Positions are written with SET and
the write community; the read community never writes. With a v3 user every request goes through
`usm.V3Session` (authenticated and encrypted; the user writes too) and its answer is decoded the same way.
"""

from __future__ import annotations

import asyncio
import ipaddress
import math
import os
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field
from typing import Any, NamedTuple

from erni import netgraph
from erni.blackboard import Link, Neighbor, Position, Route
from erni.blackboard.clock import monotonic
from erni.plugins.mobinet import ber
from erni.plugins.mobinet.ber import Value
from erni.plugins.mobinet.resource import (
    NEIGHBORS,
    POSITIONS,
    ROUTES,
    TOPOLOGY,
    NetView,
    SourceError,
)
from erni.plugins.mobinet.sanity import Absurd, Limits
from erni.plugins.mobinet.usm import UsmUser, V3Session

# --- the OIDs read and written (numeric: no MIB module is loaded at run time) -------------
# ERNI units: positions in mm, headings in centidegrees, link quality in thousandths;
# OLSRv2 link metrics are ETX scaled by METRIC_UNIT (a loss-free link costs 1024).

OID = tuple[int, ...]

METRIC_UNIT = 1024
MAXIMUM_METRIC = 16776960   # RFC 7181: the largest link metric (LinkMetricValue's upper bound, RFC 7184)
HELLO_WINDOW = 4    # HELLOs expected between two readings before their ratio is a link quality

SYS_NAME = (1, 3, 6, 1, 2, 1, 1, 5, 0)                         # SNMPv2-MIB (RFC 3418)
SYS_UP_TIME = (1, 3, 6, 1, 2, 1, 1, 3, 0)
NHDP = (1, 3, 6, 1, 2, 1, 213, 1)                              # NHDP-MIB (RFC 7939) nhdpObjects
NHDP_UP_TIME = NHDP + (2, 1, 0)
NHDP_DISC_IF = NHDP + (2, 3, 1)                                # INDEX { nhdpDiscIfSetIndex }
NHDP_DISC_IF_INDEX = NHDP_DISC_IF + (2,)                       # NeighborIfIndex
NHDP_DISC_ROUTER_INDEX = NHDP_DISC_IF + (3,)                   # NeighborRouterIndex
NHDP_DISC_IF_ADDR_TYPE = NHDP_DISC_IF + (4,)                   # InetAddressType
NHDP_DISC_IF_ADDR = NHDP_DISC_IF + (5,)                        # InetAddress
NHDP_NIB_SYMMETRIC = NHDP + (2, 6, 1, 1)                       # .<router>  TruthValue
NHDP_PERF_RECVD = NHDP + (3, 2, 1, 1)                          # .<ifIndex>  Counter32 HELLOs received
NHDP_PERF_EXPECTED = NHDP + (3, 2, 1, 2)                       # .<ifIndex>  Counter32 HELLOs expected
OLSRV2 = (1, 3, 6, 1, 2, 1, 219, 1)                            # OLSRv2-MIB (RFC 7184) olsrv2MIBObjects
OLSRV2_ORIG_ADDR_TYPE = OLSRV2 + (1, 3, 0)
OLSRV2_ORIG_ADDR = OLSRV2 + (1, 4, 0)
OLSRV2_ANSN = OLSRV2 + (2, 6, 0)
OLSRV2_NIB_ADDR = OLSRV2 + (2, 5, 1, 2)                        # .<router>  N_orig_addr
OLSRV2_NIB_IN_METRIC = OLSRV2 + (2, 5, 1, 3)                   # .<router>  N_in_metric
OLSRV2_NIB_OUT_METRIC = OLSRV2 + (2, 5, 1, 4)                  # .<router>  N_out_metric
OLSRV2_TOPO_METRIC = OLSRV2 + (2, 8, 1, 6)                     # .<from type,addr>.<to type,addr>
OLSRV2_ROUTE_NEXT_TYPE = OLSRV2 + (2, 11, 1, 4)                # .<dest type,addr>.<prefix>
OLSRV2_ROUTE_NEXT = OLSRV2 + (2, 11, 1, 5)
OLSRV2_ROUTE_DIST = OLSRV2 + (2, 11, 1, 8)                     # hops
OLSRV2_ROUTE_METRIC = OLSRV2 + (2, 11, 1, 9)                   # path cost
IP_FORWARD = (1, 3, 6, 1, 2, 1, 4, 24)                         # IP-FORWARD-MIB (RFC 4292)
INET_CIDR_ROUTE_NUMBER = IP_FORWARD + (6, 0)
INET_CIDR_ROUTE = IP_FORWARD + (7, 1)   # .<dest>.<pfxLen>.<policy>.<next hop>
INET_CIDR_TYPE = INET_CIDR_ROUTE + (8,)
INET_CIDR_METRIC1 = INET_CIDR_ROUTE + (12,)
INET_CIDR_STATUS = INET_CIDR_ROUTE + (17,)

ERNI = (1, 3, 6, 1, 4, 1, 32473, 1)                            # ERNI-MOBINET-MIB
ERNI_NODE_NAME = ERNI + (1, 1, 0)                # OCTET STRING
ERNI_NODE_ADDRESS = ERNI + (1, 3, 0)             # IpAddress
ERNI_POS_X = ERNI + (1, 4, 0)                    # Integer32 mm, read-write
ERNI_POS_Y = ERNI + (1, 5, 0)                    # Integer32 mm, read-write
ERNI_POS_HEADING = ERNI + (1, 6, 0)              # Integer32 centidegrees, read-write
ERNI_TOPOLOGY_VERSION = ERNI + (1, 9, 0)         # Counter32: changes when links/routes may have
ERNI_STATE_VERSION = ERNI + (1, 10, 0)           # Counter32: changes when anything may have
ERNI_NODES_NAME = ERNI + (2, 1, 1, 2)            # .<node>  DisplayString
ERNI_NODES_ADDRESS = ERNI + (2, 1, 1, 3)         # .<node>  IpAddress
ERNI_POSITION_X = ERNI + (2, 2, 1, 1)            # .<node>  Integer32 mm
ERNI_POSITION_Y = ERNI + (2, 2, 1, 2)            # .<node>  Integer32 mm
ERNI_POSITION_HEADING = ERNI + (2, 2, 1, 3)      # .<node>  Integer32 centidegrees
ERNI_LINK_QUALITY = ERNI + (3, 1, 1, 3)          # .<router>  Gauge32 thousandths

NAMES: dict[OID, str] = {
    SYS_NAME: "sysName", SYS_UP_TIME: "sysUpTime", NHDP_UP_TIME: "nhdpUpTime",
    NHDP_DISC_IF_INDEX: "nhdpDiscIfIndex", NHDP_DISC_ROUTER_INDEX: "nhdpDiscRouterIndex",
    NHDP_DISC_IF_ADDR_TYPE: "nhdpDiscIfSetIpAddrType", NHDP_DISC_IF_ADDR: "nhdpDiscIfSetIpAddr",
    NHDP_NIB_SYMMETRIC: "nhdpNibNeighborSetNSymmetric", NHDP_PERF_RECVD: "nhdpDiscIfRecvdPackets",
    NHDP_PERF_EXPECTED: "nhdpDiscIfExpectedPackets", OLSRV2_ORIG_ADDR_TYPE: "olsrv2OrigIpAddrType",
    OLSRV2_ORIG_ADDR: "olsrv2OrigIpAddr", OLSRV2_ANSN: "olsrv2NibNeighborSetTableAnsn",
    OLSRV2_NIB_ADDR: "olsrv2NibNeighborSetNOrigIpAddr", OLSRV2_NIB_IN_METRIC: "olsrv2NibNeighborSetNInMetricValue",
    OLSRV2_NIB_OUT_METRIC: "olsrv2NibNeighborSetNOutMetricValue",
    OLSRV2_TOPO_METRIC: "olsrv2TibRouterTopologySetMetricValue",
    OLSRV2_ROUTE_NEXT_TYPE: "olsrv2TibRoutingSetNextIfIpAddrType", OLSRV2_ROUTE_NEXT: "olsrv2TibRoutingSetNextIfIpAddr",
    OLSRV2_ROUTE_DIST: "olsrv2TibRoutingSetDist", OLSRV2_ROUTE_METRIC: "olsrv2TibRoutingSetMetricValue",
    INET_CIDR_ROUTE_NUMBER: "inetCidrRouteNumber", INET_CIDR_TYPE: "inetCidrRouteType",
    INET_CIDR_METRIC1: "inetCidrRouteMetric1", INET_CIDR_STATUS: "inetCidrRouteStatus",
    ERNI_NODE_NAME: "erniNodeName", ERNI_NODE_ADDRESS: "erniNodeAddress", ERNI_POS_X: "erniPosX",
    ERNI_POS_Y: "erniPosY", ERNI_POS_HEADING: "erniPosHeading",
    ERNI_TOPOLOGY_VERSION: "erniTopologyVersion", ERNI_STATE_VERSION: "erniStateVersion",
    ERNI_NODES_NAME: "erniNodesName", ERNI_NODES_ADDRESS: "erniNodesAddress", ERNI_POSITION_X: "erniPositionX",
    ERNI_POSITION_Y: "erniPositionY", ERNI_POSITION_HEADING: "erniPositionHeading",
    ERNI_LINK_QUALITY: "erniLinkQuality",
}

# one scalar per module tells whether the agent implements it
PROBES: dict[str, OID] = {"NHDP-MIB": NHDP_UP_TIME, "OLSRv2-MIB": OLSRV2_ANSN,
                          "IP-FORWARD-MIB": INET_CIDR_ROUTE_NUMBER, "ERNI-MOBINET-MIB": ERNI_NODE_NAME}

# the change counters: whether the last view stands (topology: links, routes, names; state: positions too)
VERSIONS = (ERNI_TOPOLOGY_VERSION, ERNI_STATE_VERSION)


def label(oid: OID) -> str:
    """`name.index` for a known column or scalar, else the dotted OID."""
    for n in range(len(oid), 0, -1):
        name = NAMES.get(oid[:n])
        if name:
            rest = ".".join(map(str, oid[n:]))
            return f"{name}.{rest}" if rest else name
    return ".".join(map(str, oid))


def dotted(oid: OID) -> str:
    """The OID as `1.3.6...`."""
    return ".".join(map(str, oid))


def column(oid: OID) -> str:
    """The name of the known column or scalar `oid` is an instance of, else the dotted OID."""
    for n in range(len(oid), 0, -1):
        name = NAMES.get(oid[:n])
        if name:
            return name
    return dotted(oid)


def _implausible(oid: OID, value: object, why: str | None) -> None:
    """Raise SourceError naming `oid` and its value when `why` says the value is not plausible."""
    if why is not None:
        raise SourceError(f"{label(oid)} ({dotted(oid)}) = {value}: {why}")


# --- typed decoding -------------------------------------------------------------------

_TYPES = {
    "Integer32": (ber.INTEGER,),
    "OCTET STRING": (ber.OCTET_STRING,),
    "IpAddress": (ber.IP_ADDRESS,),
    "Unsigned32/Gauge32": (ber.GAUGE32,),   # one tag: Unsigned32 and Gauge32 share [APPLICATION 2]
    "Counter32": (ber.COUNTER32,),
    "TimeTicks": (ber.TIME_TICKS,),
}
_NULL = Value(ber.NULL, None)


def _typed(oid: OID, value: Value, expected: str) -> Any:
    if value.tag not in _TYPES[expected]:
        raise SourceError(f"{label(oid)} ({dotted(oid)}): expected {expected}, got "
                          f"{value.type_name} {value.shown()[:40]!r}")
    return value.value


def _int(oid: OID, value: Any, expected: str = "Integer32") -> int:
    return int(_typed(oid, value, expected))


def _text(oid: OID, value: Any) -> str:
    raw = bytes(_typed(oid, value, "OCTET STRING"))
    try:
        return raw.decode("utf-8")
    except UnicodeDecodeError:
        raise SourceError(f"{label(oid)}: expected UTF-8 text, got {raw[:20]!r}") from None


def _ip(oid: OID, value: Any) -> str:
    raw = bytes(_typed(oid, value, "IpAddress"))
    if len(raw) != 4:
        raise SourceError(f"{label(oid)}: expected a 4-byte IpAddress, got {len(raw)} byte(s)")
    return str(ipaddress.IPv4Address(raw))


def _address(oid: OID, raw: bytes, kind: int | None = None) -> str:
    """An InetAddress of 4 (ipv4) or 16 (ipv6) bytes as text; `kind` its InetAddressType if known."""
    if len(raw) == 4 and kind in (None, 1):
        return str(ipaddress.IPv4Address(raw))
    if len(raw) == 16 and kind in (None, 2):
        return str(ipaddress.IPv6Address(raw))
    raise SourceError(f"{label(oid)}: expected an IPv4 (4 bytes) or IPv6 (16 bytes) InetAddress, got "
                      f"{len(raw)} byte(s) of type {kind}")


def _inet(oid: OID, value: Any, kind: int | None = None) -> str:
    return _address(oid, bytes(_typed(oid, value, "OCTET STRING")), kind)


def _inet_index(oid: OID, idx: OID, at: int) -> tuple[str, int]:
    """An `InetAddressType, InetAddress` pair inside an index: (text, position after it).

    An unknown(0) type with a zero-length address gives ""."""
    if len(idx) < at + 2:
        raise SourceError(f"{label(oid)}: index too short for an InetAddressType and InetAddress")
    kind, size = idx[at], idx[at + 1]
    octets = idx[at + 2: at + 2 + size]
    if len(octets) != size or any(o > 255 for o in octets):
        raise SourceError(f"{label(oid)}: malformed InetAddress in the index")
    if kind == 0 and size == 0:
        return "", at + 2
    return _address(oid, bytes(octets), kind), at + 2 + size


def _quality_of_metric(metric: int) -> float:
    return min(1.0, math.sqrt(METRIC_UNIT / metric)) if metric > 0 else 1.0


Columns = dict[OID, dict[OID, Value]]


class _Link(asyncio.DatagramProtocol):
    """The UDP socket to one agent: answers are matched to waiting requests by request-id."""

    def __init__(self) -> None:
        self.transport: asyncio.DatagramTransport | None = None
        self.waiting: dict[int, asyncio.Future[ber.Response]] = {}
        self.malformed = 0   # answers that were not a well-formed SNMPv2c Response (ignored)
        self.last_error = ""

    def connection_made(self, transport: asyncio.BaseTransport) -> None:
        self.transport = transport  # type: ignore[assignment]

    def datagram_received(self, data: bytes, addr: Any) -> None:
        try:
            answer = ber.decode_response(data)
        except ber.BerError as err:
            self.malformed += 1
            self.last_error = str(err)
            return
        waiting = self.waiting.get(answer.request_id)
        if answer.version == 1 and waiting is not None and not waiting.done():
            waiting.set_result(answer)

    def error_received(self, exc: Exception) -> None:
        self.last_error = str(exc)  # e.g. ICMP port unreachable: the request times out, as unanswered

    def connection_lost(self, exc: Exception | None) -> None:
        self.transport = None


class ViewStamp(NamedTuple):
    """What a decoded view stands on: the node's name, its change counters (None: not served) and
    the parts read."""

    node: str
    topology: int | None
    state: int | None
    parts: frozenset[str]

    @property
    def complete(self) -> bool:
        """Both change counters are served: they can say whether the view stands."""
        return self.topology is not None and self.state is not None

    def stands(self, node: str, topology: int | None, state: int | None) -> bool:
        """Whether the agent's (node name, topology version, state version) now leave a view read at
        this stamp standing: positions follow the state version, which moves with every robot that
        moves; the other parts (and the names of the nodes that links and routes name) the topology
        version."""
        return (node, topology) == (self.node, self.topology) and (POSITIONS not in self.parts
                                                                   or state == self.state)


class WalkKey(NamedTuple):
    """What a cached walk was read for: the node, the change counter its job follows, its columns."""

    node: str
    version: int | None
    columns: tuple[OID, ...]


@dataclass(frozen=True)
class CachedWalk:
    key: WalkKey
    when: float       # the source's clock when it was walked
    columns: Columns


@dataclass(frozen=True)
class CachedView:
    stamp: ViewStamp
    when: float       # when the oldest walk it is made of was read
    view: NetView


@dataclass
class WalkCache:
    """One agent's last walk of each job and its last decoded view."""

    walks: dict[str, CachedWalk] = field(default_factory=dict)
    view: CachedView | None = None

    def clear(self) -> None:
        self.walks.clear()
        self.view = None


@dataclass(frozen=True)
class _Decoded:
    """The rows one decoding of a job's walk gave (reused while the walk and the names stand)."""

    columns: Columns
    node: str
    names: dict[str, str]
    rows: list[Any]
    dropped: list[Absurd]


class SnmpDecoder:
    """One agent's MIB rows made a NetView: which columns give each part, and the decoding of the
    walked rows into names, neighbours (HELLO baselines kept between readings), links, routes and
    positions; a mistyped, malformed or implausible row is dropped and said (`view.dropped`)."""

    def __init__(self, where: str, limits: Limits) -> None:
        self.where = where
        self.limits = limits
        self._hellos: dict[str, tuple[int, int]] = {}        # neighbour address -> HELLO baseline
        self._decoded: dict[str, _Decoded] = {}              # job -> its last decoding

    def forget(self) -> None:
        """Drop the decodings kept for reuse (the agent restarted)."""
        self._decoded.clear()

    def decode(self, view: NetView, parts: frozenset[str], served: set[str], got: dict[str, Columns]) -> None:
        """Fill `view`'s requested `parts` from the columns walked for each job (`got`)."""
        by_index = self._decode_nodes(view, got.get("nodes", {}))
        if NEIGHBORS in parts and NEIGHBORS in got:
            self._decode_neighbors(view, got[NEIGHBORS])
        if TOPOLOGY in parts and TOPOLOGY in got:
            self._reuse(TOPOLOGY, got[TOPOLOGY], view, "links", self._decode_topology)
        if ROUTES in parts and ROUTES in got:
            self._reuse(ROUTES, got[ROUTES], view, "routes",
                        self._decode_routes if "OLSRv2-MIB" in served else self._decode_cidr_routes)
        if POSITIONS in parts and POSITIONS in got:
            self._decode_positions(view, got[POSITIONS], by_index)

    def _reuse(self, job: str, cols: Columns, view: NetView, field: str,
               decode: Callable[[NetView, Columns], None]) -> None:
        """Fill `view.<field>` by `decode(view, cols)`, or with the rows of the last decoding when it read
        the same walk (the cached columns themselves) with the same names: a team of N robots reporting
        positions changes the state version on every read, and its topology of N^2 links need not be
        decoded again for that."""
        last = self._decoded.get(job)
        if last is not None and last.columns is cols and last.node == view.node and last.names == view.names:
            setattr(view, field, list(last.rows))
            view.dropped.extend(last.dropped)
            return
        decode(view, cols)
        self._decoded[job] = _Decoded(cols, view.node, dict(view.names), list(getattr(view, field)),
                                      [row for row in view.dropped if row.part == job])

    def identity(self, ident: dict[OID, Any], served: set[str]) -> NetView:
        """The node's name and address: ERNI's when served, else sysName and the OLSRv2 originator."""
        erni = "ERNI-MOBINET-MIB" in served
        if erni:
            name, source = _text(ERNI_NODE_NAME, ident[ERNI_NODE_NAME]), "ERNI-MOBINET-MIB erniNodeName"
        elif SYS_NAME in ident:
            name, source = _text(SYS_NAME, ident[SYS_NAME]), "SNMPv2-MIB sysName"
        else:
            raise SourceError(f"SNMP agent {self.where}: serves neither sysName (SNMPv2-MIB) nor "
                              "erniNodeName: not an SNMPv2 agent")
        address = ""
        if erni and ERNI_NODE_ADDRESS in ident:
            address = _ip(ERNI_NODE_ADDRESS, ident[ERNI_NODE_ADDRESS])
        elif "OLSRv2-MIB" in served and OLSRV2_ORIG_ADDR in ident:
            kind = (_int(OLSRV2_ORIG_ADDR_TYPE, ident[OLSRV2_ORIG_ADDR_TYPE])
                    if OLSRV2_ORIG_ADDR_TYPE in ident else None)
            address = _inet(OLSRV2_ORIG_ADDR, ident[OLSRV2_ORIG_ADDR], kind)
        view = NetView(node=name, address=address)
        view.sources["node"] = f"snmp {self.where} {source}"
        return view

    def jobs(self, parts: frozenset[str], served: set[str], view: NetView) -> dict[str, list[OID]]:
        """The columns to walk for each part the served modules provide; the rest go to `missing`."""
        jobs: dict[str, list[OID]] = {}
        erni, nhdp, olsrv2 = "ERNI-MOBINET-MIB" in served, "NHDP-MIB" in served, "OLSRv2-MIB" in served
        where = f"snmp {self.where}"

        def lacks(part: str, *modules: str) -> None:
            view.missing[part] = f"{' and '.join(modules)} not served by {self.where}"

        if erni:
            jobs["nodes"] = [ERNI_NODES_NAME, ERNI_NODES_ADDRESS]
        if NEIGHBORS in parts:
            if nhdp:
                cols: list[OID] = [NHDP_DISC_IF_INDEX, NHDP_DISC_ROUTER_INDEX, NHDP_DISC_IF_ADDR_TYPE, NHDP_DISC_IF_ADDR,
                        NHDP_NIB_SYMMETRIC, NHDP_PERF_RECVD, NHDP_PERF_EXPECTED]
                tables = "NHDP-MIB nhdpDiscIfSetTable, nhdpNibNeighborSetTable"
                if olsrv2:
                    cols.append(OLSRV2_NIB_IN_METRIC)
                    tables += "; metric: OLSRv2-MIB olsrv2NibNeighborSetTable"
                if erni:
                    cols.append(ERNI_LINK_QUALITY)
                    tables += "; quality: ERNI-MOBINET-MIB erniLinkTable"
                else:
                    tables += "; quality: NHDP-MIB nhdpDiscIfSetPerfTable (HELLOs received/expected)"
                jobs[NEIGHBORS] = cols
                view.sources[NEIGHBORS] = f"{where} {tables}"
            else:
                lacks(NEIGHBORS, "NHDP-MIB")
        if TOPOLOGY in parts:
            if olsrv2:
                jobs[TOPOLOGY] = [OLSRV2_TOPO_METRIC, OLSRV2_NIB_ADDR, OLSRV2_NIB_OUT_METRIC]
                view.sources[TOPOLOGY] = (f"{where} OLSRv2-MIB olsrv2TibRouterTopologySetTable and "
                                          "olsrv2NibNeighborSetTable (this node's advertised links)")
            else:
                lacks(TOPOLOGY, "OLSRv2-MIB")
        if ROUTES in parts:
            if olsrv2:
                jobs[ROUTES] = [OLSRV2_ROUTE_NEXT_TYPE, OLSRV2_ROUTE_NEXT, OLSRV2_ROUTE_DIST, OLSRV2_ROUTE_METRIC]
                view.sources[ROUTES] = f"{where} OLSRv2-MIB olsrv2TibRoutingSetTable"
            elif "IP-FORWARD-MIB" in served:
                jobs[ROUTES] = [INET_CIDR_TYPE, INET_CIDR_METRIC1, INET_CIDR_STATUS]
                view.sources[ROUTES] = (f"{where} IP-FORWARD-MIB inetCidrRouteTable (cost: inetCidrRouteMetric1 "
                                        "in the routing protocol's units; hops 1 for local routes, else 0: unknown)")
            else:
                lacks(ROUTES, "OLSRv2-MIB", "IP-FORWARD-MIB")
        if POSITIONS in parts:
            if erni:
                jobs[POSITIONS] = [ERNI_POSITION_X, ERNI_POSITION_Y, ERNI_POSITION_HEADING]
                view.sources[POSITIONS] = f"{where} ERNI-MOBINET-MIB erniPositionTable"
            else:
                lacks(POSITIONS, "ERNI-MOBINET-MIB")
        return jobs


    def _name(self, view: NetView, address: str) -> str:
        return view.names.get(address, address)

    def _drop(self, view: NetView, part: str, oid: OID, err: SourceError) -> None:
        """Leave one row out of `part`: it was mistyped, malformed or implausible (`err` says how)."""
        view.dropped.append(Absurd(f"snmp {self.where}", part, column(oid), str(err)))

    def _decode_nodes(self, view: NetView, cols: Columns) -> dict[OID, str]:
        by_index: dict[OID, str] = {}
        for idx, val in cols.get(ERNI_NODES_NAME, {}).items():
            try:
                by_index[idx] = _text(ERNI_NODES_NAME + idx, val)
            except SourceError as err:   # the node is named by its address
                self._drop(view, "names", ERNI_NODES_NAME + idx, err)
        for idx, val in cols.get(ERNI_NODES_ADDRESS, {}).items():
            try:
                addr = _ip(ERNI_NODES_ADDRESS + idx, val)
            except SourceError as err:
                self._drop(view, "names", ERNI_NODES_ADDRESS + idx, err)
                continue
            if idx in by_index:
                view.names[addr] = by_index[idx]
        if view.address:
            view.names.setdefault(view.address, view.node)
        return by_index

    def _decode_positions(self, view: NetView, cols: Columns, by_index: dict[OID, str]) -> None:
        xs, ys, hs = cols[ERNI_POSITION_X], cols[ERNI_POSITION_Y], cols[ERNI_POSITION_HEADING]
        limits = self.limits
        for idx in sorted(xs):
            if idx not in ys:
                continue
            name = by_index.get(idx, ".".join(map(str, idx)))
            oid = ERNI_POSITION_X + idx
            try:
                x = _int(oid, xs[idx]) / 1000.0
                _implausible(oid, f"{x} m", limits.coordinate(x))
                oid = ERNI_POSITION_Y + idx
                y = _int(oid, ys[idx]) / 1000.0
                _implausible(oid, f"{y} m", limits.coordinate(y))
                h = 0.0
                if idx in hs:
                    oid = ERNI_POSITION_HEADING + idx
                    h = _int(oid, hs[idx]) / 100.0
                    _implausible(oid, f"{h} deg", limits.heading(h))
            except SourceError as err:
                self._drop(view, POSITIONS, oid, err)
                continue
            view.positions[name] = Position(x=x, y=y, heading=h)

    def _decode_neighbors(self, view: NetView, cols: Columns) -> None:
        routers: dict[int, list[tuple[int, str]]] = {}   # router index -> [(if index, address)]
        for idx, val in sorted(cols[NHDP_DISC_ROUTER_INDEX].items()):
            oid = NHDP_DISC_ROUTER_INDEX + idx
            try:
                router = _int(oid, val, "Unsigned32/Gauge32")
                if idx not in cols[NHDP_DISC_IF_ADDR]:
                    continue
                oid = NHDP_DISC_IF_ADDR_TYPE + idx
                kind = (_int(oid, cols[NHDP_DISC_IF_ADDR_TYPE][idx])
                        if idx in cols[NHDP_DISC_IF_ADDR_TYPE] else None)
                oid = NHDP_DISC_IF_ADDR + idx
                addr = _inet(oid, cols[NHDP_DISC_IF_ADDR][idx], kind)
                oid = NHDP_DISC_IF_INDEX + idx
                if_index = (_int(oid, cols[NHDP_DISC_IF_INDEX][idx], "Unsigned32/Gauge32")
                            if idx in cols[NHDP_DISC_IF_INDEX] else 0)
            except SourceError as err:
                self._drop(view, NEIGHBORS, oid, err)
                continue
            routers.setdefault(router, []).append((if_index, addr))
        sym, metric = cols[NHDP_NIB_SYMMETRIC], cols.get(OLSRV2_NIB_IN_METRIC, {})
        quality = cols.get(ERNI_LINK_QUALITY, {})
        for router, ifaces in sorted(routers.items()):
            r = (router,)
            addr = ifaces[0][1]
            oid = NHDP_NIB_SYMMETRIC + r
            try:
                truth = _int(oid, sym[r]) if r in sym else 2
                if truth not in (1, 2):
                    _implausible(oid, truth, "expected TruthValue true(1) or false(2)")
                if r in quality:
                    oid = ERNI_LINK_QUALITY + r
                    thousandths = _int(oid, quality[r], "Unsigned32/Gauge32")
                    q = thousandths / 1000.0
                    why = self.limits.quality(q)
                    _implausible(oid, thousandths, why and f"{why} (0..1000 thousandths)")
                else:
                    oid = NHDP_PERF_RECVD
                    q = self._hello_quality(addr, cols, [i for i, _ in ifaces])
                m = None
                if r in metric and truth == 1:
                    oid = OLSRV2_NIB_IN_METRIC + r
                    m = _int(oid, metric[r], "Unsigned32/Gauge32")
                    _implausible(oid, m, None if m <= MAXIMUM_METRIC else
                                 f"a link metric above MAXIMUM_METRIC {MAXIMUM_METRIC}")
            except SourceError as err:
                self._drop(view, NEIGHBORS, oid, err)
                continue
            view.neighbors.append(Neighbor(name=self._name(view, addr), address=addr, quality=q,
                                           symmetric=truth == 1, metric=m))

    def _hello_quality(self, address: str, cols: Columns, if_indexes: list[int]) -> float:
        """HELLOs received / expected since a baseline at least HELLO_WINDOW HELLOs old (else since ever)."""
        recvd = expected = 0
        for i in if_indexes:
            k = (i,)
            if k in cols[NHDP_PERF_RECVD] and k in cols[NHDP_PERF_EXPECTED]:
                got = _int(NHDP_PERF_RECVD + k, cols[NHDP_PERF_RECVD][k], "Counter32")
                due = _int(NHDP_PERF_EXPECTED + k, cols[NHDP_PERF_EXPECTED][k], "Counter32")
                _implausible(NHDP_PERF_RECVD + k, got, None if got <= due else
                             f"more HELLOs received than the {due} expected (nhdpDiscIfExpectedPackets)")
                recvd, expected = recvd + got, expected + due
        base = self._hellos.get(address)
        if base is None or expected < base[1]:          # first reading, or a counter discontinuity
            self._hellos[address] = (recvd, expected)
            return min(1.0, recvd / expected) if expected else 0.0
        d_recvd, d_expected = recvd - base[0], expected - base[1]
        if d_expected < HELLO_WINDOW:
            if base[1] == 0:
                return 0.0
            d_recvd, d_expected = recvd, expected
        else:
            self._hellos[address] = (recvd, expected)
        return max(0.0, min(1.0, d_recvd / d_expected))

    @staticmethod
    def _metric(oid: OID, value: Value) -> int:
        m = _int(oid, value, "Unsigned32/Gauge32")
        _implausible(oid, m, None if m <= MAXIMUM_METRIC else f"a link metric above MAXIMUM_METRIC {MAXIMUM_METRIC}")
        return m

    def _decode_topology(self, view: NetView, cols: Columns) -> None:
        seen: dict[frozenset[str], Link] = {}

        def add(a: str, b: str, m: int) -> None:
            key = frozenset((a, b))
            if a != b and key not in seen:
                seen[key] = Link(a=min(a, b), b=max(a, b), quality=_quality_of_metric(m), metric=m)

        for idx, val in sorted(cols[OLSRV2_TOPO_METRIC].items()):
            oid = OLSRV2_TOPO_METRIC + idx
            try:
                src, at = _inet_index(oid, idx, 0)
                dst, end = _inet_index(oid, idx, at)
                if end != len(idx) or not src or not dst:
                    raise SourceError(f"{label(oid)}: expected an index of two InetAddressType, InetAddress pairs")
                m = self._metric(oid, val)
            except SourceError as err:
                self._drop(view, TOPOLOGY, oid, err)
                continue
            add(self._name(view, src), self._name(view, dst), m)
        me = view.node
        addresses, outs = cols[OLSRV2_NIB_ADDR], cols[OLSRV2_NIB_OUT_METRIC]
        for idx, val in sorted(outs.items()):   # this node's own links: its symmetric neighbours
            oid = OLSRV2_NIB_OUT_METRIC + idx
            try:
                m = self._metric(oid, val)
                if idx not in addresses or m >= MAXIMUM_METRIC:   # no symmetric link
                    continue
                oid = OLSRV2_NIB_ADDR + idx
                other = _inet(oid, addresses[idx])
            except SourceError as err:
                self._drop(view, TOPOLOGY, oid, err)
                continue
            add(me, self._name(view, other), m)
        view.links = list(seen.values())

    def _decode_routes(self, view: NetView, cols: Columns) -> None:
        hops, dists, metrics = cols[OLSRV2_ROUTE_NEXT], cols[OLSRV2_ROUTE_DIST], cols[OLSRV2_ROUTE_METRIC]
        kinds = cols[OLSRV2_ROUTE_NEXT_TYPE]
        for idx, val in sorted(hops.items()):
            oid = OLSRV2_ROUTE_NEXT + idx
            try:
                dest, at = _inet_index(oid, idx, 0)
                if at + 1 != len(idx) or not dest:
                    raise SourceError(f"{label(oid)}: expected an index InetAddressType.InetAddress.prefixLen")
                prefix = idx[at]
                if prefix > ipaddress.ip_address(dest).max_prefixlen:
                    raise SourceError(f"{label(oid)}: prefix length {prefix} is too long for {dest}")
                oid = OLSRV2_ROUTE_NEXT_TYPE + idx
                kind = _int(oid, kinds[idx]) if idx in kinds else None
                oid = OLSRV2_ROUTE_NEXT + idx
                hop = _inet(oid, val, kind)
                dist = 0
                if idx in dists:   # every row of the routing set leads to another router: 1.. hops
                    oid = OLSRV2_ROUTE_DIST + idx
                    dist = _int(oid, dists[idx], "Unsigned32/Gauge32")
                    _implausible(oid, dist, self.limits.hops(dist))
                cost = 0
                if idx in metrics:   # the sum of `dist` link metrics, each 1..MAXIMUM_METRIC
                    oid = OLSRV2_ROUTE_METRIC + idx
                    cost = _int(oid, metrics[idx], "Unsigned32/Gauge32")
                    low, high = max(dist, 1), max(dist, 1) * MAXIMUM_METRIC
                    _implausible(oid, cost, None if low <= cost <= high else
                                 f"a path metric outside {low}..{high} (its {max(dist, 1)} link metric(s) "
                                 f"of 1..{MAXIMUM_METRIC} each)")
            except SourceError as err:
                self._drop(view, ROUTES, oid, err)
                continue
            view.routes.append(Route(destination=self._destination(view, dest, prefix),
                                     next_hop=self._name(view, hop), hops=dist, cost=cost / METRIC_UNIT))

    def _destination(self, view: NetView, address: str, prefix: int) -> str:
        host = prefix == ipaddress.ip_address(address).max_prefixlen
        return self._name(view, address) if host else f"{address}/{prefix}"

    def _decode_cidr_routes(self, view: NetView, cols: Columns) -> None:
        types, metrics, status = cols[INET_CIDR_TYPE], cols[INET_CIDR_METRIC1], cols[INET_CIDR_STATUS]
        for idx, val in sorted(types.items()):
            oid = INET_CIDR_TYPE + idx
            try:
                dest, at = _inet_index(oid, idx, 0)
                if len(idx) < at + 2 or len(idx) < at + 2 + idx[at + 1]:
                    raise SourceError(f"{label(oid)}: index too short for a prefix length and a policy")
                prefix, policy_len = idx[at], idx[at + 1]
                next_hop, end = _inet_index(oid, idx, at + 2 + policy_len)
                if end != len(idx) or not dest:
                    raise SourceError(f"{label(oid)}: malformed inetCidrRouteTable index")
                if prefix > ipaddress.ip_address(dest).max_prefixlen:
                    raise SourceError(f"{label(oid)}: prefix length {prefix} is too long for {dest}")
                kind = _int(oid, val)
                if idx in status:
                    oid = INET_CIDR_STATUS + idx
                    active = _int(oid, status[idx]) == 1
                else:
                    active = True
                oid = INET_CIDR_METRIC1 + idx
                cost = _int(oid, metrics[idx]) if idx in metrics else 0
            except SourceError as err:
                self._drop(view, ROUTES, oid, err)
                continue
            if kind not in (1, 3, 4) or not active:
                continue  # reject, blackhole, or a row that is not active: not a path
            destination = self._destination(view, dest, prefix)
            if kind == 3:  # local: the next hop is the destination (a host) or the link itself
                hop = destination if "/" not in destination else ""
            else:
                hop = self._name(view, next_hop) if next_hop else ""
            view.routes.append(Route(destination=destination, next_hop=hop, hops=1 if kind == 3 else 0,
                                     cost=float(cost)))


class SnmpSource:
    """A `NetworkSource` speaking SNMPv2c, or SNMPv3 as `usm`, to one node's network subsystem (any
    standard agent)."""

    def __init__(self, host: str, port: int, community: str = "public", timeout: float = 0.5,
                 retries: int = 0, max_repetitions: int = 100, cache_seconds: float = 5.0,
                 write_community: str | None = None, modules: frozenset[str] | None = None,
                 limits: Limits | None = None, usm: UsmUser | None = None,
                 clock: Callable[[], float] = monotonic) -> None:
        self.host, self.port = host, port
        self.clock = clock  # how old a cached walk is
        self.limits = limits or Limits()
        self.modules = modules   # the PROBES modules to use; None: every one the agent serves
        self.community = community
        self.write_community = write_community
        self.timeout, self.retries = timeout, retries
        self.max_repetitions = max_repetitions
        self._link: _Link | None = None
        self._v3 = V3Session(host, port, usm, timeout, retries) if usm is not None else None
        self._request_id = int.from_bytes(os.urandom(3), "big")
        self._rows: dict[tuple[OID, ...], int] = {}  # rows seen by the last walk of a column set
        self.cache_seconds = cache_seconds
        self._cache = WalkCache()
        self._uptime: int | None = None  # the agent's sysUpTime in its last answer (a restart resets it)
        self._ident: dict[OID, Value] | None = None  # the identity scalars of the last read (`_standing_identity`)
        self.decoder = SnmpDecoder(self.where, self.limits)
        self.requests = 0

    @property
    def where(self) -> str:
        """`host:port` of the agent."""
        return f"{self.host}:{self.port}"

    async def _open(self) -> _Link:
        link = self._link
        if link is None or link.transport is None or link.transport.is_closing():
            loop = asyncio.get_running_loop()
            try:
                _, link = await loop.create_datagram_endpoint(_Link, remote_addr=(self.host, self.port))
            except OSError as err:
                raise SourceError(f"SNMP agent {self.where}: cannot resolve or reach: {err}") from None
            self._link = link
        return link

    async def _request(self, what: str, pdu: int, varbinds: list[tuple[OID, Value]], *, write: bool = False,
                       max_repetitions: int = 0) -> list[tuple[OID, Value]]:
        """Send one request (again after each timeout, `retries` times) and return the answer's varbinds."""
        if self._v3 is not None:
            self.requests += 1
            return self._checked(what, await self._v3.request(what, pdu, varbinds, max_repetitions))
        link = await self._open()
        community = self.write_community if write and self.write_community else self.community
        self._request_id = self._request_id % 0x7FFFFFFF + 1
        rid = self._request_id
        message = ber.encode_request(pdu, community.encode(), rid, varbinds, 0, max_repetitions)
        answer: asyncio.Future[ber.Response] = asyncio.get_running_loop().create_future()
        link.waiting[rid] = answer
        self.requests += 1
        try:
            for _ in range(self.retries + 1):
                if link.transport is None:
                    break
                link.transport.sendto(message)
                try:
                    got = await asyncio.wait_for(asyncio.shield(answer), self.timeout)
                    break
                except TimeoutError:
                    continue
            else:
                got = None
        finally:
            link.waiting.pop(rid, None)
        if got is None:
            why = f"; {link.malformed} malformed answer(s), the last: {link.last_error}" if link.malformed else ""
            raise SourceError(f"SNMP {what} to {self.where}: no SNMP response received before timeout "
                              f"(timeout {self.timeout:g} s, {self.retries} retr{'y' if self.retries == 1 else 'ies'})"
                              f"{why}")
        return self._checked(what, got)

    def _checked(self, what: str, got: ber.Response) -> list[tuple[OID, Value]]:
        """The answer's varbinds; SourceError naming the error status and the varbind it points at."""
        if got.error_status:
            status = (ber.ERROR_STATUS[got.error_status] if 0 <= got.error_status < len(ber.ERROR_STATUS)
                      else f"error-status {got.error_status}")
            where = ""
            i = got.error_index
            if 0 < i <= len(got.varbinds):
                where = f" at {label(got.varbinds[i - 1][0])}"
            v3 = "v3" if self._v3 is not None else ""
            raise SourceError(f"SNMP{v3} {what} to {self.where}: agent answered {status}{where}")
        return got.varbinds

    async def get(self, oids: Iterable[OID],
                  optional: frozenset[OID] = frozenset()) -> dict[OID, Value]:
        """GET scalars; a missing one raises SourceError unless it is `optional` (then absent)."""
        oids = list(oids)
        binds = await self._request("GET", ber.GET, [(o, _NULL) for o in oids])
        out = {}
        for key, val in binds:
            if val.tag in ber.EXCEPTIONS:
                if key in optional:
                    continue
                raise SourceError(f"SNMP GET to {self.where}: {label(key)} not served "
                                  f"({val.type_name})")
            out[key] = val
        missing = [o for o in oids if o not in out and o not in optional]
        if missing:  # an answer about other objects than asked: a broken or hostile agent
            raise SourceError(f"SNMP GET to {self.where}: the answer lacks {label(missing[0])} "
                              f"(it named {', '.join(label(k) for k in out) or 'nothing'})")
        return out

    async def walk(self, columns: list[OID]) -> Columns:
        """Walk table columns together: {column: {index: value}}."""
        result: Columns = {c: {} for c in columns}
        cursors: dict[OID, OID] = {c: c for c in columns}
        key_set = tuple(columns)
        # ask for one row more than last time: steady-state walks take one round trip
        reps = min(self.max_repetitions, self._rows.get(key_set, 8) + 1)
        for _ in range(1000):  # bounded: a looping agent cannot hold the thread forever
            pending = list(cursors)
            if not pending:
                break
            binds = await self._request("GETBULK", ber.GET_BULK, [(cursors[c], _NULL) for c in pending],
                                        max_repetitions=reps)
            if not binds:
                break
            for n, (oid, val) in enumerate(binds):
                col = pending[n % len(pending)]
                if col not in cursors:
                    continue
                key = tuple(oid)
                if val.tag in ber.EXCEPTIONS or key[: len(col)] != col:
                    del cursors[col]
                    continue
                if key <= cursors[col]:
                    raise SourceError(f"SNMP GETBULK to {self.where}: OID not increasing at "
                                      f"{label(key)}")
                result[col][key[len(col):]] = val
                cursors[col] = key
            reps = self.max_repetitions
        self._rows[key_set] = max((len(v) for v in result.values()), default=0)
        return result

    # -- reading --------------------------------------------------------------------------

    async def read(self, parts: frozenset[str]) -> NetView:
        """Read the requested parts from whichever served modules provide them."""
        steady, current = await self._steady(parts)
        if steady is not None:
            return steady
        ident = self._standing_identity(current)
        if ident is None:
            scalars = [SYS_NAME, ERNI_NODE_NAME, ERNI_NODE_ADDRESS, OLSRV2_ORIG_ADDR_TYPE, OLSRV2_ORIG_ADDR,
                       *PROBES.values(), *VERSIONS]
            ident = await self.get(dict.fromkeys([*scalars, SYS_UP_TIME]), frozenset([*scalars, SYS_UP_TIME]))
        self._ident = ident
        served = {module for module, oid in PROBES.items()
                  if oid in ident and (self.modules is None or module in self.modules)}
        view = self.decoder.identity(ident, served)
        topo_v, state_v = (_int(oid, ident[oid], "Counter32") if oid in ident and "ERNI-MOBINET-MIB" in served
                           else None for oid in VERSIONS)
        stamp = ViewStamp(view.node, topo_v, state_v, parts)
        self._restarted(ident)  # after the identity, whose errors come first
        now = self.clock()
        last = self._cache.view
        if (stamp.complete and last is not None and last.stamp.parts == parts
                and last.stamp.stands(view.node, topo_v, state_v) and self._fresh(last.when, now)):
            return self._copy(last.view)  # nothing changed: the last decoded view stands
        got, oldest = await self._walked(self.decoder.jobs(parts, served, view), stamp, now)
        self.decoder.decode(view, parts, served, got)
        self._cache.view = CachedView(stamp, oldest, view)
        return view

    async def _steady(self, parts: frozenset[str]) -> tuple[NetView | None, dict[OID, Value] | None]:
        """The last view, when the node's name and its change counters alone say it stands (the steady
        state), unless the agent restarted (sysUpTime went back: its counters began anew); else None,
        with the name, counters and sysUpTime the check read (None when it read nothing)."""
        last = self._cache.view
        if last is None or not last.stamp.complete or last.stamp.parts != parts \
                or not self._fresh(last.when, self.clock()):
            return None, None
        check = [ERNI_NODE_NAME, *VERSIONS]
        current = await self.get([*check, SYS_UP_TIME], frozenset([*check, SYS_UP_TIME]))
        if not all(oid in current for oid in check):
            return None, None
        topo_v, state_v = (_int(oid, current[oid], "Counter32") for oid in VERSIONS)
        if last.stamp.stands(_text(ERNI_NODE_NAME, current[ERNI_NODE_NAME]), topo_v, state_v) \
                and not self._restarted(current):
            return self._copy(last.view), None
        return None, current

    def _standing_identity(self, current: dict[OID, Value] | None) -> dict[OID, Value] | None:
        """The identity scalars of the last read with the steady check's new readings in, when that
        check says only the state moved (the same node and topology version, no restart: robots
        moved); else None (read them again). A walking robot's reads then skip one GET each."""
        last = self._ident
        if current is None or last is None or SYS_UP_TIME not in current or SYS_UP_TIME not in last \
                or any(oid not in last for oid in (ERNI_NODE_NAME, VERSIONS[0])):
            return None
        same = (current[ERNI_NODE_NAME] == last[ERNI_NODE_NAME] and current[VERSIONS[0]] == last[VERSIONS[0]]
                and _int(SYS_UP_TIME, current[SYS_UP_TIME], "TimeTicks") >= _int(SYS_UP_TIME, last[SYS_UP_TIME],
                                                                               "TimeTicks"))
        return {**last, **current} if same else None

    def _fresh(self, when: float, now: float) -> bool:
        """Whether something read at `when` may still be used at `now` (younger than `cache_seconds`)."""
        return now - when < self.cache_seconds

    async def _walked(self, jobs: dict[str, list[OID]], stamp: ViewStamp,
                      now: float) -> tuple[dict[str, Columns], float]:
        """The columns of each job: cached while its change counter and columns stand and the walk is
        fresh, else walked now (all at once); with the time of the oldest walk among them."""
        got: dict[str, Columns] = {}
        walks: dict[str, WalkKey] = {}
        oldest = now  # the view is as old as the oldest walk it is made of
        for job, cols in jobs.items():
            follows_state = job == POSITIONS or (job == "nodes" and POSITIONS in stamp.parts)
            key = WalkKey(stamp.node, stamp.state if follows_state else stamp.topology, tuple(cols))
            entry = self._cache.walks.get(job)
            if key.version is not None and entry is not None and entry.key == key and self._fresh(entry.when, now):
                got[job] = entry.columns
                oldest = min(oldest, entry.when)
            else:
                walks[job] = key
        # the node table and the position table have a row per node: walked together, one request
        # a round (robots move: both are walked at every position report)
        groups = [[job] for job in walks if job not in ("nodes", POSITIONS)]
        together = [job for job in ("nodes", POSITIONS) if job in walks]
        if together:
            groups.append(together)
        done = await asyncio.gather(*(self.walk([c for job in group for c in jobs[job]]) for group in groups),
                                    return_exceptions=True)
        for group, value in zip(groups, done):
            if isinstance(value, BaseException):
                if isinstance(value, SourceError):
                    raise value
                raise SourceError(f"SNMP agent {self.where}: {type(value).__name__}: {value}") from value
            for job in group:
                columns = {c: value[c] for c in jobs[job]}
                got[job] = columns
                self._cache.walks[job] = CachedWalk(walks[job], now, columns)
        return got, oldest

    def _restarted(self, values: dict[OID, Value]) -> bool:
        """Whether the agent restarted since the last answer (its sysUpTime went back); then every
        cached walk and view is dropped, for its change counters count from zero again."""
        value = values.get(SYS_UP_TIME)
        if value is None:
            return False  # not served: the change counters and the cache's age alone decide
        up = _int(SYS_UP_TIME, value, "TimeTicks")
        restarted = self._uptime is not None and up < self._uptime
        self._uptime = up
        if restarted:
            self._cache.clear()
            self.decoder.forget()
        return restarted

    @staticmethod
    def _copy(view: NetView) -> NetView:
        return NetView(node=view.node, address=view.address, names=dict(view.names),
                       neighbors=list(view.neighbors), links=list(view.links), routes=list(view.routes),
                       positions=dict(view.positions), sources=dict(view.sources), missing=dict(view.missing),
                       dropped=list(view.dropped))

    async def write_position(self, position: Position) -> None:
        """SET the node's position scalars (mm, mm, centidegrees) in one request (write community)."""
        if not self.write_community and self._v3 is None:
            raise SourceError(f"SNMP SET to {self.where}: no write community configured "
                              "(MobiNet setting write_community)")
        heading = ((position.heading + 180.0) % 360.0) - 180.0
        values = [(ERNI_POS_X, round(position.x * 1000)), (ERNI_POS_Y, round(position.y * 1000)),
                  (ERNI_POS_HEADING, round(heading * 100))]
        for oid, v in values:
            if not -(2**31) <= v < 2**31:
                raise SourceError(f"{label(oid)}: {v} does not fit an Integer32 (position too far)")
        await self._request("SET", ber.SET, [(o, Value(ber.INTEGER, v)) for o, v in values], write=True)

    async def aclose(self) -> None:
        """Close the socket; requests still waiting time out."""
        if self._v3 is not None:
            await self._v3.aclose()
        link, self._link = self._link, None
        if link is not None and link.transport is not None:
            link.transport.close()


def articulation_points(links: Iterable[Link]) -> list[str]:
    """Cut vertices of the topology given by `links`, sorted."""
    return sorted(netgraph.articulation_points(netgraph.from_edges((l.a, l.b) for l in links)))
