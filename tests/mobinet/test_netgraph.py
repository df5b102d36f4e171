"""netgraph against networkx as an independent oracle, on known and random graphs."""

from __future__ import annotations

import math

import networkx as nx
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from erni import netgraph as ng


def to_nx(adj):
    g = nx.Graph()
    g.add_nodes_from(adj)
    for a, nbrs in adj.items():
        for b, w in nbrs.items():
            g.add_edge(a, b, weight=w)
    return g


@st.composite
def graphs(draw, max_nodes=14):
    n = draw(st.integers(1, max_nodes))
    pairs = [(i, j) for i in range(n) for j in range(i + 1, n)]
    chosen = draw(st.lists(st.sampled_from(pairs), unique=True, max_size=len(pairs))) if pairs else []
    weights = draw(st.lists(st.integers(1, 20), min_size=len(chosen), max_size=len(chosen)))
    return ng.from_edges([(a, b, float(w)) for (a, b), w in zip(chosen, weights)], nodes=range(n))


def test_known_graph_bridge_and_cut_vertices():
    # two triangles joined by a path 3-4-5: cut vertices 3, 4, 5
    adj = ng.from_edges([(1, 2), (2, 3), (3, 1), (3, 4), (4, 5), (5, 6), (6, 7), (7, 5)])
    assert ng.articulation_points(adj) == {3, 4, 5}
    assert ng.connected_components(adj) == [set(range(1, 8))]


def test_star_centre_is_the_only_cut_vertex_and_cycle_has_none():
    star = ng.from_edges([("hub", f"leaf{i}") for i in range(5)])
    assert ng.articulation_points(star) == {"hub"}
    ring = ng.from_edges([(i, (i + 1) % 6) for i in range(6)])
    assert ng.articulation_points(ring) == set()


def test_components_largest_first_with_isolated_nodes():
    adj = ng.from_edges([("a", "b"), ("c", "d"), ("d", "e")], nodes=["z"])
    assert ng.connected_components(adj) == [{"c", "d", "e"}, {"a", "b"}, {"z"}]


def test_routes_prefer_cheaper_multi_hop_path():
    adj = ng.from_edges([("a", "b", 10.0), ("a", "c", 1.0), ("c", "b", 2.0), ("b", "d", 1.0)])
    table = ng.routes_from(adj, "a")
    assert table["b"] == ng.RouteEntry("b", "c", 2, 3.0)
    assert table["d"] == ng.RouteEntry("d", "c", 3, 4.0)
    assert "a" not in table
    assert ng.shortest_path(adj, "a", "d") == (4.0, ["a", "c", "b", "d"])


def test_equal_cost_prefers_fewer_hops():
    adj = ng.from_edges([("s", "t", 2.0), ("s", "m", 1.0), ("m", "t", 1.0)])
    assert ng.routes_from(adj, "s")["t"] == ng.RouteEntry("t", "t", 1, 2.0)


def test_unreachable_and_bad_input():
    adj = ng.from_edges([("a", "b")], nodes=["c"])
    assert ng.shortest_path(adj, "a", "c") == (math.inf, [])
    with pytest.raises(KeyError, match="unknown source node 'q'"):
        ng.dijkstra(adj, "q")
    with pytest.raises(ValueError, match="weight must be >= 0"):
        ng.from_edges([("a", "b", -1.0)])


def test_rng_known_configuration():
    # a, b, c on a line: a-c is blocked by b; a right-angle witness blocks the long side
    pos = {"a": (0.0, 0.0), "b": (1.0, 0.0), "c": (2.0, 0.0), "d": (1.0, 5.0)}
    edges = ng.rng_edges(pos)
    assert frozenset(("a", "b")) in edges and frozenset(("b", "c")) in edges
    assert frozenset(("a", "c")) not in edges
    assert ng.rng_neighbors(pos, "b") >= {"a", "c"}
    # restricting candidates to communication links drops d, which is out of range
    links = [("a", "b"), ("b", "c"), ("a", "c")]
    assert ng.rng_neighbors(pos, "b", links) == {"a", "c"}


@settings(max_examples=150, deadline=None)
@given(graphs())
def test_articulation_points_and_components_match_networkx(adj):
    g = to_nx(adj)
    assert ng.articulation_points(adj) == set(nx.articulation_points(g))
    assert sorted(map(sorted, ng.connected_components(adj))) == \
        sorted(map(sorted, nx.connected_components(g)))


@settings(max_examples=150, deadline=None)
@given(graphs(), st.data())
def test_shortest_paths_match_networkx(adj, data):
    g = to_nx(adj)
    src = data.draw(st.sampled_from(sorted(adj)))
    expected = nx.single_source_dijkstra_path_length(g, src, weight="weight")
    cost, _, _ = ng.dijkstra(adj, src)
    assert cost.keys() == expected.keys()
    for node, c in expected.items():
        assert cost[node] == pytest.approx(c)
    for dest, entry in ng.routes_from(adj, src).items():
        # the next hop really starts a shortest path
        assert adj[src][entry.next_hop] + (0 if entry.next_hop == dest else
               nx.dijkstra_path_length(g, entry.next_hop, dest)) == pytest.approx(entry.cost)


@settings(max_examples=80, deadline=None)
@given(st.dictionaries(st.integers(0, 40),
                       st.tuples(st.integers(0, 50), st.integers(0, 50)), min_size=1, max_size=12))
def test_rng_matches_brute_force_definition(raw):
    pos = {k: (float(x), float(y)) for k, (x, y) in raw.items()}
    edges = ng.rng_edges(pos)
    names = list(pos)
    for i, a in enumerate(names):
        for b in names[i + 1:]:
            d = math.dist(pos[a], pos[b])
            blocked = any(max(math.dist(pos[a], pos[w]), math.dist(pos[b], pos[w])) < d
                          for w in names if w not in (a, b))
            assert (frozenset((a, b)) in edges) == (not blocked)
    # RNG of points in general position is connected (it contains the minimum spanning tree)
    if len(set(pos.values())) == len(pos):
        assert len(ng.connected_components(ng.from_edges([tuple(e) for e in edges], nodes=pos))) == 1
