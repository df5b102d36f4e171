"""`BabelSource`: the network subsystem read from babeld's local interface (Babel, RFC 8966).

babeld started with `-g PORT` (or `local-port PORT` in its configuration) accepts TCP
connections on [::1]:PORT; after a header (`BABEL 1.0`, `version`, `host`, `my-id`, `ok`)
the request `dump` answers one line per interface, neighbour, exported route (xroute) and
route, then `ok`. The source keeps one connection, asks for a dump on every read and builds
the parts from it:

- **neighbours**: one per `neighbour` line. babeld's costs on a link-quality (wireless)
  interface are rxcost = 256 / beta (beta: the share of this neighbour's Hellos received
  lately) and txcost = 256 / alpha (alpha: the share of our Hellos the neighbour received, as
  its IHU tells); its link cost is rxcost * txcost / 256 = 256 * ETX. The link quality
  reported is the delivery ratio sqrt(alpha * beta) = 256 / sqrt(rxcost * txcost), capped at 1
  (the same ETX-to-quality rule as the SNMP source's sqrt(1024 / metric)); a neighbour with
  an infinite cost (no IHU, or no Hello among the last twelve) has quality 0 and is not
  symmetric. `metric` is babeld's cost.
- **routes**: the installed (selected) routes: destination, next hop, cost = metric / 256 (a
  loss-free hop costs 1, as ETX); hops is 1 when the next hop is the destination, else 0:
  Babel carries no hop count.
- **topology**: Babel is distance-vector: no node knows the whole graph. The source reports
  what the daemon does know: this node's links (its neighbour table), and for every route a
  neighbour N advertises to a destination D, an edge N-D when N's advertised metric
  (refmetric) shows that N reaches D without passing through this node: N's path through us
  would cost at least cost(N) + our best metric to D not via N, and the edge is kept only when
  refmetric < `avoid_margin` times that. Such an edge may stand for several radio hops, so the
  graph answers whether *this* node is an articulation point (the network-aware stop's
  question), not whether others are. It errs on the side of caution: when the best routes
  between two neighbours both run through this node, a worse link around it that no route
  uses shows nowhere in the daemon's state, and the node is reported as a cut vertex.
- **positions**: Babel has none; listed in `missing`.

Rows babeld cannot have computed are dropped and recorded in `NetView.dropped` (`sanity`): a
neighbour with a finite link cost but an rxcost or txcost of 0 (its quality would read as a lost
link's), and an installed route whose metric is 0 or below the refmetric it was advertised with
(babeld's metric is refmetric + link cost). Qualities are computed within 0..1 and hops are
derived, so neither can be out of range here.

Addresses are named through `names` (address -> agent name, e.g. MobiNet's view of the team
directory); a neighbour's IPv4 address is the host prefix it originates (the route through it
with refmetric 0). Malformed lines raise `SourceError` naming the line; unknown line kinds
and unknown fields (newer babeld versions) are ignored.
"""

from __future__ import annotations

import asyncio
import ipaddress
import math
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field

from erni.blackboard import Link, Neighbor, Position, Route
from erni.plugins.mobinet.resource import (
    NEIGHBORS,
    POSITIONS,
    ROUTES,
    TOPOLOGY,
    NetView,
    SourceError,
)
from erni.plugins.mobinet.sanity import Absurd

INFINITY = 0xFFFF          # Babel's infinite metric
UNIT = 256                 # the cost of a loss-free hop on a link-quality interface
AVOID_MARGIN = 0.75


@dataclass(frozen=True)
class BabelInterface:
    """An `interface` line: a babel interface and its addresses."""

    name: str
    up: bool
    ipv6: str = ""
    ipv4: str = ""


@dataclass(frozen=True)
class BabelNeighbour:
    """A `neighbour` line."""

    id: str
    address: str           # link-local IPv6
    interface: str
    reach: int
    rxcost: int
    txcost: int
    cost: int


@dataclass(frozen=True)
class BabelRoute:
    """A `route` line: one neighbour's advertisement of a prefix, selected or not."""

    id: str
    prefix: str
    source: str
    installed: bool
    router_id: str
    metric: int
    refmetric: int
    via: str               # the neighbour's link-local address
    interface: str


@dataclass
class BabelDump:
    """Everything one `dump` said."""

    version: str = ""
    host: str = ""
    my_id: str = ""
    interfaces: list[BabelInterface] = field(default_factory=list)
    neighbours: list[BabelNeighbour] = field(default_factory=list)
    xroutes: list[tuple[str, int]] = field(default_factory=list)   # (prefix, metric) this node exports
    routes: list[BabelRoute] = field(default_factory=list)


def _fields(line: str, words: list[str], start: int) -> dict[str, str]:
    if (len(words) - start) % 2:
        raise SourceError(f"babeld: malformed line {line[:120]!r}: expected KEY VALUE pairs")
    return {words[i]: words[i + 1] for i in range(start, len(words), 2)}


def _number(line: str, values: dict[str, str], key: str, base: int = 10) -> int:
    if key not in values:
        raise SourceError(f"babeld: line {line[:120]!r} lacks {key!r}")
    try:
        value = int(values[key], base)
    except ValueError:
        raise SourceError(f"babeld: {key} {values[key][:20]!r} in {line[:80]!r}: expected a "
                          f"{'hexadecimal ' if base == 16 else ''}number") from None
    if not 0 <= value <= INFINITY:
        raise SourceError(f"babeld: {key} {value} in {line[:80]!r}: expected 0..{INFINITY}")
    return value


def _text(line: str, values: dict[str, str], key: str) -> str:
    if key not in values:
        raise SourceError(f"babeld: line {line[:120]!r} lacks {key!r}")
    return values[key]


def _flag(line: str, values: dict[str, str], key: str, yes: str, no: str) -> bool:
    word = _text(line, values, key)
    if word not in (yes, no):
        raise SourceError(f"babeld: {key} {word[:10]!r} in {line[:80]!r}: expected {yes} or {no}")
    return word == yes


def _address(line: str, text: str, what: str) -> str:
    try:
        return str(ipaddress.ip_address(text))
    except ValueError:
        raise SourceError(f"babeld: {what} {text[:50]!r} in {line[:80]!r}: expected an IP address") from None


def _prefix(line: str, text: str, what: str) -> str:
    try:
        return str(ipaddress.ip_network(text, strict=False))
    except ValueError:
        raise SourceError(f"babeld: {what} {text[:50]!r} in {line[:80]!r}: expected an IP prefix") from None


def parse_dump(lines: list[str]) -> BabelDump:
    """Parse the header and the `add ...` lines of a dump (SourceError on a malformed one)."""
    dump = BabelDump()
    for raw in lines:
        line = raw.strip()
        words = line.split()
        if not words:
            continue
        if words[0] in ("version", "host", "my-id") and len(words) == 2:
            setattr(dump, {"version": "version", "host": "host", "my-id": "my_id"}[words[0]], words[1])
            continue
        if words[0] != "add" or len(words) < 3:
            continue   # BABEL 1.0, ok, and what a newer babeld may add
        kind, ident = words[1], words[2]
        if kind == "interface":
            values = _fields(line, words, 3)
            dump.interfaces.append(BabelInterface(
                ident, _flag(line, values, "up", "true", "false"),
                _address(line, values["ipv6"], "ipv6") if "ipv6" in values else "",
                _address(line, values["ipv4"], "ipv4") if "ipv4" in values else ""))
        elif kind == "neighbour":
            values = _fields(line, words, 3)
            dump.neighbours.append(BabelNeighbour(
                ident, _address(line, _text(line, values, "address"), "address"), _text(line, values, "if"),
                _number(line, values, "reach", 16), _number(line, values, "rxcost"),
                _number(line, values, "txcost"), _number(line, values, "cost")))
        elif kind == "xroute":
            values = _fields(line, words, 3)
            dump.xroutes.append((_prefix(line, _text(line, values, "prefix"), "prefix"),
                                 _number(line, values, "metric")))
        elif kind == "route":
            values = _fields(line, words, 3)
            dump.routes.append(BabelRoute(
                ident, _prefix(line, _text(line, values, "prefix"), "prefix"),
                _prefix(line, values.get("from", "0.0.0.0/0"), "from"), _flag(line, values, "installed", "yes", "no"),
                _text(line, values, "id"), _number(line, values, "metric"), _number(line, values, "refmetric"),
                _address(line, _text(line, values, "via"), "via"), _text(line, values, "if")))
    return dump


def quality(rxcost: int, txcost: int) -> float:
    """Delivery ratio of a link from babeld's costs: 256 / sqrt(rxcost * txcost), capped at 1; 0 if infinite."""
    if rxcost >= INFINITY or txcost >= INFINITY or rxcost <= 0 or txcost <= 0:
        return 0.0
    return min(1.0, UNIT / math.sqrt(rxcost * txcost))


def _quality_of_metric(metric: int) -> float:
    return min(1.0, math.sqrt(UNIT / metric)) if 0 < metric < INFINITY else (1.0 if metric == 0 else 0.0)


RECENT_HELLOS = 6


def recent_delivery(reach: int) -> float:
    """The share of this neighbour's last `RECENT_HELLOS` Hellos that arrived: the newest bits of
    babeld's 16-bit reach (the most significant bit is the newest Hello). babeld's costs average
    over more Hellos and weigh them, so a link going bad shows here a few Hellos sooner."""
    return bin((reach & 0xFFFF) >> (16 - RECENT_HELLOS)).count("1") / RECENT_HELLOS


def implausible_neighbour(n: BabelNeighbour) -> str | None:
    """Why babeld cannot have computed this neighbour line, or None."""
    if n.cost < INFINITY and (n.rxcost == 0 or n.txcost == 0):
        return (f"neighbour {n.address} on {n.interface}: finite cost {n.cost} with rxcost {n.rxcost} "
                f"txcost {n.txcost} (a cost of 0 is no link)")
    return None


def implausible_route(r: BabelRoute) -> str | None:
    """Why babeld cannot have computed this installed route line, or None."""
    if r.installed and r.metric < INFINITY and (r.metric == 0 or r.metric < r.refmetric):
        return (f"route {r.prefix} via {r.via}: metric {r.metric} with refmetric {r.refmetric} "
                "(a route costs its refmetric plus a link cost of at least 1)")
    return None


def _host(prefix: str) -> str | None:
    net = ipaddress.ip_network(prefix)
    return str(net.network_address) if net.prefixlen == net.max_prefixlen else None


@dataclass(frozen=True)
class _Names:
    """How a view names addresses: the team directory with this node's own addresses, and each
    neighbour's own address (the host prefix it originates) for its link-local one."""

    names: dict[str, str]
    neighbour_ip: dict[str, str]

    def of(self, addr: str) -> str:
        return self.names.get(addr, addr)

    def neighbour(self, via: str) -> str:
        return self.of(self.neighbour_ip.get(via, via))

    def destination(self, prefix: str) -> str:
        host = _host(prefix)
        return self.of(host) if host else prefix


def build_view(dump: BabelDump, parts: frozenset[str], *, node: str, where: str,
               names: Mapping[str, str] | None = None, avoid_margin: float = AVOID_MARGIN) -> NetView:
    """Turn a dump into a NetView with the requested parts (see the module's docstring)."""
    mine = {ifc.ipv4 for ifc in dump.interfaces if ifc.ipv4}
    mine |= {h for prefix, _ in dump.xroutes if (h := _host(prefix))}
    address = next((ifc.ipv4 for ifc in dump.interfaces if ifc.up and ifc.ipv4), "") or min(mine, default="")
    naming = _naming(dump, node, mine, names)
    view = NetView(node=node, address=address)
    view.names = dict(naming.names)
    view.sources["node"] = f"{where} ({dump.version or 'babeld'}, my-id {dump.my_id or '?'})"
    named = "; names: the team directory (agents' beacons)"
    if NEIGHBORS in parts:
        _neighbours(view, dump, naming, where)
        view.sources[NEIGHBORS] = (f"{where} neighbour table (quality 256/sqrt(rxcost*txcost), recent: the "
                                   f"last {RECENT_HELLOS} Hellos of reach, metric: babeld's cost){named}")
    if ROUTES in parts:
        _routes(view, dump, naming, where)
        view.sources[ROUTES] = f"{where} route table (installed routes; cost = metric/256; hops unknown past 1){named}"
    if TOPOLOGY in parts:
        _links(view, dump, naming, mine, where, avoid_margin)
        view.sources[TOPOLOGY] = (f"{where} neighbour table (this node's links) and route table (an edge "
                                  f"N-D where neighbour N's refmetric to D shows a path avoiding this node){named}")
    if POSITIONS in parts:
        view.missing[POSITIONS] = "babeld carries no positions (Babel has no such TLV)"
    return view


def _naming(dump: BabelDump, node: str, mine: set[str], names: Mapping[str, str] | None) -> _Names:
    """The team directory with this node's own addresses, and each neighbour's own address: the host
    prefix it originates (advertised through it with refmetric 0)."""
    named = dict(names or {})
    for own in mine:
        named[own] = node
    neighbour_ip: dict[str, str] = {}
    for r in sorted(dump.routes, key=lambda r: r.prefix):
        host = _host(r.prefix)
        if host and r.refmetric == 0 and r.via not in neighbour_ip and ipaddress.ip_address(host).version == 4:
            neighbour_ip[r.via] = host
    return _Names(named, neighbour_ip)


def _links(view: NetView, dump: BabelDump, naming: _Names, mine: set[str], where: str, margin: float) -> None:
    """The topology from the plausible rows as `view.links` (the implausible dropped and said)."""
    bad_neighbours = {n.address for n in dump.neighbours if implausible_neighbour(n)}
    bad_routes = {r.id for r in dump.routes if implausible_route(r)}
    sane = BabelDump(dump.version, dump.host, dump.my_id, dump.interfaces,
                     [n for n in dump.neighbours if n.address not in bad_neighbours], dump.xroutes,
                     [r for r in dump.routes if r.id not in bad_routes])
    by_via = {n.address: n for n in sane.neighbours}
    view.links = _topology(sane, view.node, naming.neighbour_ip, by_via, mine, naming.neighbour, naming.destination,
                           margin)
    view.dropped.extend(Absurd(where, TOPOLOGY, kind, why) for kind, why in
                        [*(("neighbour", implausible_neighbour(n)) for n in dump.neighbours),
                         *(("route", implausible_route(r)) for r in dump.routes)] if why)


def _neighbours(view: NetView, dump: BabelDump, naming: _Names, where: str) -> None:
    """The neighbour table's plausible rows as `view.neighbors` (the others dropped and said)."""
    for n in dump.neighbours:
        why = implausible_neighbour(n)
        if why:
            view.dropped.append(Absurd(where, NEIGHBORS, "neighbour", why))
            continue
        finite = n.cost < INFINITY
        ip = naming.neighbour_ip.get(n.address, "")
        view.neighbors.append(Neighbor(name=naming.neighbour(n.address), address=ip or n.address,
                                       quality=quality(n.rxcost, n.txcost) if finite else 0.0,
                                       symmetric=finite, metric=n.cost if finite else None,
                                       recent=recent_delivery(n.reach)))


def _routes(view: NetView, dump: BabelDump, naming: _Names, where: str) -> None:
    """The installed, reachable, plausible routes as `view.routes` (the implausible dropped and said)."""
    for r in dump.routes:
        if not r.installed or r.metric >= INFINITY:
            continue
        why = implausible_route(r)
        if why:
            view.dropped.append(Absurd(where, ROUTES, "route", why))
            continue
        hop = naming.neighbour_ip.get(r.via, r.via)
        view.routes.append(Route(destination=naming.destination(r.prefix), next_hop=naming.neighbour(r.via),
                                 hops=1 if _host(r.prefix) == hop else 0, cost=r.metric / UNIT))


def _topology(dump: BabelDump, node: str, neighbour_ip: dict[str, str], by_via: dict[str, BabelNeighbour],
              mine: set[str], neighbour_name: Callable[[str], str], destination: Callable[[str], str],
              margin: float) -> list[Link]:
    links: dict[frozenset[str], Link] = {}

    def add(a: str, b: str, q: float, metric: int) -> None:
        key = frozenset((a, b))
        if a != b and key not in links:
            links[key] = Link(a=min(a, b), b=max(a, b), quality=q, metric=metric)

    for n in dump.neighbours:
        if n.cost < INFINITY:
            add(node, neighbour_name(n.address), quality(n.rxcost, n.txcost), n.cost)
    best_without: dict[tuple[str, str], int] = {}   # (prefix, via) -> our best metric to prefix not via that neighbour
    for r in dump.routes:
        for other in by_via:
            if other != r.via and r.metric < best_without.get((r.prefix, other), INFINITY):
                best_without[(r.prefix, other)] = r.metric
    for r in dump.routes:
        neighbour = by_via.get(r.via)
        host = _host(r.prefix)
        if (neighbour is None or neighbour.cost >= INFINITY or r.refmetric >= INFINITY or r.refmetric == 0
                or (host is not None and host in mine) or neighbour_ip.get(r.via) == host):
            continue
        through_us = neighbour.cost + best_without.get((r.prefix, r.via), INFINITY)
        if r.refmetric < margin * through_us:
            add(neighbour_name(r.via), destination(r.prefix), _quality_of_metric(r.refmetric), r.refmetric)
    return list(links.values())


class BabelSource:
    """A `NetworkSource` reading babeld's local interface (read-only) on this node."""

    def __init__(self, host: str = "::1", port: int = 33123, *, node: str = "", timeout: float = 1.0,
                 names: Callable[[], Mapping[str, str]] | None = None, avoid_margin: float = AVOID_MARGIN) -> None:
        self.host, self.port = host, port
        self.node = node
        self.timeout = timeout
        self.names = names or (lambda: {})
        self.avoid_margin = avoid_margin
        self.header: BabelDump | None = None
        self.requests = 0
        self._reader: asyncio.StreamReader | None = None
        self._writer: asyncio.StreamWriter | None = None

    @property
    def where(self) -> str:
        """`babel [HOST]:PORT`."""
        host = f"[{self.host}]" if ":" in self.host else self.host
        return f"babel {host}:{self.port}"

    async def _lines_until_ok(self, reader: asyncio.StreamReader) -> list[str]:
        lines: list[str] = []
        while True:
            raw = await reader.readline()
            if not raw:
                raise SourceError(f"{self.where}: babeld closed the connection")
            line = raw.decode("utf-8", "replace").strip()
            if line == "ok":
                return lines
            if line in ("no", "bad") or line.startswith("no "):
                raise SourceError(f"{self.where}: babeld answered {line[:80]!r}")
            lines.append(line)
            if len(lines) > 100_000:
                raise SourceError(f"{self.where}: more than 100000 lines without 'ok'")

    async def _connect(self) -> tuple[asyncio.StreamReader, asyncio.StreamWriter]:
        if self._reader is None or self._writer is None:
            try:
                reader, writer = await asyncio.open_connection(self.host, self.port)
            except OSError as err:
                raise SourceError(f"{self.where}: cannot connect ({err.strerror or err}): is babeld "
                                  f"running with -g {self.port} (local-port {self.port})?") from None
            self._reader, self._writer = reader, writer
            header = await self._lines_until_ok(reader)
            if not header or not header[0].startswith("BABEL "):
                await self.aclose()
                raise SourceError(f"{self.where}: not babeld's local interface (it said "
                                  f"{(header[0] if header else '')[:40]!r}, expected 'BABEL 1.0')")
            self.header = parse_dump(header)
        return self._reader, self._writer

    async def dump(self) -> BabelDump:
        """Ask babeld for a dump and parse it (SourceError on failure; reconnects on the next call)."""
        try:
            return await asyncio.wait_for(self._dump(), self.timeout)
        except TimeoutError:
            await self.aclose()
            raise SourceError(f"{self.where}: no complete answer within {self.timeout:g} s") from None
        except SourceError:
            await self.aclose()
            raise
        except OSError as err:
            await self.aclose()
            raise SourceError(f"{self.where}: {err}") from None

    async def _dump(self) -> BabelDump:
        reader, writer = await self._connect()
        self.requests += 1
        writer.write(b"dump\n")
        await writer.drain()
        dump = parse_dump(await self._lines_until_ok(reader))
        if self.header is not None:
            dump.version, dump.host, dump.my_id = self.header.version, self.header.host, self.header.my_id
        return dump

    async def read(self, parts: frozenset[str]) -> NetView:
        """One dump, turned into the requested parts."""
        dump = await self.dump()
        return build_view(dump, parts, node=self.node, where=self.where, names=self.names(),
                          avoid_margin=self.avoid_margin)

    async def write_position(self, position: Position) -> None:
        """Babel has nowhere to put a position: always a SourceError."""
        raise SourceError(f"{self.where}: babeld carries no positions")

    async def aclose(self) -> None:
        """Close the connection."""
        writer, self._reader, self._writer = self._writer, None, None
        if writer is not None:
            writer.close()
            try:
                await writer.wait_closed()
            except OSError:
                pass
