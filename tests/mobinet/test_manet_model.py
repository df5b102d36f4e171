"""The simulated MANET model: radio, neighbours, routes, articulation points, known positions."""

from __future__ import annotations

import math

import networkx as nx
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from erni.sim.manet import MAX_METRIC, METRIC_UNIT, ManetNetwork, RadioModel, link_metric, link_metrics
from erni.sim.manet_scenario import ScenarioError, load_scenario
from tests.mobinet.conftest import line_network


def test_radio_quality_is_lossless_then_falls_to_zero_at_range():
    radio = RadioModel(100.0, 50.0)
    assert radio.quality(0) == radio.quality(50) == 1.0
    assert radio.quality(75) == pytest.approx(0.5)
    assert radio.quality(100) == radio.quality(150) == 0.0
    qs = [radio.quality(d) for d in range(0, 120, 5)]
    assert qs == sorted(qs, reverse=True)


@given(st.floats(0.01, 1.0))
def test_range_for_a_quality_is_the_longest_link_that_still_has_it(q):
    radio = RadioModel(8.0, 4.0)
    r = radio.range_for(q)
    assert radio.quality(r) == pytest.approx(q)
    assert radio.quality(r + 0.01) < q


def test_range_for_rejects_a_quality_outside_0_1():
    with pytest.raises(ValueError, match=r"link quality must be in \(0, 1\], got 0"):
        RadioModel(8.0, 4.0).range_for(0.0)


def test_radio_and_node_input_errors_are_clear():
    with pytest.raises(ValueError, match="lossless_range must be in"):
        RadioModel(10.0, 20.0)
    net = ManetNetwork(RadioModel(10.0, 5.0))
    net.add_node("a", 0, 0)
    with pytest.raises(ValueError, match="already exists"):
        net.add_node("a", 1, 1)
    with pytest.raises(ValueError, match="x must be a finite number"):
        net.move("a", float("nan"), 0)
    with pytest.raises(KeyError, match="unknown node 'zz'"):
        net.move("zz", 0, 0)


def test_link_metric_is_scaled_etx():
    assert link_metric(1.0) == METRIC_UNIT
    assert link_metric(0.5) == 4 * METRIC_UNIT
    assert link_metric(0.0) == 16776960


def test_line_neighbours_routes_and_cut_vertices():
    net = line_network()
    truth = net.truth()
    assert truth.articulation_points == {"robot2", "robot3", "robot4"}
    view = net.view("robot1")
    assert [n.name for n in view.neighbors] == ["robot2"]
    assert view.neighbors[0].quality == pytest.approx(0.8)
    route = view.routes["robot5"]
    assert (route.next_hop, route.hops) == ("robot2", 4)
    assert route.cost == 4 * link_metric(0.8)


def test_moves_change_neighbours_routes_and_articulation_points():
    net = line_network()
    before = net.version
    net.move("robot5", 150.0, 40.0)   # now close to robot3 and robot4
    assert net.version > before
    truth = net.truth()
    assert truth.articulation_points == {"robot2", "robot3"}
    assert {n.name for n in net.view("robot5").neighbors} >= {"robot3", "robot4"}
    net.move("robot2", 60.0, 200.0)   # robot1 is cut off
    truth = net.truth()
    assert len(truth.components) == 3
    assert net.view("robot1").routes == {}
    assert "robot1" not in net.view("robot3").routes


def test_weak_links_are_heard_but_not_used_for_routing():
    net = ManetNetwork(RadioModel(100.0, 50.0, min_quality=0.3))
    net.add_node("a", 0, 0)
    net.add_node("b", 90, 0)       # quality 0.2: heard, not symmetric
    nb = net.view("a").neighbors
    assert [(n.name, n.symmetric) for n in nb] == [("b", False)]
    assert net.view("a").routes == {}


def test_positions_spread_within_a_component_and_go_stale_across_a_partition():
    net = line_network()
    net.set_position("robot3", 121.0, 1.0, 90.0)
    assert net.view("robot1").positions["robot3"].x == 121.0
    net.move("robot2", 60.0, 200.0)            # robot1 alone now
    net.set_position("robot3", 130.0, 0.0, 0.0)
    assert net.view("robot5").positions["robot3"].x == 130.0
    assert net.view("robot1").positions["robot3"].x == 121.0   # stale: partitioned
    net.move("robot2", 60.0, 0.0)              # healed: the newest report spreads
    assert net.view("robot1").positions["robot3"].x == 130.0
    assert net.view("robot3").position_updates == 2


def test_gps_mode_reports_moves():
    net = ManetNetwork(RadioModel(100.0, 50.0), gps=True)
    net.add_node("a", 0, 0)
    net.add_node("b", 10, 0)
    net.move("b", 20, 5)
    assert (net.view("a").positions["b"].x, net.view("a").positions["b"].y) == (20.0, 5.0)


@settings(max_examples=40, deadline=None)
@given(st.lists(st.tuples(st.floats(0, 300), st.floats(0, 300)), min_size=2, max_size=14))
def test_truth_matches_networkx_on_random_layouts(points):
    net = ManetNetwork(RadioModel(100.0, 40.0, 0.1))
    for i, (x, y) in enumerate(points):
        net.add_node(f"n{i}", x, y)
    g = nx.Graph()
    g.add_nodes_from(net.names())
    for i, (ax, ay) in enumerate(points):
        for j in range(i + 1, len(points)):
            q = net.radio.quality(math.dist((ax, ay), points[j]))
            if q >= 0.1:
                g.add_edge(f"n{i}", f"n{j}", weight=link_metric(q))
    truth = net.truth()
    assert truth.articulation_points == set(nx.articulation_points(g))
    costs = nx.single_source_dijkstra_path_length(g, "n0")
    routes = net.view("n0").routes
    assert set(routes) == set(costs) - {"n0"}
    for dest, r in routes.items():
        assert r.cost == pytest.approx(costs[dest])


@settings(max_examples=60, deadline=None)
@given(st.lists(st.floats(1e-4, 1.0) | st.sampled_from([1.0, 0.5, 0.25, 0.1, 2 ** -0.5, 1e-4]), min_size=1, max_size=30))
def test_link_metrics_together_are_link_metric_one_by_one(qualities):
    assert link_metrics(np.array(qualities)).tolist() == [link_metric(q) for q in qualities]
    assert link_metrics(np.array([1e-4])).tolist() == [MAX_METRIC]  # capped


@settings(max_examples=40, deadline=None)
@given(st.lists(st.tuples(st.floats(0, 300), st.floats(0, 300)), min_size=2, max_size=14),
       st.sampled_from([(100.0, 40.0, 0.1), (100.0, 0.0, 0.3), (50.0, 50.0, 1.0)]))
def test_the_truths_links_are_the_radios_quality_pair_by_pair(points, radio):
    """Every pair closer than the radio's range is a link with the quality its distance gives, in
    the order of the pairs; those of at least min_quality carry their metric both ways."""
    net = ManetNetwork(RadioModel(*radio))
    for i, (x, y) in enumerate(points):
        net.add_node(f"n{i}", x, y)
    want = {}
    for i, (ax, ay) in enumerate(points):
        for j in range(i + 1, len(points)):
            q = net.radio.quality(math.dist((ax, ay), points[j]))
            if q > 0:
                want[frozenset((f"n{i}", f"n{j}"))] = q
    truth = net.truth()
    assert list(truth.links) == list(want)
    for key, q in want.items():
        assert truth.links[key] == pytest.approx(q, rel=1e-12, abs=1e-12)
        a, b = sorted(key)
        if q >= radio[2] + 1e-9:
            assert truth.symmetric[a][b] == truth.symmetric[b][a] == link_metric(truth.links[key])
        elif q < radio[2] - 1e-9:
            assert b not in truth.symmetric[a] and a not in truth.symmetric[b]


def test_scenario_files(tmp_path):
    good = load_scenario("examples/net-line.toml")
    net = good.build()
    assert net.names() == ["robot1", "robot2", "robot3", "robot4", "robot5"]
    assert good.ports()["robot2"] == 1162
    bad = tmp_path / "bad.toml"
    bad.write_text('comm_range = 100\nlossless_range = 50\nnodes = [{name = "a", x = 0, y = 0}]\n'
                   'moves = [{at = 1, node = "zz", x = 0, y = 0}]\n')
    with pytest.raises(ScenarioError, match="unknown node 'zz'"):
        load_scenario(bad)
    bad.write_text("comm_range = 'far'\n")
    with pytest.raises(ScenarioError, match="comm_range: Input should be a valid number"):
        load_scenario(bad)
    bad.write_text("nodes = [\n")
    with pytest.raises(ScenarioError, match="not valid TOML"):
        load_scenario(bad)


def test_moves_that_change_no_link_change_nothing_served():
    net = ManetNetwork(RadioModel(100.0, 50.0))
    net.add_node("a", 0, 0)
    net.add_node("b", 10, 0)
    net.add_node("c", 300, 0)                  # out of everyone's range
    before, view = net.version, net.view("a")
    net.move("b", 12, 3)                       # a-b stays loss-free: nothing served changes
    assert net.truth().positions["b"] == (12.0, 3.0)
    assert net.version == before
    assert net.view("a") is view
    net.move("c", 80, 0)                       # c joins through lossy links
    assert net.version > before
    assert {n.name for n in net.view("a").neighbors} == {"b", "c"}
    before = net.version
    net.set_position("a", 1, 1)                # a report is served: version moves
    assert net.version > before


class Clock:
    """A network clock the test moves by hand."""

    def __init__(self) -> None:
        self.t = 100.0

    def __call__(self) -> float:
        return self.t


def test_hello_counters_grow_with_time_and_the_link_quality():
    clock = Clock()
    net = ManetNetwork(RadioModel(100.0, 50.0, 0.1), clock=clock)
    net.add_node("a", 0, 0)
    net.add_node("b", 75, 0)                 # quality 0.5
    assert net.hello_counts("a", "b") == (0, 0)
    clock.t += 40.0                          # 20 HELLO intervals
    assert net.hello_counts("a", "b") == (10, 20)
    net.move("b", 50, 0)                     # loss-free from now on
    clock.t += 20.0
    assert net.hello_counts("b", "a") == (20, 30)
    net.move("b", 500, 0)                    # gone: nothing more is expected
    clock.t += 60.0
    assert net.hello_counts("a", "b") == (20, 30)
    assert net.link_since("a", "b") is None
    net.move("b", 50, 0)                     # back: the counters go on from where they were
    assert net.link_since("a", "b") == clock.t
    clock.t += 4.0
    assert net.hello_counts("a", "b") == (22, 32)


@settings(max_examples=60, deadline=None)
@given(st.lists(st.tuples(st.floats(0, 3), st.floats(0, 150)), min_size=1, max_size=12))
def test_hello_counters_never_go_down(steps):
    clock = Clock()
    net = ManetNetwork(RadioModel(100.0, 50.0, 0.1), clock=clock)
    net.add_node("a", 0, 0)
    net.add_node("b", 60, 0)
    last = (0, 0)
    for dt, x in steps:
        clock.t += dt
        net.move("b", x, 0)
        now = net.hello_counts("a", "b")
        assert now[0] >= last[0] and now[1] >= last[1] and now[0] <= now[1]
        last = now


def test_neighbour_set_changes_ansn_and_recalculations_are_counted():
    net = line_network()
    c = net.view("robot3").counters
    net.move("robot5", 150.0, 40.0)          # robot5 becomes robot3's neighbour
    after = net.view("robot3").counters
    assert after.neighbor_changes == c.neighbor_changes + 1
    assert after.ansn == c.ansn + 1          # its advertised neighbours changed
    assert after.mpr_recalcs == c.mpr_recalcs + 1
    assert after.route_recalcs == c.route_recalcs + 1
    far = net.view("robot1").counters
    assert far.neighbor_changes == 1          # robot2, when it came; robot5 never was its neighbour
    net.move("robot5", 150.0, 40.0)           # no link changes: nothing is counted
    assert net.view("robot1").counters == far
    net.move("robot2", 60.0, 200.0)           # robot1 loses its only neighbour
    alone = net.view("robot1").counters
    assert (alone.neighbor_changes, alone.ansn) == (far.neighbor_changes + 1, far.ansn + 1)
    assert alone.route_recalcs == far.route_recalcs + 1
    assert net.view("robot1").ansn == {"robot1": alone.ansn}


@settings(max_examples=60, deadline=None)
@given(st.lists(st.tuples(st.integers(0, 4), st.floats(-120, 120), st.floats(-120, 120)), min_size=1, max_size=25),
       st.sampled_from([(100.0, 50.0), (100.0, 100.0), (100.0, 0.0)]))
def test_the_truth_kept_across_moves_is_the_truth_worked_out_afresh(moves, ranges):
    """A move that changes no pair's link quality keeps the links, routes, components and cut
    vertices and takes the new positions; whatever the moves, that is what a fresh computation
    gives, and every HELLO count matches a network that only ever computed afresh."""
    clock = Clock()
    nets = [ManetNetwork(RadioModel(*ranges), clock=clock) for _ in range(2)]
    for net in nets:
        for i, (x, y) in enumerate([(0, 0), (40, 0), (80, 0), (0, 60), (200, 0)]):
            net.add_node(f"n{i}", x, y)
    kept, fresh = nets
    for node, x, y in moves:
        clock.t += 0.75
        kept.move(f"n{node}", x, y)
        fresh._qualities = None  # the reference works the truth out again at every move
        fresh.move(f"n{node}", x, y)
        want, got = fresh.truth(), kept.truth()
        assert want is not got
        assert got.positions == want.positions
        assert got.links == want.links and got.symmetric == want.symmetric
        assert sorted(map(sorted, got.components)) == sorted(map(sorted, want.components))
        assert got.articulation_points == want.articulation_points
        assert kept.version == fresh.version  # what the nodes serve moved (or not) alike
    clock.t += 3.0
    for a in range(5):
        for b in range(5):
            if a != b:  # seconds heard are exact; delivered ones are summed in other steps (rounding)
                (got_delivered, got_heard), (want_delivered, want_heard) = (
                    kept.hello_counts(f"n{a}", f"n{b}"), fresh.hello_counts(f"n{a}", f"n{b}"))
                assert got_heard == want_heard and abs(got_delivered - want_delivered) <= 1


def _graphs(nodes: int = 5) -> st.SearchStrategy[dict[str, dict[str, int]]]:
    """Symmetric graphs over n0..n4 with link metrics from a small set (so that changes are likely)."""
    pairs = [(f"n{a}", f"n{b}") for a in range(nodes) for b in range(a + 1, nodes)]
    return st.lists(st.sampled_from([None, 256, 512]), min_size=len(pairs), max_size=len(pairs)).map(
        lambda ms: {n: {m: k for (a, b), k in zip(pairs, ms) if k is not None for n2, m in ((a, b), (b, a))
                        if n2 == n} for n in (f"n{i}" for i in range(nodes))})


@given(_graphs(), _graphs(), st.integers(0, 4))
def test_two_hop_change_is_a_change_of_the_neighbour_node_metric_set(old, new, me):
    """The MPR recalculation counter's test, against its definition: the set of (neighbour, node,
    metric) two hops out, for the neighbours the node has before and after."""
    from erni.sim.manet import two_hop_changed

    name = f"n{me}"
    neighbors = new[name].keys()
    two_old = {(n, m, k) for n in neighbors for m, k in old.get(n, {}).items() if m != name}
    two_new = {(n, m, k) for n in neighbors for m, k in new[n].items() if m != name}
    assert two_hop_changed(name, neighbors, old, new) == (two_old != two_new)


@given(_graphs(), _graphs(), st.sets(st.integers(0, 4)))
def test_a_components_edges_changed_is_a_change_of_its_edge_set(old, new, members):
    """The route recalculation counter's test, against its definition: the set of (node,
    neighbour, metric) edges leaving the component's nodes."""
    from erni.sim.manet import edges_changed

    comp = {f"n{i}" for i in members}
    edges_old = {(a, b, m) for a in comp for b, m in old.get(a, {}).items()}
    edges_new = {(a, b, m) for a in comp for b, m in new.get(a, {}).items()}
    assert edges_changed(comp, old, new) == (edges_old != edges_new)
