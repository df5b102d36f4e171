"""Graph algorithms on undirected weighted adjacency maps: components, cut vertices, paths."""

from __future__ import annotations

import heapq
import math
from collections.abc import Hashable, Iterable, Mapping
from dataclasses import dataclass
from typing import Any

Node = Hashable
Adjacency = Mapping[Any, Mapping[Any, float]]


def from_edges(edges: Iterable[tuple[Any, Any] | tuple[Any, Any, float]],
               nodes: Iterable[Any] = ()) -> dict[Any, dict[Any, float]]:
    """Build an undirected adjacency map from `(a, b)` or `(a, b, weight)` edges (weight 1)."""
    adj: dict[Any, dict[Any, float]] = {n: {} for n in nodes}
    for edge in edges:
        if len(edge) == 2:
            a, b = edge  # type: ignore[misc]
            w = 1.0
        else:
            a, b, w = edge  # type: ignore[misc]
        add_edge(adj, a, b, w)
    return adj


def add_edge(adj: dict[Any, dict[Any, float]], a: Any, b: Any, weight: float = 1.0) -> None:
    """Add the undirected edge a-b with `weight` (self-loops are ignored; weight must be >= 0)."""
    if weight < 0 or math.isnan(weight):
        raise ValueError(f"edge {a!r}-{b!r}: weight must be >= 0, got {weight!r}")
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
        stack = [(root, None, iter(adj.get(root, ())))]
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
        raise KeyError(f"unknown source node {source!r}")
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
