"""Potential-field self-deployment (paper 001, eqs. 15 and 16): forces, neighbourhoods, convergence."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
from hypothesis import example, given, settings
from hypothesis import strategies as st
from numpy.typing import NDArray

from erni.strategies.potential import (
    EPS,
    SpreadConfig,
    forces,
    mean_nn_distance,
    nearest_on_circles,
    nearest_on_segments,
    neighbourhoods,
    robot_command,
    simulate,
    spread_step,
    wrap,
)


def test_pair_force_pushes_apart_when_close_and_pulls_when_far():
    cfg = SpreadConfig(distance=5.0, chi=0.0)
    close = np.array([[0.0, 0.0], [2.0, 0.0]])
    f, _ = forces(close, np.zeros(2), cfg)
    assert f[0] == pytest.approx([-3.0, 0.0]) and f[1] == pytest.approx([3.0, 0.0])
    far = np.array([[0.0, 0.0], [7.0, 0.0]])
    f, _ = forces(far, np.zeros(2), cfg)
    assert f[0] == pytest.approx([2.0, 0.0])
    out_of_range = np.array([[0.0, 0.0], [20.0, 0.0]])
    f, _ = forces(out_of_range, np.zeros(2), cfg)
    assert f == pytest.approx(np.zeros((2, 2)))


def test_heading_torque_turns_toward_the_neighbourhood_centre():
    cfg = SpreadConfig(chi=1.0)
    pos = np.array([[0.0, 0.0], [0.0, 5.0]])
    _, tq = forces(pos, np.array([0.0, 0.0]), cfg)
    assert tq[0] == pytest.approx(math.pi / 2)   # centre straight up, heading along +x
    assert tq[1] == pytest.approx(-math.pi / 2)


def test_walls_and_obstacles_keep_their_own_distances():
    cfg = SpreadConfig(distance=5.0, wall_distance=2.0, obstacle_distance=1.5, chi=0.0)
    pos = np.array([[0.0, 14.0]])
    f, _ = forces(pos, np.zeros(1), cfg, walls=[[-50, 15, 50, 15]])
    assert f[0] == pytest.approx([0.0, -1.0])  # 1 m from the wall, 2 m wanted: pushed down by 1
    f, _ = forces(np.array([[0.0, 0.0]]), np.zeros(1), cfg, obstacles=[[3.0, 0.0, 1.0]])
    assert f[0] == pytest.approx([0.5, 0.0])   # nearest point 2 m away, 1.5 wanted: pulled by 0.5


def test_nearest_points_on_walls_and_circles():
    walls = np.array([[-10.0, 15.0, 10.0, 15.0], [3.0, 0.0, 3.0, 4.0], [1.0, 1.0, 1.0, 1.0]])  # the last: a point
    assert nearest_on_segments([2.0, 2.0], walls) == pytest.approx(np.array([[2.0, 15.0], [3.0, 2.0], [1.0, 1.0]]))
    assert nearest_on_segments([20.0, 0.0], walls) == pytest.approx(np.array([[10.0, 15.0], [3.0, 0.0], [1.0, 1.0]]))
    circles = np.array([[3.0, 4.0, 1.0], [0.0, 0.0, 2.0]])
    assert nearest_on_circles([0.0, 0.0], circles) == pytest.approx(np.array([[2.4, 3.2], [0.0, 0.0]]))  # inside: p itself
    assert nearest_on_circles([0.5, 0.0], circles)[1] == pytest.approx([0.5, 0.0])
    assert nearest_on_segments([0.0, 0.0], np.zeros((0, 4))).shape == (0, 2)
    assert nearest_on_circles([0.0, 0.0], np.zeros((0, 3))).shape == (0, 2)


def test_walls_count_only_within_the_sensing_range():
    # paper 001, 3.3: the boundary belongs to the neighbourhood only inside the sensing range
    cfg = SpreadConfig(distance=5.0, wall_distance=2.5, range=6.0, sensing=2.5, chi=0.0, obstacle_weight=2.0)
    wall = [[-50, 15, 50, 15]]
    f, _ = forces(np.array([[0.0, 11.0]]), np.zeros(1), cfg, walls=wall)
    assert f[0] == pytest.approx([0.0, 0.0])    # 4 m away: beyond sensing, not pulled toward the wall
    f, _ = forces(np.array([[0.0, 13.0]]), np.zeros(1), cfg, walls=wall)
    assert f[0] == pytest.approx([0.0, -1.0])   # 2 m away, 2.5 wanted, w = 2: pushed off by 1
    f, _ = forces(np.array([[0.0, 11.0]]), np.zeros(1), dataclasses.replace(cfg, sensing=None), walls=wall)
    assert f[0] == pytest.approx([0.0, 3.0])    # sensed at the neighbourhood range: pulled by w (4 - 2.5)
    with pytest.raises(ValueError, match="sensing"):
        SpreadConfig(sensing=0.0)


@pytest.mark.parametrize("rng_m,low,high", [(5.0, 1.0, 1.1), (10.0, 0.0, 0.5)])
def test_the_settled_spacing_depends_on_the_neighbourhood_range(rng_m, low, high):
    # every robot within R pulls toward d: with R = d no pair pulls and nobody ends closer than d;
    # with R = 2 d the start bunch never leaves everyone's range and stays bunched
    rng = np.random.default_rng(5)
    pos = rng.uniform(-1, 1, (12, 2))
    cfg = SpreadConfig(distance=5.0, range=rng_m, neighbourhood="physical", model="holonomic")
    final, _ = simulate(pos, rng.uniform(-math.pi, math.pi, 12), cfg, 150.0)
    d = np.hypot(*(final[:, None, :] - final[None, :, :]).transpose(2, 0, 1))
    np.fill_diagonal(d, np.inf)
    assert low * 5.0 - 0.02 <= d.min(axis=1).min() and d.min(axis=1).mean() <= high * 5.0


def test_delaunay_neighbourhood_is_symmetric_and_local():
    rng = np.random.default_rng(0)
    pos = rng.uniform(0, 30, (40, 2))
    nb = neighbourhoods(pos, "delaunay")
    for i, js in enumerate(nb):
        assert len(js) >= 2
        for j in js:
            assert i in nb[j]
    phys = neighbourhoods(pos, "physical", 6.0)
    assert all(np.all(np.hypot(*(pos[js] - pos[i]).T) <= 6.0) for i, js in enumerate(phys))
    # robots on one line (no triangulation): each and the next along it, in any order given
    assert [list(x) for x in neighbourhoods(np.array([[0, 0], [2, 0], [1, 0]]), "delaunay")] == \
        [[2], [2], [0, 1]]
    assert [list(x) for x in neighbourhoods(np.array([[0, 0], [3, 4]]), "gabriel")] == [[1], [0]]


@settings(max_examples=60, deadline=None)
@given(st.lists(st.tuples(st.integers(-40, 40), st.integers(-40, 40)), min_size=2, max_size=25, unique=True))
@example([(0, 0), (1, 0), (-1, 0)])  # on one line: no triangulation to start from
def test_gabriel_neighbourhood_is_the_brute_force_gabriel_graph(points):
    """An edge (i, j) iff no other robot lies in the closed disc on the diameter p_i p_j (brute
    force over all pairs here; the strategy only tries the Delaunay edges)."""
    pos = np.array(points, dtype=float) * 0.5   # on a grid: collinear and cocircular cases come up
    nb = neighbourhoods(pos, "gabriel")
    n = len(pos)
    for i in range(n):
        for j in range(i + 1, n):
            mid, r2 = (pos[i] + pos[j]) / 2, np.sum((pos[i] - pos[j]) ** 2) / 4
            empty = all(np.sum((pos[k] - mid) ** 2) > r2 + 1e-9 for k in range(n) if k not in (i, j))
            assert (j in nb[i]) == empty, (i, j, empty)
            assert (i in nb[j]) == (j in nb[i])


def test_gabriel_drops_the_long_hull_edges_a_delaunay_neighbourhood_has():
    # a flat triangle: Delaunay links the two ends across the hull, Gabriel does not
    pos = np.array([[0.0, 0.0], [10.0, 0.0], [5.0, 1.0]])
    assert [list(x) for x in neighbourhoods(pos, "delaunay")] == [[1, 2], [0, 2], [0, 1]]
    assert [list(x) for x in neighbourhoods(pos, "gabriel")] == [[2], [2], [0, 1]]
    # four robots on a circle: no diagonal (each has the other two on its circle), a centre robot
    # on every side's circle leaves it linked to the corners only
    square = np.array([[0.0, 0.0], [2.0, 0.0], [2.0, 2.0], [0.0, 2.0]])
    assert [list(x) for x in neighbourhoods(square, "gabriel")] == [[1, 3], [0, 2], [1, 3], [0, 2]]
    centred = np.vstack([square, [[1.0, 1.0]]])
    assert [list(x) for x in neighbourhoods(centred, "gabriel")] == [[4], [4], [4], [4], [0, 1, 2, 3]]
    with pytest.raises(Exception, match="neighbourhood: expected one of physical, delaunay, gabriel"):
        SpreadConfig(neighbourhood="voronoi")


def test_nonholonomic_velocity_stays_along_the_heading():
    rng = np.random.default_rng(3)
    pos = rng.uniform(-1, 1, (8, 2))
    th = rng.uniform(-math.pi, math.pi, 8)
    v, om = np.zeros((8, 2)), np.zeros(8)
    cfg = SpreadConfig(model="nonholonomic")
    for _ in range(20):
        pos, th, v, om = spread_step(pos, th, v, om, cfg)
        side = v[:, 0] * np.sin(th) - v[:, 1] * np.cos(th)   # x' sin(theta) - y' cos(theta) = 0
        assert np.abs(side) == pytest.approx(np.zeros(8), abs=1e-9)


@pytest.mark.parametrize("model,mode,rng_m,low", [
    ("holonomic", "physical", 6.0, 0.9),
    ("nonholonomic", "physical", 6.0, 0.8),
    ("holonomic", "delaunay", 15.0, 0.75),
])
def test_spreading_converges_near_the_desired_distance(model, mode, rng_m, low):
    rng = np.random.default_rng(11)
    pos = rng.uniform(-1, 1, (12, 2))
    th = rng.uniform(-math.pi, math.pi, 12)
    start = mean_nn_distance(pos)
    cfg = SpreadConfig(distance=5.0, gain=2.0, dt=0.2, range=rng_m, neighbourhood=mode, model=model)
    final, final_th = simulate(pos, th, cfg, 60.0)
    nn = mean_nn_distance(final)
    assert start < 1.0
    assert low * 5.0 <= nn <= 1.1 * 5.0, nn
    # settled: another 10 s barely moves anyone
    later, _ = simulate(final, final_th, cfg, 10.0)
    assert np.max(np.hypot(*(later - final).T)) < 0.5


def test_robot_command_drives_toward_a_far_neighbour():
    cfg = SpreadConfig(distance=5.0, model="nonholonomic", chi=0.0, vmax=0.5)
    pos = np.array([[0.0, 0.0], [10.0, 0.0]])
    v, _ = robot_command(pos, 0.0, 0.0, 0.0, 0, cfg)
    assert 0 < v <= 0.5
    v, _w = robot_command(pos, math.pi, 0.0, 0.0, 0, cfg)
    assert v < 0  # facing away: backing up is allowed by (16)


def test_a_holonomic_robot_at_its_distance_stands_still_whatever_its_heading():
    # the pair is at d: no spring force; the wheeled robot faces across the pair, which the
    # heading term of (15) would turn toward, not drive sideways
    cfg = SpreadConfig(distance=5.0, model="holonomic", vmax=0.5)
    pos = np.array([[0.0, 0.0], [5.0, 0.0]])
    assert robot_command(pos, math.pi / 2, 0.0, 0.0, 0, cfg) == (0.0, 0.0)
    v, _ = robot_command(np.array([[0.0, 0.0], [3.0, 0.0]]), math.pi / 2, 0.0, 0.0, 0, cfg)
    assert v == pytest.approx(0.0, abs=1e-9)  # pushed along x, facing y: it turns first (cos 90 deg = 0)
    v, _ = robot_command(np.array([[0.0, 0.0], [3.0, 0.0]]), 0.0, 0.0, 0.0, 0, cfg)
    assert v == pytest.approx(-0.5)  # facing the push's opposite: backs away, at most vmax


def test_bad_config_is_named():
    with pytest.raises(ValueError, match="neighbourhood"):
        SpreadConfig(neighbourhood="voronoi")
    with pytest.raises(ValueError, match="dt"):
        SpreadConfig(dt=0)


def forces_robot_by_robot(p: NDArray[np.float64], th: NDArray[np.float64], cfg: SpreadConfig,
                          obs: NDArray[np.float64], wal: NDArray[np.float64]
                          ) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Equations 15/16's force and torque computed robot by robot: the reference for `forces`."""
    n = len(p)
    nbrs = neighbourhoods(p, cfg.neighbourhood, cfg.range)
    force = np.zeros((n, 2))
    torque = np.zeros(n)
    w = cfg.weight
    for i in range(n):
        pts = [p[nbrs[i]]]
        want = [np.full(len(nbrs[i]), cfg.distance)]
        wobj = cfg.obstacle_weight if cfg.obstacle_weight is not None else float(max(1, len(nbrs[i]))) * w
        sensing = cfg.range if cfg.sensing is None else cfg.sensing
        weights = [np.full(len(nbrs[i]), w)]
        if len(obs):
            q = nearest_on_circles(p[i], obs)
            near = np.hypot(*(q - p[i]).T) <= sensing
            pts.append(q[near])
            want.append(np.full(int(near.sum()), cfg.obstacle_distance))
            weights.append(np.full(int(near.sum()), wobj))
        if len(wal):
            q = nearest_on_segments(p[i], wal)
            near = np.hypot(*(q - p[i]).T) <= sensing
            pts.append(q[near])
            want.append(np.full(int(near.sum()), cfg.wall_distance))
            weights.append(np.full(int(near.sum()), wobj))
        others = np.concatenate(pts)
        if len(others) == 0:
            continue
        dij = np.concatenate(want)
        wij = np.concatenate(weights)
        rel = others - p[i]
        dist = np.hypot(rel[:, 0], rel[:, 1])
        ok = dist > EPS
        unit = np.zeros_like(rel)
        unit[ok] = rel[ok] / dist[ok, None]
        if not ok.all():  # coincident: push apart in a direction fixed by the robot's index
            ang = 2.0 * math.pi * ((i * 0.618034) % 1.0)
            unit[~ok] = (math.cos(ang), math.sin(ang))
        force[i] = ((wij * (dist - dij))[:, None] * unit).sum(axis=0)
        # heading term: turn toward the neighbourhood's weighted centre s = mean(w (p_j - p_i))
        s = (wij[:, None] * rel).mean(axis=0)
        s2 = float(s @ s)
        if s2 > 1e-6:
            s2 = max(s2, (0.1 * cfg.distance) ** 2)  # regularised: |s| floored at d / 10
            err = float(wrap(math.atan2(s[1], s[0]) - th[i]))
            torque[i] = cfg.chi * err
            force[i] += cfg.chi * err * float(wij.mean()) * np.array([-s[1], s[0]]) / s2
    return force, torque


coord = st.floats(-20.0, 20.0, allow_nan=False)


@settings(max_examples=60, deadline=None)
@given(st.lists(st.tuples(coord, coord), min_size=1, max_size=25), st.integers(0, 3), st.integers(0, 3),
       st.sampled_from(["physical", "delaunay"]), st.data())
def test_forces_equal_the_robot_by_robot_sums(points: list[tuple[float, float]], n_obs: int, n_walls: int,
                                              hood: str, data: st.DataObject) -> None:
    p = np.array(points)
    p[len(p) // 2:] = np.round(p[len(p) // 2:])  # some coincident robots too
    th = np.array([data.draw(st.floats(-math.pi, math.pi)) for _ in points])
    obs = np.array([[data.draw(coord), data.draw(coord), data.draw(st.floats(0.1, 3.0))] for _ in range(n_obs)])
    wal = np.array([[data.draw(coord) for _ in range(4)] for _ in range(n_walls)])
    cfg = SpreadConfig(neighbourhood=hood, range=data.draw(st.floats(1.0, 30.0)), chi=data.draw(st.floats(0.0, 2.0)),
                       sensing=data.draw(st.one_of(st.none(), st.floats(0.5, 30.0))),
                       obstacle_weight=data.draw(st.one_of(st.none(), st.floats(0.1, 5.0))))
    obs, wal = obs.reshape(-1, 3), wal.reshape(-1, 4)
    f, tq = forces(p, th, cfg, obs, wal)
    rf, rtq = forces_robot_by_robot(p, th, cfg, obs, wal)
    assert f == pytest.approx(rf, rel=1e-9, abs=1e-9)
    assert tq == pytest.approx(rtq, rel=1e-9, abs=1e-9)


@settings(max_examples=60, deadline=None)
@given(st.lists(st.tuples(coord, coord), max_size=40), st.floats(0.5, 30.0))
def test_physical_neighbourhoods_are_every_robot_within_range(points: list[tuple[float, float]], rng: float) -> None:
    p = np.array(points, dtype=float).reshape(-1, 2)
    d = np.hypot(p[:, None, 0] - p[None, :, 0], p[:, None, 1] - p[None, :, 1])
    np.fill_diagonal(d, np.inf)
    clear = np.abs(d - rng) > 1e-9  # a neighbour at the range to the last bit may fall either side
    got = neighbourhoods(p, "physical", rng)
    for i in range(len(p)):
        want = set(np.flatnonzero(d[i] <= rng).tolist())
        assert {j for j in got[i].tolist() if clear[i, j]} == {j for j in want if clear[i, j]}
        assert list(got[i]) == sorted(got[i])
