"""`SnmpSource`: the network subsystem read and written over SNMPv2c (pysnmp 7 asyncio API).

Each part of a view is one table walk done with GETBULK over all the part's columns at
once (several round trips only for large tables); the parts of one read run concurrently.
When the agent serves the ERNI change counters (erniTopologyVersion, erniStateVersion), a
part whose counter has not moved is answered from the last walk (for at most
`cache_seconds`), so a steady network costs one GET per read.
Every value is type-checked: a missing answer, an error status, a wrong type or a
malformed value raises `SourceError` naming the OID and what was expected.
"""

from __future__ import annotations

import asyncio
import ipaddress
import math
import time
from collections.abc import Iterable
from typing import Any, cast

from pyasn1.type import univ
from pysnmp.hlapi.v3arch.asyncio import (
    CommunityData,
    ContextData,
    ObjectIdentity,
    ObjectType,
    SnmpEngine,
    UdpTransportTarget,
    bulk_cmd,
    get_cmd,
    set_cmd,
)
from pysnmp.proto import rfc1902, rfc1905

from erni import netgraph
from erni.blackboard import Link, Neighbor, Position, Route
from erni.plugins.mobinet.resource import (
    NEIGHBORS,
    POSITIONS,
    ROUTES,
    TOPOLOGY,
    NetView,
    SourceError,
)

# --- the OIDs read and written (numeric: pysnmp ships none of these MIBs) -------------
# ERNI units: positions in mm, headings in centidegrees, link quality in thousandths;
# OLSRv2 link metrics are ETX scaled by METRIC_UNIT (a loss-free link costs 1024).

OID = tuple[int, ...]

METRIC_UNIT = 1024

NHDP = (1, 3, 6, 1, 2, 1, 213, 1)
NHDP_DISC_IF_ADDR = NHDP + (2, 3, 1, 4)          # .<nbr>  OCTET STRING (4): neighbour address
NHDP_NIB_SYMMETRIC = NHDP + (2, 6, 1, 1)         # .<nbr>  TruthValue: symmetric neighbour
NHDP_PERF_RECVD = NHDP + (3, 2, 1, 1)            # .<nbr>  Counter32: HELLOs received
NHDP_PERF_EXPECTED = NHDP + (3, 2, 1, 2)         # .<nbr>  Counter32: HELLOs expected
OLSRV2 = (1, 3, 6, 1, 2, 1, 219, 1)
OLSRV2_LINK_IN_METRIC = OLSRV2 + (2, 1, 1, 1)    # .<ifIndex>.<nbr>  Unsigned32
OLSRV2_TOPO_FROM = OLSRV2 + (2, 8, 1, 2)         # .<from>.<to>  OCTET STRING (4)
OLSRV2_TOPO_TO = OLSRV2 + (2, 8, 1, 4)           # .<from>.<to>  OCTET STRING (4)
OLSRV2_TOPO_METRIC = OLSRV2 + (2, 8, 1, 6)       # .<from>.<to>  Unsigned32
OLSRV2_ROUTE_NEXT_HOP = OLSRV2 + (2, 11, 1, 5)   # .1.4.<a.b.c.d>.32  OCTET STRING (4)
OLSRV2_ROUTE_DIST = OLSRV2 + (2, 11, 1, 8)       # .1.4.<a.b.c.d>.32  Unsigned32 hops
OLSRV2_ROUTE_METRIC = OLSRV2 + (2, 11, 1, 9)     # .1.4.<a.b.c.d>.32  Unsigned32 path cost
INET_CIDR_METRIC1 = (1, 3, 6, 1, 2, 1, 4, 24, 7, 1, 12)  # Integer32 path cost (fallback)

ERNI = (1, 3, 6, 1, 4, 1, 32473, 1)
ERNI_NODE_NAME = ERNI + (1, 1, 0)                # OCTET STRING
ERNI_NODE_ADDRESS = ERNI + (1, 3, 0)             # IpAddress
ERNI_POS_X = ERNI + (1, 4, 0)                    # Integer32 mm, read-write
ERNI_POS_Y = ERNI + (1, 5, 0)                    # Integer32 mm, read-write
ERNI_POS_HEADING = ERNI + (1, 6, 0)              # Integer32 centidegrees, read-write
ERNI_TOPOLOGY_VERSION = ERNI + (1, 9, 0)         # Counter32: changes when links/routes may have
ERNI_STATE_VERSION = ERNI + (1, 10, 0)           # Counter32: changes when anything may have
ERNI_NODES_NAME = ERNI + (2, 1, 2)               # .<node>  OCTET STRING
ERNI_NODES_ADDRESS = ERNI + (2, 1, 3)            # .<node>  IpAddress
ERNI_NODES_X = ERNI + (2, 1, 4)                  # .<node>  Integer32 mm
ERNI_NODES_Y = ERNI + (2, 1, 5)                  # .<node>  Integer32 mm
ERNI_NODES_HEADING = ERNI + (2, 1, 6)            # .<node>  Integer32 centidegrees
ERNI_LINK_QUALITY = ERNI + (3, 1, 3)             # .<nbr>  Gauge32 thousandths

NAMES: dict[OID, str] = {
    NHDP_DISC_IF_ADDR: "nhdpDiscIfSetIpAddr", NHDP_NIB_SYMMETRIC: "nhdpNibNeighborSetSymmetric",
    NHDP_PERF_RECVD: "nhdpDiscIfRecvdPackets", NHDP_PERF_EXPECTED: "nhdpDiscIfExpectedPackets",
    OLSRV2_LINK_IN_METRIC: "olsrv2IibLinkSetInMetric", OLSRV2_TOPO_FROM: "olsrv2TibRouterTopologySetFromOrigAddr",
    OLSRV2_TOPO_TO: "olsrv2TibRouterTopologySetToOrigAddr",
    OLSRV2_TOPO_METRIC: "olsrv2TibRouterTopologySetMetricValue",
    OLSRV2_ROUTE_NEXT_HOP: "olsrv2TibRoutingSetNextIfAddr", OLSRV2_ROUTE_DIST: "olsrv2TibRoutingSetDist",
    OLSRV2_ROUTE_METRIC: "olsrv2TibRoutingSetMetricValue", INET_CIDR_METRIC1: "inetCidrRouteMetric1",
    ERNI_NODE_NAME: "erniNodeName", ERNI_NODE_ADDRESS: "erniNodeAddress", ERNI_POS_X: "erniPosX",
    ERNI_POS_Y: "erniPosY", ERNI_POS_HEADING: "erniPosHeading",
    ERNI_TOPOLOGY_VERSION: "erniTopologyVersion", ERNI_STATE_VERSION: "erniStateVersion", ERNI_NODES_NAME: "erniNodesName",
    ERNI_NODES_ADDRESS: "erniNodesAddress", ERNI_NODES_X: "erniNodesX", ERNI_NODES_Y: "erniNodesY",
    ERNI_NODES_HEADING: "erniNodesHeading", ERNI_LINK_QUALITY: "erniLinkQuality",
}


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


# --- typed decoding -------------------------------------------------------------------

_INT = univ.Integer.tagSet
_STR = univ.OctetString.tagSet
_TYPES = {
    "Integer32": (_INT,),
    "OCTET STRING": (_STR,),
    "IpAddress": (rfc1902.IpAddress.tagSet,),
    "Unsigned32/Gauge32": (rfc1902.Unsigned32.tagSet, rfc1902.Gauge32.tagSet),
    "Counter32": (rfc1902.Counter32.tagSet,),
}
_EXCEPTIONS = (rfc1905.NoSuchObject.tagSet, rfc1905.NoSuchInstance.tagSet,
               rfc1905.EndOfMibView.tagSet)


def _typed(oid: OID, value: Any, expected: str) -> Any:
    if value.tagSet not in _TYPES[expected]:
        shown = value.prettyPrint() if hasattr(value, "prettyPrint") else repr(value)
        raise SourceError(f"{label(oid)} ({dotted(oid)}): expected {expected}, got "
                          f"{type(value).__name__} {shown[:40]!r}")
    return value


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


def _inet(oid: OID, value: Any) -> str:
    raw = bytes(_typed(oid, value, "OCTET STRING"))
    if len(raw) != 4:
        raise SourceError(f"{label(oid)}: expected a 4-byte IPv4 InetAddress, got "
                          f"{len(raw)} byte(s)")
    return str(ipaddress.IPv4Address(raw))


def _quality_of_metric(metric: int) -> float:
    return min(1.0, math.sqrt(METRIC_UNIT / metric)) if metric > 0 else 1.0


class SnmpSource:
    """A `NetworkSource` speaking SNMPv2c to one node's network subsystem."""

    def __init__(self, host: str, port: int, community: str = "public", timeout: float = 0.5,
                 retries: int = 0, max_repetitions: int = 100, cache_seconds: float = 5.0) -> None:
        self.host, self.port = host, port
        self.community = community
        self.timeout, self.retries = timeout, retries
        self.max_repetitions = max_repetitions
        self._engine: SnmpEngine | None = None
        self._target: UdpTransportTarget | None = None
        self._rows: dict[tuple[OID, ...], int] = {}  # rows seen by the last walk of a column set
        self.cache_seconds = cache_seconds
        self._cache: dict[str, tuple[Any, float, Any]] = {}  # job -> (key, when, walked columns)
        self.requests = 0

    @property
    def where(self) -> str:
        """`host:port` of the agent."""
        return f"{self.host}:{self.port}"

    async def _session(self) -> tuple[SnmpEngine, UdpTransportTarget]:
        if self._engine is None:
            self._engine = SnmpEngine()  # created inside the running loop, as pysnmp requires
        if self._target is None:
            try:
                self._target = await UdpTransportTarget.create(
                    (self.host, self.port), timeout=self.timeout, retries=self.retries)
            except Exception as err:
                raise SourceError(f"SNMP agent {self.where}: cannot resolve: {err}") from None
        return self._engine, self._target

    def _auth(self) -> CommunityData:
        return CommunityData(self.community, mpModel=1)

    def _check(self, what: str, err_ind: Any, err_stat: Any, err_idx: Any, binds: Any) -> None:
        if err_ind:
            raise SourceError(f"SNMP {what} to {self.where}: {err_ind} (timeout {self.timeout:g} s, "
                              f"{self.retries} retr{'y' if self.retries == 1 else 'ies'})")
        if int(err_stat):
            where = ""
            i = int(err_idx)
            if 0 < i <= len(binds):
                where = f" at {label(tuple(binds[i - 1][0]))}"
            raise SourceError(f"SNMP {what} to {self.where}: agent answered "
                              f"{err_stat.prettyPrint()}{where}")

    async def get(self, oids: Iterable[OID],
                  optional: frozenset[OID] = frozenset()) -> dict[OID, Any]:
        """GET scalars; a missing one raises SourceError unless it is `optional` (then absent)."""
        engine, target = await self._session()
        oids = list(oids)
        self.requests += 1
        res = await get_cmd(engine, self._auth(), target, ContextData(),
                            *(ObjectType(ObjectIdentity(dotted(o))) for o in oids),
                            lookupMib=False)
        self._check("GET", *res)
        out = {}
        for oid, val in res[3]:
            key = tuple(oid)
            if val.tagSet in _EXCEPTIONS:
                if key in optional:
                    continue
                raise SourceError(f"SNMP GET to {self.where}: {label(key)} not served "
                                  f"({type(val).__name__})")
            out[key] = val
        missing = [o for o in oids if o not in out and o not in optional]
        if missing:  # an answer about other objects than asked: a broken or hostile agent
            raise SourceError(f"SNMP GET to {self.where}: the answer lacks {label(missing[0])} "
                              f"(it named {', '.join(label(k) for k in out) or 'nothing'})")
        return out

    async def walk(self, columns: list[OID]) -> dict[OID, dict[OID, Any]]:
        """Walk table columns together: {column: {index: value}}."""
        engine, target = await self._session()
        result: dict[OID, dict[OID, Any]] = {c: {} for c in columns}
        cursors: dict[OID, OID] = {c: c for c in columns}
        key_set = tuple(columns)
        # ask for one row more than last time: steady-state walks take one round trip
        reps = min(self.max_repetitions, self._rows.get(key_set, 8) + 1)
        for _ in range(1000):  # bounded: a looping agent cannot hold the thread forever
            pending = list(cursors)
            if not pending:
                break
            self.requests += 1
            res = await bulk_cmd(engine, self._auth(), target, ContextData(), 0, reps,
                                 *(ObjectType(ObjectIdentity(dotted(cursors[c]))) for c in pending),
                                 lookupMib=False)
            self._check("GETBULK", *res)
            binds = res[3]
            if not binds:
                break
            for n, (oid, val) in enumerate(binds):
                col = pending[n % len(pending)]
                if col not in cursors:
                    continue
                key = tuple(oid)
                if val.tagSet in _EXCEPTIONS or key[: len(col)] != col:
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

    async def read(self, parts: frozenset[str]) -> NetView:
        """Read the requested parts (plus the node's identity and the node table)."""
        versions = frozenset({ERNI_TOPOLOGY_VERSION, ERNI_STATE_VERSION})
        ident = await self.get([ERNI_NODE_NAME, ERNI_NODE_ADDRESS, *versions], versions)
        view = NetView(node=_text(ERNI_NODE_NAME, ident[ERNI_NODE_NAME]),
                       address=_ip(ERNI_NODE_ADDRESS, ident[ERNI_NODE_ADDRESS]))
        topo_v, state_v = (
            _int(oid, ident[oid], "Counter32") if oid in ident else None
            for oid in (ERNI_TOPOLOGY_VERSION, ERNI_STATE_VERSION))
        node_cols: list[OID] = [ERNI_NODES_NAME, ERNI_NODES_ADDRESS]
        if POSITIONS in parts:
            node_cols += [ERNI_NODES_X, ERNI_NODES_Y, ERNI_NODES_HEADING]
        wanted: dict[str, tuple[list[OID], int | None]] = {
            "nodes" + ("+positions" if POSITIONS in parts else ""): (node_cols, state_v)}
        if NEIGHBORS in parts:
            wanted[NEIGHBORS] = ([NHDP_DISC_IF_ADDR, NHDP_NIB_SYMMETRIC,
                                  OLSRV2_LINK_IN_METRIC, ERNI_LINK_QUALITY,
                                  NHDP_PERF_RECVD, NHDP_PERF_EXPECTED], topo_v)
        if TOPOLOGY in parts:
            # the index is (from router, to router): the node table names them, so only the
            # metric column is walked (the address columns only for routers it does not list)
            wanted[TOPOLOGY] = ([OLSRV2_TOPO_METRIC], topo_v)
        if ROUTES in parts:
            wanted[ROUTES] = ([OLSRV2_ROUTE_NEXT_HOP, OLSRV2_ROUTE_DIST,
                               OLSRV2_ROUTE_METRIC], topo_v)
        now = time.monotonic()
        whole = ("view", view.node, topo_v, state_v, parts)
        entry = self._cache.get("view")
        if (None not in whole and entry is not None and entry[0] == whole
                and now - entry[1] < self.cache_seconds):
            return cast(NetView, entry[2])  # nothing changed: the last decoded view stands
        got: dict[str, Any] = {}
        walks: dict[str, Any] = {}
        oldest = now  # the view is as old as the oldest walk it is made of
        for job, (cols, version) in wanted.items():
            entry = self._cache.get(job)
            key = (view.node, version)
            if (version is not None and entry is not None and entry[0] == key
                    and now - entry[1] < self.cache_seconds):
                got[job] = entry[2]
                oldest = min(oldest, entry[1])
            else:
                walks[job] = self.walk(cols)
        done = await asyncio.gather(*walks.values(), return_exceptions=True)
        for value in done:
            if isinstance(value, BaseException):
                if isinstance(value, SourceError):
                    raise value
                raise SourceError(f"SNMP agent {self.where}: {type(value).__name__}: {value}") from value
        for job, walked in zip(walks, done):
            got[job] = walked
            self._cache[job] = ((view.node, wanted[job][1]), now, cols)
        by_index = self._decode_nodes(view, got[next(iter(wanted))], POSITIONS in parts)
        if NEIGHBORS in parts:
            self._decode_neighbors(view, got[NEIGHBORS])
        if TOPOLOGY in parts:
            metrics = got[TOPOLOGY][OLSRV2_TOPO_METRIC]
            if any(len(i) != 2 or i[:1] not in by_index or i[1:] not in by_index for i in metrics):
                ends = await self.walk([OLSRV2_TOPO_FROM, OLSRV2_TOPO_TO])
                self._decode_topology(view, {**ends, OLSRV2_TOPO_METRIC: metrics})
            else:
                self._decode_topology_by_index(view, metrics, by_index)
        if ROUTES in parts:
            self._decode_routes(view, got[ROUTES])
        self._cache["view"] = (whole, oldest, view)
        return view

    async def write_position(self, position: Position) -> None:
        """SET the node's position scalars (mm, mm, centidegrees) in one request."""
        engine, target = await self._session()
        heading = ((position.heading + 180.0) % 360.0) - 180.0
        values = [(ERNI_POS_X, round(position.x * 1000)), (ERNI_POS_Y, round(position.y * 1000)),
                  (ERNI_POS_HEADING, round(heading * 100))]
        for oid, v in values:
            if not -(2**31) <= v < 2**31:
                raise SourceError(f"{label(oid)}: {v} does not fit an Integer32 (position too far)")
        self.requests += 1
        res = await set_cmd(engine, self._auth(), target, ContextData(),
                            *(ObjectType(ObjectIdentity(dotted(o)), rfc1902.Integer32(v))
                              for o, v in values), lookupMib=False)
        self._check("SET", *res)

    async def aclose(self) -> None:
        """Close the engine's transport."""
        if self._engine is not None:
            self._engine.close_dispatcher()
            self._engine = None

    # -- decoding -------------------------------------------------------------------------

    def _name(self, view: NetView, address: str) -> str:
        return view.names.get(address, address)

    def _decode_nodes(self, view: NetView, cols: dict[OID, dict[OID, Any]],
                      positions: bool) -> dict[OID, str]:
        names = cols[ERNI_NODES_NAME]
        by_index: dict[OID, str] = {}
        for idx, val in names.items():
            by_index[idx] = _text(ERNI_NODES_NAME + idx, val)
        for idx, val in cols[ERNI_NODES_ADDRESS].items():
            addr = _ip(ERNI_NODES_ADDRESS + idx, val)
            if idx in by_index:
                view.names[addr] = by_index[idx]
        view.names.setdefault(view.address, view.node)
        if not positions:
            return by_index
        xs, ys, hs = (cols[ERNI_NODES_X], cols[ERNI_NODES_Y], cols[ERNI_NODES_HEADING])
        for idx, name in by_index.items():
            if idx not in xs or idx not in ys:
                continue  # position not known to this node
            x = _int(ERNI_NODES_X + idx, xs[idx]) / 1000.0
            y = _int(ERNI_NODES_Y + idx, ys[idx]) / 1000.0
            h = _int(ERNI_NODES_HEADING + idx, hs[idx]) / 100.0 if idx in hs else 0.0
            view.positions[name] = Position(x=x, y=y, heading=h)
        return by_index

    def _decode_neighbors(self, view: NetView, cols: dict[OID, dict[OID, Any]]) -> None:
        sym = cols[NHDP_NIB_SYMMETRIC]
        metric = {idx[-1:]: v for idx, v in cols[OLSRV2_LINK_IN_METRIC].items()}
        quality = cols[ERNI_LINK_QUALITY]
        recvd, expected = cols[NHDP_PERF_RECVD], cols[NHDP_PERF_EXPECTED]
        for idx, val in sorted(cols[NHDP_DISC_IF_ADDR].items()):
            addr = _inet(NHDP_DISC_IF_ADDR + idx, val)
            truth = _int(NHDP_NIB_SYMMETRIC + idx, sym[idx]) if idx in sym else 2
            if truth not in (1, 2):
                raise SourceError(f"{label(NHDP_NIB_SYMMETRIC + idx)}: expected TruthValue "
                                  f"1 or 2, got {truth}")
            if idx in quality:
                q = _int(ERNI_LINK_QUALITY + idx, quality[idx], "Unsigned32/Gauge32") / 1000.0
            elif idx in recvd and idx in expected:
                exp = _int(NHDP_PERF_EXPECTED + idx, expected[idx], "Counter32")
                got = _int(NHDP_PERF_RECVD + idx, recvd[idx], "Counter32")
                q = got / exp if exp else 0.0
            else:
                q = 0.0
            if not 0.0 <= q <= 1.0:
                raise SourceError(f"{label(ERNI_LINK_QUALITY + idx)}: expected 0..1000, "
                                  f"got {round(q * 1000)}")
            m = (_int(OLSRV2_LINK_IN_METRIC + (1,) + idx, metric[idx], "Unsigned32/Gauge32")
                 if idx in metric else None)
            view.neighbors.append(Neighbor(name=self._name(view, addr), address=addr, quality=q,
                                           symmetric=truth == 1, metric=m))

    def _decode_topology_by_index(self, view: NetView, metrics: dict[OID, Any],
                                  by_index: dict[OID, str]) -> None:
        seen: dict[frozenset[str], Link] = {}
        for idx, val in sorted(metrics.items()):
            a, b = by_index[idx[:1]], by_index[idx[1:]]
            m = _int(OLSRV2_TOPO_METRIC + idx, val, "Unsigned32/Gauge32")
            key = frozenset((a, b))
            if a != b and key not in seen:
                seen[key] = Link(a=min(a, b), b=max(a, b), quality=_quality_of_metric(m), metric=m)
        view.links = list(seen.values())

    def _decode_topology(self, view: NetView, cols: dict[OID, dict[OID, Any]]) -> None:
        froms, tos, metrics = (cols[OLSRV2_TOPO_FROM], cols[OLSRV2_TOPO_TO],
                               cols[OLSRV2_TOPO_METRIC])
        seen: dict[frozenset[str], Link] = {}
        for idx, val in sorted(froms.items()):
            if idx not in tos or idx not in metrics:
                continue
            a = self._name(view, _inet(OLSRV2_TOPO_FROM + idx, val))
            b = self._name(view, _inet(OLSRV2_TOPO_TO + idx, tos[idx]))
            m = _int(OLSRV2_TOPO_METRIC + idx, metrics[idx], "Unsigned32/Gauge32")
            key = frozenset((a, b))
            if a != b and key not in seen:
                seen[key] = Link(a=min(a, b), b=max(a, b), quality=_quality_of_metric(m), metric=m)
        view.links = list(seen.values())

    def _decode_routes(self, view: NetView, cols: dict[OID, dict[OID, Any]]) -> None:
        hops, dists, metrics = (cols[OLSRV2_ROUTE_NEXT_HOP], cols[OLSRV2_ROUTE_DIST],
                                cols[OLSRV2_ROUTE_METRIC])
        for idx, val in sorted(hops.items()):
            if len(idx) != 7 or idx[0] != 1 or idx[1] != 4 or max(idx[2:6]) > 255:
                raise SourceError(f"{label(OLSRV2_ROUTE_NEXT_HOP + idx)}: expected an "
                                  "index 1.4.a.b.c.d.prefixLen")
            dest = str(ipaddress.IPv4Address(bytes(idx[2:6])))
            hop = _inet(OLSRV2_ROUTE_NEXT_HOP + idx, val)
            dist = _int(OLSRV2_ROUTE_DIST + idx, dists[idx], "Unsigned32/Gauge32") if idx in dists else 0
            cost = (_int(OLSRV2_ROUTE_METRIC + idx, metrics[idx], "Unsigned32/Gauge32")
                    if idx in metrics else 0)
            view.routes.append(Route(destination=self._name(view, dest), next_hop=self._name(view, hop),
                                     hops=dist, cost=cost / METRIC_UNIT))


def articulation_points(links: Iterable[Link]) -> list[str]:
    """Cut vertices of the topology given by `links`, sorted."""
    return sorted(netgraph.articulation_points(netgraph.from_edges((l.a, l.b) for l in links)))
