"""PoI coverage with preserved connectivity: WiDep (paper 000, section 5.1 and Algorithm 1).

Every robot heads for the point of interest p along the unit vector Delta = d_p / |d_p| and
moves at most d = (R - d+(u)) / 2, where R is the communication range and d+(u) the distance
to its farthest RNG neighbour (the Relative Neighbourhood Graph of the communication graph,
whose edges are the pairs closer than R). Two RNG neighbours moving in opposite directions
therefore stay within R of each other, so a connected team stays connected when all robots
step at once from the same snapshot. A robot whose straight path to p crosses a known
obstacle heads for an auxiliary PoI beside the obstacle first.

Inputs and units (pure functions, no blackboard):
- `positions`: float array (N, 2) of robot positions (m); `i`: the index of the moving robot.
- `poi`: (2,) target point (m); `R`: communication range (m); `tolerance`: arrival radius (m).
- `obstacles`: array (M, 3) of circles (x, y, radius) in m, or None; `margin`: clearance (m)
  kept from obstacles; `separation`: distance (m) a step never closes below to another robot;
  `step_cap`: longest step (m); `witness_margin`, `slack` (m): robustness to stale positions
  for robots deciding asynchronously (a witness must be that much closer; R is reduced by slack).

Outputs: `widep_step` -> `Step` (target point, step length, the waypoint steered for,
whether it is an auxiliary PoI, whether the robot is at the PoI); `widep_round` -> new
positions (N, 2) and whether the PoI is covered (some robot within `tolerance`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from erni.blackboard.errors import UsageError

EPS = 1e-9


def _points(positions: ArrayLike) -> NDArray[np.float64]:
    pos = np.asarray(positions, dtype=float)
    if pos.ndim != 2 or pos.shape[1] != 2:
        raise UsageError(f"positions: expected an (N, 2) array of x, y in metres, got shape {pos.shape}")
    if not np.all(np.isfinite(pos)):
        raise UsageError("positions: expected finite coordinates")
    return pos


def _circles(obstacles: ArrayLike | None) -> NDArray[np.float64]:
    if obstacles is None:
        return np.zeros((0, 3))
    obs = np.asarray(obstacles, dtype=float).reshape(-1, 3) if np.size(obstacles) else np.zeros((0, 3))
    if np.any(obs[:, 2] < 0):
        raise UsageError("obstacles: expected circles (x, y, radius) with radius >= 0")
    return obs


def distances(positions: ArrayLike) -> NDArray[np.float64]:
    """Return the (N, N) matrix of Euclidean distances (m)."""
    pos = _points(positions)
    diff = pos[:, None, :] - pos[None, :, :]
    return np.hypot(diff[..., 0], diff[..., 1])


def comm_adjacency(positions: ArrayLike, R: float) -> NDArray[np.bool_]:
    """Return the boolean (N, N) adjacency of the communication graph: distinct robots within R."""
    d = distances(positions)
    adj = d <= R
    np.fill_diagonal(adj, False)
    return adj


def rng_adjacency(positions: ArrayLike, R: float) -> NDArray[np.bool_]:
    """Return the boolean (N, N) RNG of the communication graph (witnesses: every robot)."""
    d = distances(positions)
    n = len(d)
    adj = d <= R
    np.fill_diagonal(adj, False)
    rng = adj.copy()
    for u in range(n):
        for v in range(u + 1, n):
            if not adj[u, v]:
                continue
            witness = np.maximum(d[u], d[v]) < d[u, v]
            witness[u] = witness[v] = False
            if witness.any():
                rng[u, v] = rng[v, u] = False
    return rng


def farthest_rng(positions: ArrayLike, i: int, R: float, witness_margin: float = 0.0) -> float:
    """Return d+(u): the distance (m) from robot i to its farthest RNG neighbour (0 if none).

    With `witness_margin` > 0 a robot w only removes the edge u-v when it is that much closer
    to both (max(d(u,w), d(v,w)) < d(u,v) - margin): a robust RNG for positions that may be
    stale by up to margin / 2 per robot, as on robots deciding asynchronously.
    """
    pos = _points(positions)
    d = np.hypot(*(pos - pos[i]).T)
    best = 0.0
    for v in np.flatnonzero((d <= R) & (np.arange(len(pos)) != i)):
        dm = np.maximum(d, np.hypot(*(pos - pos[v]).T))
        dm[i] = dm[v] = math.inf
        if not np.any(dm < d[v] - witness_margin):
            best = max(best, float(d[v]))
    return best


def max_step(positions: ArrayLike, i: int, R: float, witness_margin: float = 0.0, slack: float = 0.0) -> float:
    """Return the largest connectivity-safe step (m) of robot i: (R - slack - d+(u)) / 2, never negative."""
    return max(0.0, (R - slack - farthest_rng(positions, i, R, witness_margin)) / 2.0)


def connected(positions: ArrayLike, R: float) -> bool:
    """True when the communication graph (robots within R) is connected (or has < 2 robots)."""
    adj = comm_adjacency(positions, R)
    n = len(adj)
    if n < 2:
        return True
    seen = np.zeros(n, dtype=bool)
    seen[0] = True
    frontier = [0]
    while frontier:
        u = frontier.pop()
        for v in np.flatnonzero(adj[u] & ~seen):
            seen[v] = True
            frontier.append(int(v))
    return bool(seen.all())


def segment_hits(a: ArrayLike, b: ArrayLike, obstacles: ArrayLike | None, margin: float = 0.0) -> NDArray[np.bool_]:
    """Return a boolean mask of the circles (x, y, r) that the segment a-b passes within r + margin of."""
    obs = _circles(obstacles)
    if len(obs) == 0:
        return np.zeros(0, dtype=bool)
    pa, pb = np.asarray(a, dtype=float), np.asarray(b, dtype=float)
    ab = pb - pa
    length2 = float(ab @ ab)
    centres = obs[:, :2]
    if length2 < EPS:
        s = np.zeros(len(obs))
    else:
        s = np.clip(((centres - pa) @ ab) / length2, 0.0, 1.0)
    nearest = pa + s[:, None] * ab
    hit: NDArray[np.bool_] = np.hypot(*(centres - nearest).T) < obs[:, 2] + margin
    return hit


def auxiliary_poi(p: ArrayLike, target: ArrayLike, obstacles: ArrayLike | None,
                  margin: float = 0.3, buffer: float = 0.15) -> NDArray[np.float64] | None:
    """Return an auxiliary PoI beside the first obstacle blocking p -> target, or None if clear.

    The path is blocked when it passes within radius + `margin` of an obstacle. The point lies
    on the perpendicular to p -> target through the obstacle's centre, on the side away from
    the centre, pushed out until both legs (p -> aux, aux -> target) clear that obstacle by
    `margin` + `buffer` (or 8 widenings were tried): a robot that stops within `buffer` of the
    point finds its way to the target clear, instead of a new auxiliary PoI a few cm away.
    """
    obs = _circles(obstacles)
    pa, pt = np.asarray(p, dtype=float), np.asarray(target, dtype=float)
    hits = segment_hits(pa, pt, obs, margin)
    if not hits.any():
        return None
    idx = np.flatnonzero(hits)
    first = idx[np.argmin(np.hypot(*(obs[idx, :2] - pa).T))]
    cx, cy, r = obs[first]
    centre = np.array([cx, cy])
    heading = pt - pa
    norm = float(np.hypot(*heading))
    u = heading / norm if norm > EPS else np.array([1.0, 0.0])
    normal = np.array([-u[1], u[0]])
    side = float(np.dot(centre - pa, normal))
    if abs(side) < EPS:  # dead centre: go left of the direction of travel
        side = -1.0
    direction = -normal if side > 0 else normal
    one = obs[first:first + 1]
    clear = margin + buffer
    reach = r + clear
    aux: NDArray[np.float64] = centre + direction * reach * 1.05
    for _ in range(8):
        aux = centre + direction * reach * 1.05
        if not segment_hits(pa, aux, one, clear).any() and not segment_hits(aux, pt, one, clear).any():
            break
        reach *= 1.25
    return aux


@dataclass(frozen=True)
class Step:
    """One robot's WiDep decision: where to go and why."""

    target: NDArray[np.float64]      # (2,) the point to move to (m)
    length: float           # distance to it (m)
    waypoint: NDArray[np.float64]    # (2,) the point steered for: the PoI or an auxiliary PoI (m)
    auxiliary: bool         # True when steering for an auxiliary PoI
    arrived: bool           # True when the robot is within tolerance of the PoI
    limit: float            # the connectivity bound (R - d+(u)) / 2 (m)


def _separation_limit(p: NDArray[np.float64], u: NDArray[np.float64], others: NDArray[np.float64], sep: float,
                      length: float) -> float:
    limit = length
    for q in others:
        w = p - q
        wu = float(w @ u)
        if wu >= 0:
            continue  # moving away from q
        ww = float(w @ w)
        if ww <= sep * sep:
            return 0.0  # already too close and approaching
        disc = wu * wu - ww + sep * sep
        if disc < 0:
            continue  # the line passes clear of q
        limit = min(limit, max(0.0, -wu - math.sqrt(disc)))
    return limit


def widep_step(positions: ArrayLike, i: int, poi: ArrayLike, R: float, *, tolerance: float = 0.5,
               obstacles: ArrayLike | None = None, margin: float = 0.3, separation: float = 0.0,
               step_cap: float | None = None, witness_margin: float = 0.0, slack: float = 0.0,
               fixed: ArrayLike | None = None) -> Step:
    """Return robot i's next WiDep move toward `poi` under the RNG connectivity bound.

    `witness_margin` and `slack` (m) make the bound robust to stale positions (see `farthest_rng`).
    `fixed` (boolean mask, default none): the nodes that never move (a control node, a base
    station). They count for connectivity, but a step goes round each as an obstacle of radius
    `separation` - `margin` (by an auxiliary PoI) instead of keeping `separation` from it and
    waiting for it to move, which it never does.
    """
    pos = _points(positions)
    if not 0 <= i < len(pos):
        raise UsageError(f"i: expected a robot index in 0..{len(pos) - 1}, got {i}")
    if not R > 0:
        raise UsageError(f"R: expected a positive communication range (m), got {R!r}")
    still = np.zeros(len(pos), dtype=bool) if fixed is None else np.array(fixed, dtype=bool).reshape(-1)
    if still.shape != (len(pos),):
        raise UsageError(f"fixed: expected {len(pos)} booleans, one per position, got {still.shape[0]}")
    still[i] = False
    if still.any() and separation > 0:
        around = np.column_stack([pos[still], np.full(int(still.sum()), max(0.0, separation - margin))])
        obstacles = np.vstack([_circles(obstacles), around])
    p = pos[i]
    goal = np.asarray(poi, dtype=float).reshape(2)
    limit = max_step(pos, i, R, witness_margin, slack)
    if float(np.hypot(*(goal - p))) <= tolerance:
        return Step(p.copy(), 0.0, goal, False, True, limit)
    aux = auxiliary_poi(p, goal, obstacles, margin)
    waypoint = goal if aux is None else aux
    heading = waypoint - p
    dist = float(np.hypot(*heading))
    u = heading / dist if dist > EPS else np.zeros(2)
    length = min(limit, dist if aux is not None else max(0.0, dist - 0.5 * tolerance))
    if step_cap is not None:
        length = min(length, step_cap)
    if separation > 0 and length > 0:
        others = pos[~still & (np.arange(len(pos)) != i)]
        wanted = length
        length = _separation_limit(p, u, others, separation, wanted)
        if length < 0.25 * wanted:  # a robot in the way: sidestep (the bound holds in any direction)
            for angle in (0.5, -0.5, 1.0, -1.0):
                c, s = math.cos(angle), math.sin(angle)
                turned = np.array([c * u[0] - s * u[1], s * u[0] + c * u[1]])
                side = _separation_limit(p, turned, others, separation, wanted)
                if side > length and not segment_hits(p, p + turned * side, obstacles, margin).any():
                    u, length = turned, side
                    break
    if length > 0 and aux is None and segment_hits(p, p + u * length, obstacles, margin).any():
        length = 0.0  # never step into an obstacle's clearance
    return Step(p + u * length, length, waypoint, aux is not None, False, limit)


def covered(positions: ArrayLike, poi: ArrayLike, tolerance: float) -> bool:
    """True when some robot is within `tolerance` (m) of the PoI."""
    pos = _points(positions)
    goal = np.asarray(poi, dtype=float).reshape(2)
    return bool(len(pos)) and bool(np.min(np.hypot(*(pos - goal).T)) <= tolerance)


def widep_round(positions: ArrayLike, poi: ArrayLike, R: float, *, tolerance: float = 0.5,
                obstacles: ArrayLike | None = None, margin: float = 0.3, separation: float = 0.0,
                step_cap: float | None = None, movable: ArrayLike | None = None
                ) -> tuple[NDArray[np.float64], bool]:
    """Move every movable robot one WiDep step from the same snapshot; return (positions, covered).

    Once the PoI is covered nobody moves. `movable` is a boolean mask (default: all robots);
    a node not movable (a base station) counts for connectivity and is gone round (`widep_step`'s
    `fixed`).
    """
    pos = _points(positions)
    if covered(pos, poi, tolerance):
        return pos.copy(), True
    mask = np.ones(len(pos), dtype=bool) if movable is None else np.asarray(movable, dtype=bool)
    new = pos.copy()
    for i in np.flatnonzero(mask):
        new[i] = widep_step(pos, int(i), poi, R, tolerance=tolerance, obstacles=obstacles,
                            margin=margin, separation=separation, step_cap=step_cap, fixed=~mask).target
    return new, covered(new, poi, tolerance)
