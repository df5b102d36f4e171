"""Pure graph helpers for network awareness: components, articulation points, RNG, routes.

A graph is an adjacency mapping `{node: {neighbour: weight}}`, undirected (every edge is
listed from both ends). Nodes are any hashable, orderable values (robot names in ERNI).
Nothing here imports the rest of ERNI, so the simulator and every plugin can share it.
"""

from erni.netgraph.graph import (
    Adjacency,
    RouteEntry,
    add_edge,
    articulation_points,
    connected_components,
    dijkstra,
    from_edges,
    rng_edges,
    rng_neighbors,
    routes_from,
    shortest_path,
)

__all__ = [
    "Adjacency", "RouteEntry", "add_edge", "articulation_points", "connected_components",
    "dijkstra", "from_edges", "rng_edges", "rng_neighbors", "routes_from", "shortest_path",
]
