"""WiDep (paper 000, Algorithm 1): step bound, auxiliary PoI, and connectivity kept at every round."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from erni.netgraph import rng_neighbors
from erni.strategies.widep import (
    auxiliary_poi,
    comm_adjacency,
    connected,
    covered,
    farthest_rng,
    max_step,
    rng_adjacency,
    segment_hits,
    widep_round,
    widep_step,
)


def test_step_bound_is_half_the_slack_to_the_farthest_rng_neighbour():
    # u at origin; v at 3 m (RNG neighbour); w at 4 m behind v (not an RNG neighbour of u: v witnesses)
    pos = np.array([[0.0, 0.0], [3.0, 0.0], [6.5, 0.0]])
    assert farthest_rng(pos, 0, 4.5) == pytest.approx(3.0)
    assert max_step(pos, 0, 4.5) == pytest.approx(0.75)
    step = widep_step(pos, 0, (0.0, 10.0), 4.5)
    assert step.length == pytest.approx(0.75)
    assert step.target == pytest.approx([0.0, 0.75])
    assert not step.auxiliary and not step.arrived


def test_rng_agrees_with_netgraph():
    rng = np.random.default_rng(5)
    pos = rng.uniform(0, 8, (12, 2))
    adj = rng_adjacency(pos, 4.0)
    comm = comm_adjacency(pos, 4.0)
    names = {i: (float(p[0]), float(p[1])) for i, p in enumerate(pos)}
    edges = [(i, j) for i in range(12) for j in range(i + 1, 12) if comm[i, j]]
    for i in range(12):
        assert set(np.flatnonzero(adj[i])) == rng_neighbors(names, i, edges)


def test_arrived_robot_does_not_move_and_short_last_step_stops_at_the_poi():
    pos = np.array([[0.0, 0.0], [1.0, 0.0]])
    at = widep_step(pos, 0, (0.1, 0.1), 4.5, tolerance=0.5)
    assert at.arrived and at.length == 0.0
    near = widep_step(pos, 1, (1.0, 1.0), 4.5, tolerance=0.4)
    assert near.length == pytest.approx(0.8)
    assert math.dist(near.target, (1.0, 1.0)) <= 0.4


def test_obstacle_on_the_way_gives_an_auxiliary_poi_with_clear_legs():
    obstacles = np.array([[0.0, 5.0, 1.0]])
    p, poi = np.array([0.0, 0.0]), np.array([0.0, 10.0])
    aux = auxiliary_poi(p, poi, obstacles, margin=0.3)
    assert aux is not None
    assert not segment_hits(p, aux, obstacles, 0.3).any()
    assert not segment_hits(aux, poi, obstacles, 0.3).any()
    assert auxiliary_poi(p, (5.0, 0.0), obstacles) is None
    step = widep_step(np.array([p, [0.0, -1.0]]), 0, poi, 4.5, obstacles=obstacles)
    assert step.auxiliary and step.waypoint == pytest.approx(aux)


def test_team_reaches_the_poi_around_an_obstacle_connected_all_the_way():
    # the paper's demo: three robots near the base, PoI at (0, 11), R = 4.5 m, an obstacle on the way
    pos = np.array([[0.0, 0.0], [-1.0, -0.5], [1.0, -0.5], [0.0, -1.5]])
    movable = np.array([False, True, True, True])  # robot 0 is the base station
    obstacles = np.array([[0.0, 3.0, 0.6]])
    poi = (0.0, 7.0)
    rounds = 0
    done = False
    while not done and rounds < 300:
        pos, done = widep_round(pos, poi, 4.5, tolerance=0.5, obstacles=obstacles, separation=0.4,
                                movable=movable)
        rounds += 1
        assert connected(pos, 4.5), f"disconnected at round {rounds}"
        centres = obstacles[:, :2]
        assert np.min(np.hypot(*(pos[1:, None, :] - centres[None]).transpose(2, 0, 1))) > 0.6
    # a chain from the base cannot reach 7 m with 3 robots only if it breaks: it must be covered
    assert done, f"PoI not covered after {rounds} rounds: {pos.tolist()}"
    assert covered(pos, poi, 0.5)


# connected layouts grown like a random tree: each robot lands within R of an earlier one
growth = st.lists(st.tuples(st.floats(0, 1), st.floats(-math.pi, math.pi), st.floats(0.3, 0.99)),
                  min_size=2, max_size=9)


def grow(steps: list[tuple[float, float, float]], R: float) -> np.ndarray:
    pos = [np.zeros(2)]
    for pick, angle, frac in steps:
        parent = pos[min(int(pick * len(pos)), len(pos) - 1)]
        pos.append(parent + frac * R * np.array([math.cos(angle), math.sin(angle)]))
    return np.array(pos)


@settings(max_examples=60)
@given(growth, st.tuples(st.floats(-20, 20), st.floats(-20, 20)), st.floats(2.0, 6.0),
       st.sampled_from([0.0, 0.4]))
def test_connectivity_is_never_lost_from_any_connected_start(steps, poi, R, separation):
    pos = grow(steps, R)
    assert connected(pos, R)
    for _ in range(25):
        pos, done = widep_round(pos, poi, R, tolerance=0.5, separation=separation)
        assert connected(pos, R)
        if done:
            break


def test_bad_input_is_named():
    with pytest.raises(ValueError, match="positions"):
        widep_step(np.zeros(3), 0, (1, 1), 4.5)
    with pytest.raises(ValueError, match="R: expected a positive"):
        widep_step(np.zeros((2, 2)), 0, (1, 1), 0.0)
    with pytest.raises(ValueError, match="robot index"):
        widep_step(np.zeros((2, 2)), 5, (1, 1), 4.5)


def test_a_fixed_node_is_gone_round_as_an_obstacle_not_waited_for():
    pos = np.array([[0.0, 1.15], [0.0, 0.0]])  # a robot right behind a node that never moves
    poi = (0.0, -3.5)
    blocked = widep_step(pos, 0, poi, 4.5, separation=1.0, step_cap=0.6)
    assert blocked.length < 0.2 and np.hypot(*blocked.target) >= 0.999  # only creeps up to the separation
    round_it = widep_step(pos, 0, poi, 4.5, separation=1.0, step_cap=0.6, margin=0.4, fixed=[False, True])
    assert round_it.auxiliary and round_it.length > 0.4
    assert np.hypot(*round_it.target) > 0.9  # beside the node, not through it
    # widep_round's base station (not movable) is gone round the same way
    moved, _ = widep_round(pos, poi, 4.5, separation=1.0, step_cap=0.6, margin=0.4, movable=[True, False])
    assert np.allclose(moved[0], round_it.target) and np.allclose(moved[1], pos[1])
    with pytest.raises(ValueError, match="fixed: expected 2 booleans"):
        widep_step(pos, 0, poi, 4.5, separation=1.0, fixed=[True])
