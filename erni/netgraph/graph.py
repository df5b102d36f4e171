"""Graph algorithms on undirected weighted adjacency maps: components, cut vertices, paths, RNG."""

from __future__ import annotations

import heapq
import math
from collections.abc import Hashable, Iterable, Iterator, Mapping
from dataclasses import dataclass
from typing import Any

from erni.blackboard.errors import NotFoundError, UsageError

Node = Hashable
Adjacency = Mapping[Any, Mapping[Any, float]]


def from_edges(edges: Iterable[tuple[Any, Any] | tuple[Any, Any, float]],
               nodes: Iterable[Any] = ()) -> dict[Any, dict[Any, float]]:
    """Build an undirected adjacency map from `(a, b)` or `(a, b, weight)` edges (weight 1)."""
    adj: dict[Any, dict[Any, float]] = {n: {} for n in nodes}
    for edge in edges:
        if len(edge) == 2:
            a, b = edge
            w = 1.0
        else:
            a, b, w = edge
        add_edge(adj, a, b, w)
    return adj


def add_edge(adj: dict[Any, dict[Any, float]], a: Any, b: Any, weight: float = 1.0) -> None:
    """Add the undirected edge a-b with `weight` (self-loops are ignored; weight must be >= 0)."""
    if weight < 0 or math.isnan(weight):
        raise UsageError(f"edge {a!r}-{b!r}: weight must be >= 0, got {weight!r}")
    adj.setdefault(a, {})
    adj.setdefault(b, {})
    if a == b:
        return
    adj[a][b] = weight
    adj[b][a] = weight


def _sorted(nodes: Iterable[Any]) -> list[Any]:
    try:
        return sorted(nodes)
    except TypeError:
        return sorted(nodes, key=repr)


def connected_components(adj: Adjacency) -> list[set[Any]]:
    """Return the connected components, largest first (ties broken by smallest member)."""
    seen: set[Any] = set()
    comps: list[set[Any]] = []
    for start in _sorted(adj):
        if start in seen:
            continue
        comp = {start}
        stack = [start]
        seen.add(start)
        while stack:
            u = stack.pop()
            for v in adj.get(u, ()):
                if v not in seen:
                    seen.add(v)
                    comp.add(v)
                    stack.append(v)
        comps.append(comp)
    comps.sort(key=lambda c: (-len(c), repr(_sorted(c)[0])))
    return comps


def articulation_points(adj: Adjacency) -> set[Any]:
    """Return the cut vertices: nodes whose removal splits their connected component."""
    disc: dict[Any, int] = {}
    low: dict[Any, int] = {}
    cut: set[Any] = set()
    counter = 0
    for root in _sorted(adj):
        if root in disc:
            continue
        disc[root] = low[root] = counter
        counter += 1
        root_children = 0
        # iterative DFS: (node, parent, iterator over neighbours)
        stack: list[tuple[Any, Any, Iterator[Any]]] = [(root, None, iter(adj.get(root, ())))]
        while stack:
            u, parent, it = stack[-1]
            advanced = False
            for v in it:
                if v == u:
                    continue
                if v not in disc:
                    disc[v] = low[v] = counter
                    counter += 1
                    if u == root:
                        root_children += 1
                    stack.append((v, u, iter(adj.get(v, ()))))
                    advanced = True
                    break
                if v != parent:
                    low[u] = min(low[u], disc[v])
            if advanced:
                continue
            stack.pop()
            if parent is not None:
                low[parent] = min(low[parent], low[u])
                if parent != root and low[u] >= disc[parent]:
                    cut.add(parent)
        if root_children > 1:
            cut.add(root)
    return cut


def dijkstra(adj: Adjacency, source: Any) -> tuple[dict[Any, float], dict[Any, Any], dict[Any, int]]:
    """Return (cost, predecessor, hops) from `source`; equal costs prefer fewer hops."""
    if source not in adj:
        raise NotFoundError(f"unknown source node {source!r}")
    cost: dict[Any, float] = {source: 0.0}
    hops: dict[Any, int] = {source: 0}
    prev: dict[Any, Any] = {}
    done: set[Any] = set()
    seq = 0
    heap: list[tuple[float, int, int, Any]] = [(0.0, 0, seq, source)]
    while heap:
        c, h, _, u = heapq.heappop(heap)
        if u in done:
            continue
        done.add(u)
        for v, w in adj[u].items():
            if v in done:
                continue
            nc, nh = c + w, h + 1
            if v not in cost or (nc, nh) < (cost[v], hops[v]):
                cost[v], hops[v], prev[v] = nc, nh, u
                seq += 1
                heapq.heappush(heap, (nc, nh, seq, v))
    return cost, prev, hops


def shortest_path(adj: Adjacency, source: Any, target: Any) -> tuple[float, list[Any]]:
    """Return (cost, [source, ..., target]); (inf, []) when target is unreachable."""
    cost, prev, _ = dijkstra(adj, source)
    if target not in cost:
        return math.inf, []
    path = [target]
    while path[-1] != source:
        path.append(prev[path[-1]])
    path.reverse()
    return cost[target], path


@dataclass(frozen=True)
class RouteEntry:
    """One route of a routing table: first hop, number of hops and total path cost."""

    destination: Any
    next_hop: Any
    hops: int
    cost: float


def routes_from(adj: Adjacency, source: Any) -> dict[Any, RouteEntry]:
    """Return the routing table of `source`: one entry per reachable destination (not itself)."""
    cost, prev, hops = dijkstra(adj, source)
    table: dict[Any, RouteEntry] = {}
    for dest in cost:
        if dest == source:
            continue
        hop = dest
        while prev[hop] != source:
            hop = prev[hop]
        table[dest] = RouteEntry(dest, hop, hops[dest], cost[dest])
    return table


# --- geometric graphs ---------------------------------------------------------------

Point = tuple[float, float]


def _dist(p: Point, q: Point) -> float:
    return math.hypot(p[0] - q[0], p[1] - q[1])


def rng_edges(positions: Mapping[Any, Point],
              edges: Iterable[tuple[Any, Any]] | None = None) -> set[frozenset[Any]]:
    """Return the RNG edges: u-v is kept unless some w has max(d(u,w), d(v,w)) < d(u,v).

    `edges` restricts the candidates (for example to links of the communication graph);
    by default every pair of nodes is a candidate. Witnesses are all positioned nodes.
    """
    names = list(positions)
    if edges is None:
        candidates = [(names[i], names[j]) for i in range(len(names))
                      for j in range(i + 1, len(names))]
    else:
        candidates = [(a, b) for a, b in edges if a != b]
    kept: set[frozenset[Any]] = set()
    for a, b in candidates:
        if a not in positions or b not in positions:
            raise NotFoundError(f"edge {a!r}-{b!r}: node without a position")
        pa, pb = positions[a], positions[b]
        dab = _dist(pa, pb)
        blocked = False
        for w in names:
            if w == a or w == b:
                continue
            pw = positions[w]
            if max(_dist(pa, pw), _dist(pb, pw)) < dab:
                blocked = True
                break
        if not blocked:
            kept.add(frozenset((a, b)))
    return kept


def rng_neighbors(positions: Mapping[Any, Point], node: Any,
                  edges: Iterable[tuple[Any, Any]] | None = None) -> set[Any]:
    """Return the RNG neighbours of `node` (candidates restricted to `edges` if given)."""
    if node not in positions:
        raise NotFoundError(f"unknown node {node!r}")
    if edges is None:
        cand = [(node, other) for other in positions if other != node]
    else:
        cand = [(a, b) for a, b in edges if node in (a, b)]
    return {next(iter(e - {node})) for e in rng_edges(positions, cand)}
