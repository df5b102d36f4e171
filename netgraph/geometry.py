"""Geometric graphs on node positions: the relative neighbourhood graph (RNG)."""

from __future__ import annotations

import math
from collections.abc import Iterable, Mapping
from typing import Any

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
            raise KeyError(f"edge {a!r}-{b!r}: node without a position")
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
        raise KeyError(f"unknown node {node!r}")
    if edges is None:
        cand = [(node, other) for other in positions if other != node]
    else:
        cand = [(a, b) for a, b in edges if node in (a, b)]
    return {next(iter(e - {node})) for e in rng_edges(positions, cand)}
