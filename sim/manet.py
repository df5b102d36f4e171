"""Simulated MANET network subsystem: radio links, neighbours, ETX routing, known positions.

The model is what a proactive link-state MANET (NHDP + OLSRv2 with an ETX-like metric)
would converge to, computed directly from node positions:

- **Radio.** The delivery ratio of a link is 1 up to `lossless_range`, falls linearly to 0
  at `comm_range` (R) and is 0 beyond R. Links are symmetric.
- **Neighbours.** A node hears every node with a delivery ratio > 0; a neighbour is
  *symmetric* (usable for routing) when the ratio is at least `min_quality`.
- **Metric.** A link's metric is its ETX (1 / (forward ratio * reverse ratio)) scaled by
  `METRIC_UNIT` = 1024 into OLSRv2's compressed range (max 16776960); a path's cost is the
  sum of its link metrics. Routes are Dijkstra on that metric over symmetric links.
- **Positions as the network knows them.** Each node reports its own position (its SNMP
  SET, or `set_position()`); the report reaches every node of the reporter's connected
  component, at once and again whenever the topology changes; partitioned nodes keep
  what they knew.
- **Protocol bookkeeping.** What an NHDP/OLSRv2 router would count is kept with the
  network's clock: HELLOs expected and received from each neighbour (one every
  `HELLO_INTERVAL`, each received with the link's delivery ratio; counters only grow), the
  changes of each node's Neighbor Set, its ANSN (bumped when its advertised neighbours or
  their metrics change), and its MPR-set and routing-set recalculations. Every router
  selects all its symmetric neighbours as MPRs and advertises all of them (RFC 7181 allows
  both), so the advertised topology is the set of symmetric links.

`ManetNetwork` is thread-safe: the SNMP agent reads views while a simulator moves nodes.
"""

from __future__ import annotations

import dataclasses
import ipaddress
import math
import threading
import time
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from erni import netgraph
from erni.blackboard.errors import NotFoundError, UsageError

METRIC_UNIT = 1024
MAX_METRIC = 16776960
# protocol constants: RFC 6130 (NHDP) and RFC 7181 (OLSRv2) defaults, in seconds
HELLO_INTERVAL = 2.0
L_HOLD_TIME = 6.0        # a link is heard until 3 HELLO intervals without one
H_HOLD_TIME = 6.0        # 2-hop information lasts as long
TC_INTERVAL = 5.0
T_HOLD_TIME = 15.0       # topology information lasts 3 TC intervals


@dataclass(frozen=True)
class RadioModel:
    """Link delivery ratio as a function of distance (metres)."""

    comm_range: float
    lossless_range: float
    min_quality: float = 0.1

    def __post_init__(self) -> None:
        if not self.comm_range > 0:
            raise UsageError(f"radio: comm_range must be > 0 m, got {self.comm_range}")
        if not 0 <= self.lossless_range <= self.comm_range:
            raise UsageError(f"radio: lossless_range must be in [0, comm_range={self.comm_range}] m, "
                             f"got {self.lossless_range}")
        if not 0 < self.min_quality <= 1:
            raise UsageError(f"radio: min_quality must be in (0, 1], got {self.min_quality}")

    def quality(self, distance: float) -> float:
        """Delivery ratio in [0, 1] of a link of length `distance`."""
        if distance <= self.lossless_range:
            return 1.0
        if distance >= self.comm_range:
            return 0.0
        return (self.comm_range - distance) / (self.comm_range - self.lossless_range)

    def link_qualities(self, distances: np.ndarray) -> np.ndarray:
        """The delivery ratio of a link for each of `distances` (m), 0 at `comm_range` and beyond:
        what `quality` gives every pair the network links (vectorised: compared at each move)."""
        q = np.zeros_like(distances)
        inside = distances < self.comm_range
        lossless = distances <= self.lossless_range
        q[inside & lossless] = 1.0
        band = inside & ~lossless  # here lossless_range < d < comm_range, so no division by zero
        if band.any():
            q[band] = (self.comm_range - distances[band]) / (self.comm_range - self.lossless_range)
        return q

    def range_for(self, quality: float) -> float:
        """The longest link (m) whose delivery ratio is still at least `quality` (in (0, 1])."""
        if not 0 < quality <= 1:
            raise UsageError(f"radio: a link quality must be in (0, 1], got {quality}")
        return self.comm_range - quality * (self.comm_range - self.lossless_range)


def link_metric(quality: float) -> int:
    """OLSRv2 link metric (ETX * METRIC_UNIT, capped at MAX_METRIC) of a symmetric link."""
    if quality <= 0:
        return MAX_METRIC
    return min(MAX_METRIC, round(METRIC_UNIT / (quality * quality)))


def link_metrics(qualities: np.ndarray) -> np.ndarray:
    """`link_metric` of each of `qualities` (all > 0), worked out together: the same integers
    (numpy rounds halves to even, as `round` does)."""
    metrics: np.ndarray = np.minimum(MAX_METRIC, np.rint(METRIC_UNIT / (qualities * qualities))).astype(np.int64)
    return metrics


@dataclass(frozen=True)
class KnownPosition:
    """A node position as the network knows it (m, deg) and when it was reported."""

    x: float
    y: float
    heading: float = 0.0
    reported: float = field(default_factory=time.monotonic)


@dataclass(frozen=True)
class NeighborState:
    """A one-hop neighbour seen by a node."""

    name: str
    index: int
    address: str
    quality: float
    symmetric: bool
    metric: int


@dataclass(frozen=True)
class NodeInfo:
    """A node's identity in the network."""

    name: str
    index: int
    address: str


@dataclass(frozen=True)
class NodeCounters:
    """A node's protocol counters at the time of its view (they only grow)."""

    neighbor_changes: int = 0     # tuples added to, removed from or changed in its Neighbor Set
    ansn: int = 0                 # advertised neighbour sequence number (unbounded; mod 2**16 on the wire)
    mpr_recalcs: int = 0          # MPR set recalculations
    route_recalcs: int = 0        # routing set recalculations
    routes_at: float = 0.0        # network clock time of the last routing set recalculation


@dataclass(frozen=True)
class NodeView:
    """What one node's network subsystem knows: the data its SNMP agent serves."""

    node: NodeInfo
    version: int
    neighbors: tuple[NeighborState, ...]
    topology: tuple[tuple[str, str, int], ...]
    routes: dict[str, netgraph.RouteEntry]
    positions: dict[str, KnownPosition]
    known_nodes: tuple[NodeInfo, ...]
    position_updates: int
    topology_version: int = 0
    counters: NodeCounters = field(default_factory=NodeCounters)
    ansn: dict[str, int] = field(default_factory=dict)   # ANSN of every router of the component


@dataclass
class _LinkRecord:
    """HELLO bookkeeping of one (undirected) link: seconds heard and delivered, folded at changes."""

    heard: float
    delivered: float
    at: float          # when the sums were last folded
    quality: float     # delivery ratio since `at` (0: not heard)
    since: float       # when the link was last (re)established


@dataclass(frozen=True)
class GroundTruth:
    """The simulator's truth: true positions, link qualities, components, cut vertices."""

    positions: dict[str, tuple[float, float]]
    links: dict[frozenset[str], float]
    symmetric: dict[str, dict[str, int]]
    components: list[set[str]]
    articulation_points: set[str]

    def routes(self, name: str) -> dict[str, netgraph.RouteEntry]:
        """Routing table of `name` over symmetric links (costs in metric units)."""
        return netgraph.routes_from(self.symmetric, name)


class ManetNetwork:
    """A simulated MANET: add and move nodes, report positions, read per-node views and truth."""

    def __init__(self, radio: RadioModel, subnet: str = "10.0.0.0/16", gps: bool = False,
                 clock: Callable[[], float] = time.monotonic) -> None:
        self.radio = radio
        self.gps = gps
        self.clock = clock
        self._net = ipaddress.ip_network(subnet)
        self._lock = threading.RLock()
        self._nodes: dict[str, NodeInfo] = {}
        self._by_address: dict[str, str] = {}
        self._pos: dict[str, tuple[float, float]] = {}
        self._known: dict[str, dict[str, KnownPosition]] = {}
        self._updates: dict[str, int] = {}
        self._version = 0
        self._rows_version = 0
        self._topo_version = 0
        self._truth: GroundTruth | None = None
        self._qualities: np.ndarray | None = None  # every pair's link quality when the truth was last made
        self._views: dict[str, NodeView] = {}
        self._topologies: dict[str, tuple[tuple[str, str, int], ...]] = {}
        self._records: dict[frozenset[str], _LinkRecord] = {}
        self._served_hellos: dict[tuple[str, str], tuple[int, int]] = {}
        self._counters: dict[str, NodeCounters] = {}

    # -- building and moving -------------------------------------------------------------

    def add_node(self, name: str, x: float, y: float, heading: float = 0.0) -> NodeInfo:
        """Add a node at (x, y); its initial position is known to its component."""
        if not name or not isinstance(name, str):
            raise UsageError(f"node name must be a non-empty string, got {name!r}")
        _check_xy(name, x, y)
        with self._lock:
            if name in self._nodes:
                raise UsageError(f"node {name!r} already exists")
            index = len(self._nodes) + 1
            if index >= self._net.num_addresses - 1:
                raise UsageError(f"subnet {self._net} has no address left for node {name!r}")
            address = str(self._net.network_address + index)
            info = NodeInfo(name, index, address)
            self._nodes[name] = info
            self._by_address[address] = name
            self._pos[name] = (float(x), float(y))
            self._known[name] = {}
            self._updates[name] = 0
            self._counters[name] = NodeCounters(routes_at=self.clock())
            self._changed(nodes_changed=True)
            self._report(name, KnownPosition(float(x), float(y), float(heading), self.clock()))
            return info

    def move(self, name: str, x: float, y: float) -> None:
        """Move a node to its new true position (what the simulator's world says)."""
        self.move_many({name: (x, y)})

    def move_many(self, positions: dict[str, tuple[float, float]]) -> None:
        """Move several nodes at once (one topology change)."""
        with self._lock:
            for name, (x, y) in positions.items():
                self._require(name)
                _check_xy(name, x, y)
            for name, (x, y) in positions.items():
                self._pos[name] = (float(x), float(y))
            self._changed()
            if self.gps:
                for name, (x, y) in positions.items():
                    old = self._known[name].get(name)
                    self._report(name, KnownPosition(float(x), float(y), old.heading if old else 0.0,
                                                     self.clock()))

    def set_position(self, name: str, x: float, y: float, heading: float = 0.0) -> None:
        """Record the position node `name` reports about itself (its SNMP SET)."""
        _check_xy(name, x, y)
        if not math.isfinite(heading):
            raise UsageError(f"node {name!r}: heading must be finite, got {heading!r}")
        with self._lock:
            self._require(name)
            self._updates[name] += 1
            self._report(name, KnownPosition(float(x), float(y), float(heading), self.clock()))

    # -- reading --------------------------------------------------------------------------

    @property
    def version(self) -> int:
        """Counter bumped whenever anything a node serves changes (links, routes, reports)."""
        return self._version

    @property
    def rows_version(self) -> int:
        """Counter bumped when the set of rows some node serves changes: links, routes, nodes, or an
        origin a node had no position of. A position report alone changes values, not rows."""
        return self._rows_version

    def known_position(self, name: str, origin: str) -> KnownPosition | None:
        """The newest position of `origin` that node `name` has learned (None: none yet)."""
        return self._known[name].get(origin)

    def position_updates(self, name: str) -> int:
        """How many positions node `name` has reported about itself."""
        return self._updates[name]

    def names(self) -> list[str]:
        """Node names in index order."""
        with self._lock:
            return list(self._nodes)

    def info(self, name: str) -> NodeInfo:
        """Identity (index, address) of a node."""
        with self._lock:
            return self._require(name)

    def name_of(self, address: str) -> str | None:
        """The node name owning `address`, or None."""
        return self._by_address.get(address)

    def truth(self) -> GroundTruth:
        """The ground truth of the whole network (cached until the next change)."""
        with self._lock:
            if self._truth is None:
                self._truth = self._compute_truth()
            return self._truth

    def view(self, name: str) -> NodeView:
        """What node `name` knows (cached until the next change)."""
        with self._lock:
            view = self._views.get(name)
            if view is not None:
                return view
            info = self._require(name)
            truth = self.truth()
            comp = next(c for c in truth.components if name in c)
            neighbors = []
            for other, o_info in self._nodes.items():
                if other == name:
                    continue
                q = truth.links.get(frozenset((name, other)), 0.0)
                if q <= 0:
                    continue
                sym = other in truth.symmetric[name]
                neighbors.append(NeighborState(other, o_info.index, o_info.address, q, sym,
                                               link_metric(q)))
            key = min(comp, key=self._index)
            topology = self._topologies.get(key)  # shared by every node of the component
            if topology is None:
                topology = tuple(
                    (a, b, m) for a in sorted(comp, key=self._index) for b, m in
                    sorted(truth.symmetric[a].items(), key=lambda kv: self._index(kv[0]))
                )
                self._topologies[key] = topology
            routes = netgraph.routes_from({n: truth.symmetric[n] for n in comp}, name)
            known = dict(self._known[name])
            names = set(comp) | set(known) | {n.name for n in neighbors}
            view = NodeView(
                node=info, version=self._version, neighbors=tuple(neighbors), topology=topology,
                routes=routes, positions=known,
                known_nodes=tuple(sorted((self._nodes[n] for n in names), key=lambda i: i.index)),
                position_updates=self._updates[name], topology_version=self._topo_version,
                counters=self._counters[name], ansn={n: self._counters[n].ansn for n in comp},
            )
            self._views[name] = view
            return view

    def hello_counts(self, name: str, neighbor: str) -> tuple[int, int]:
        """HELLOs (received, expected) by `name` from `neighbor` so far; both only grow."""
        with self._lock:
            record = self._records.get(frozenset((name, neighbor)))
            if record is None:
                return 0, 0
            now = self.clock()
            live = max(0.0, now - record.at)
            heard = record.heard + (live if record.quality > 0 else 0.0)
            delivered = record.delivered + live * record.quality
            counts = (int(delivered / HELLO_INTERVAL), int(heard / HELLO_INTERVAL))
            last = self._served_hellos.get((name, neighbor), (0, 0))
            counts = (max(counts[0], last[0]), max(counts[1], last[1]))  # float folding never undoes a count
            self._served_hellos[(name, neighbor)] = counts
            return counts

    def link_since(self, name: str, neighbor: str) -> float | None:
        """Network clock time the link between two nodes was last established (None: never heard)."""
        with self._lock:
            record = self._records.get(frozenset((name, neighbor)))
            return None if record is None or record.quality <= 0 else record.since

    # -- internals ------------------------------------------------------------------------

    def _index(self, name: str) -> int:
        return self._nodes[name].index

    def _require(self, name: str) -> NodeInfo:
        try:
            return self._nodes[name]
        except KeyError:
            raise NotFoundError(f"unknown node {name!r}; known: {', '.join(self._nodes) or 'none'}") from None

    def _changed(self, nodes_changed: bool = False) -> None:
        """Recompute the truth after moves; bump versions only if what nodes serve changed.

        Moves that leave every pair's link quality as it was (robots inside each other's loss-free
        range, or out of range) keep the truth's links, routes, components and cut vertices and
        take the new positions only: the qualities of all pairs are compared vectorised, where
        working out the truth again costs a Python step per pair (a 50-robot team fed 10 times a
        second: 12 000 a second)."""
        old = self._truth
        qualities = self._pair_qualities()
        unchanged = self._qualities is not None and np.array_equal(qualities, self._qualities)
        self._qualities = qualities
        if not nodes_changed and old is not None and unchanged:
            self._truth = dataclasses.replace(old, positions=dict(self._pos))
            return  # no link changed quality: nothing to fold, no version to bump
        new = self._compute_truth(qualities)
        self._truth = new
        now = self.clock()
        self._fold_links(new, now)
        if not nodes_changed and old is not None and _same_links(old, new):
            return  # e.g. moves within the loss-free range: links, metrics and routes stand
        self._count_changes(old, new, now)
        self._version += 1
        self._rows_version += 1
        self._topo_version += 1
        self._views.clear()
        self._topologies.clear()
        self._disseminate()

    def _fold_links(self, new: GroundTruth, now: float) -> None:
        """Add the time since the last fold to every link's HELLO sums; start or stop links."""
        for key in set(self._records) | set(new.links):
            quality = new.links.get(key, 0.0)
            record = self._records.get(key)
            if record is None:
                self._records[key] = _LinkRecord(0.0, 0.0, now, quality, now)
                continue
            live = max(0.0, now - record.at)
            if record.quality > 0:
                record.heard += live
                record.delivered += live * record.quality
            if record.quality <= 0 < quality:
                record.since = now
            record.quality, record.at = quality, now

    def _count_changes(self, old: GroundTruth | None, new: GroundTruth, now: float) -> None:
        """Bump each node's protocol counters for what this change did to its neighbourhood."""
        heard_old = _heard(old.links) if old is not None else {}
        heard_new = _heard(new.links)
        sym_old = old.symmetric if old is not None else {}
        component_of = {n: i for i, comp in enumerate(new.components) for n in comp}
        topo_changed = set()
        for i, comp in enumerate(new.components):
            if edges_changed(comp, sym_old, new.symmetric):
                topo_changed.add(i)
        for name in new.symmetric:
            c = self._counters[name]
            h_old, h_new = heard_old.get(name, {}), heard_new.get(name, {})
            s_old, s_new = sym_old.get(name, {}), new.symmetric[name]
            tuples = len(h_old.keys() ^ h_new.keys()) + sum(
                1 for n in h_old.keys() & h_new.keys() if (n in s_old) != (n in s_new))
            recalc = component_of[name] in topo_changed
            self._counters[name] = NodeCounters(
                neighbor_changes=c.neighbor_changes + tuples,
                ansn=c.ansn + (s_old != s_new),
                mpr_recalcs=c.mpr_recalcs + (s_old.keys() != s_new.keys()
                                             or two_hop_changed(name, s_new.keys(), sym_old, new.symmetric)),
                route_recalcs=c.route_recalcs + recalc,
                routes_at=now if recalc else c.routes_at)

    def _report(self, name: str, pos: KnownPosition) -> None:
        comp = next(c for c in self.truth().components if name in c)
        for member in comp:
            known = self._known[member]
            if name not in known:
                self._rows_version += 1   # a new origin: its member serves rows it did not serve before
            known[name] = pos
        self._version += 1
        self._views.clear()

    def _disseminate(self) -> None:
        """Within each component, every node learns the newest report of every origin."""
        for comp in self.truth().components:
            newest: dict[str, KnownPosition] = {}
            for member in comp:
                for origin, pos in self._known[member].items():
                    if origin not in newest or pos.reported > newest[origin].reported:
                        newest[origin] = pos
            for member in comp:
                self._known[member].update(newest)

    def _pair_qualities(self) -> np.ndarray:
        """The link quality of every pair of nodes, in the order they were added (N x N)."""
        xy = np.array([self._pos[n] for n in self._nodes], dtype=float).reshape(-1, 2)
        distances = np.hypot(xy[:, 0, None] - xy[None, :, 0], xy[:, 1, None] - xy[None, :, 1])
        return self.radio.link_qualities(distances)

    def _compute_truth(self, qualities: np.ndarray | None = None) -> GroundTruth:
        """The truth of the network now, from every pair's link quality (`_pair_qualities`, which a
        move has just worked out: given, it is not worked out again). Only the linked pairs take a
        Python step; their metrics are worked out together."""
        names = list(self._nodes)
        q = self._pair_qualities() if qualities is None else qualities
        rows, cols = np.nonzero(np.triu(q, 1) > 0)   # in the order of the pairs: row by row
        linked = q[rows, cols]
        metrics = link_metrics(linked)
        links: dict[frozenset[str], float] = {}
        sym: dict[str, dict[str, int]] = {n: {} for n in names}
        min_q = self.radio.min_quality
        for i, j, quality, m in zip(rows.tolist(), cols.tolist(), linked.tolist(), metrics.tolist()):
            a, b = names[i], names[j]
            links[frozenset((a, b))] = quality
            if quality >= min_q:
                sym[a][b] = m
                sym[b][a] = m
        return GroundTruth(
            positions=dict(self._pos), links=links, symmetric=sym,
            components=netgraph.connected_components(sym),
            articulation_points=netgraph.articulation_points(sym),
        )


def _heard(links: dict[frozenset[str], float]) -> dict[str, dict[str, float]]:
    """Every node's heard neighbours with their delivery ratios."""
    out: dict[str, dict[str, float]] = {}
    for key, q in links.items():
        a, b = tuple(key)
        out.setdefault(a, {})[b] = q
        out.setdefault(b, {})[a] = q
    return out


def edges_changed(nodes: Iterable[str], old: dict[str, dict[str, int]], new: dict[str, dict[str, int]]) -> bool:
    """Whether the (node, neighbour, metric) edges leaving `nodes` changed (a component's topology:
    its nodes recompute their routes). Compared node by node, without building the edge sets."""
    return any(new.get(a, {}) != old.get(a, {}) for a in nodes)


def two_hop_changed(name: str, neighbors: Iterable[str], old: dict[str, dict[str, int]],
                    new: dict[str, dict[str, int]]) -> bool:
    """Whether `name`'s two-hop neighbourhood through `neighbors` (the same before and after) changed:
    another node or metric beyond one of them (what makes OLSR recompute its MPRs). Compared
    neighbour by neighbour, stopping at the first change; the sets of (neighbour, node, metric)
    a team of 50 moving at the radio's edge built cost 60 % of each feed."""
    for n in neighbors:
        a, b = old.get(n, {}), new.get(n, {})
        if a != b and {m: k for m, k in a.items() if m != name} != {m: k for m, k in b.items() if m != name}:
            return True
    return False


def _same_links(a: GroundTruth, b: GroundTruth) -> bool:
    """True when two truths serve the same links: metrics and qualities (to 1/1000) agree."""
    if a.symmetric != b.symmetric or a.links.keys() != b.links.keys():
        return False
    return all(round(q * 1000) == round(b.links[k] * 1000) for k, q in a.links.items())


def _check_xy(name: Any, x: Any, y: Any) -> None:
    for label, v in (("x", x), ("y", y)):
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
            raise UsageError(f"node {name!r}: {label} must be a finite number of metres, got {v!r}")
