"""Kinematic mode: many robots stepped in-process as unicycles, with the radio model's connectivity.

For teams too large for one process per agent (paper 001's 120 robots on a laptop), the
experiments run the mission's pure strategy functions directly on arrays of poses. This
module holds what those runs share: a unicycle that drives toward targets under speed and
turn-rate limits, the radio's connectivity (links within R, components, reach of a base
station), the area covered by sensing discs, and a `Track` that records every pose.
Units: metres, seconds, radians.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.spatial import cKDTree

from erni import netgraph


def distances(pos: ArrayLike) -> NDArray[np.float64]:
    """Pairwise distances (N, N) of positions (N, 2)."""
    p = np.asarray(pos, dtype=float)
    d: NDArray[np.float64] = np.hypot(*(p[:, None, :] - p[None, :, :]).transpose(2, 0, 1))
    return d


def links(pos: ArrayLike, comm_range: float) -> dict[int, set[int]]:
    """The radio graph: i -> the nodes closer than `comm_range` (candidates from a k-d tree)."""
    p = np.asarray(pos, dtype=float).reshape(-1, 2)
    graph: dict[int, set[int]] = {i: set() for i in range(len(p))}
    if len(p) < 2 or comm_range <= 0:
        return graph
    pairs = cKDTree(p).query_pairs(comm_range * (1 + 1e-9), output_type="ndarray")
    if len(pairs):
        i, j = pairs[:, 0], pairs[:, 1]
        close = np.hypot(p[i, 0] - p[j, 0], p[i, 1] - p[j, 1]) < comm_range  # as `distances` measures
        for a, b in zip(i[close].tolist(), j[close].tolist()):
            graph[a].add(b)
            graph[b].add(a)
    return graph


def components(pos: ArrayLike, comm_range: float) -> list[set[int]]:
    """Connected components of the radio graph (lists of node indices)."""
    graph = links(pos, comm_range)
    return netgraph.connected_components({i: {j: 1 for j in nb} for i, nb in graph.items()})


def largest_share(pos: ArrayLike, comm_range: float) -> float:
    """Share (0..1) of the nodes in the largest connected component."""
    n = len(np.asarray(pos))
    if n == 0:
        return 0.0
    return max(len(c) for c in components(pos, comm_range)) / n


def reach_of(pos: ArrayLike, comm_range: float, node: int) -> set[int]:
    """Nodes that `node` reaches directly or over several hops (itself excluded)."""
    for comp in components(pos, comm_range):
        if node in comp:
            return comp - {node}
    return set()


def coverage(pos: ArrayLike, radius: float, box: tuple[float, float, float, float] | None = None,
             cell: float | None = None) -> float:
    """Area (m^2) covered by discs of `radius` around the positions, inside `box` if given."""
    p = np.asarray(pos, dtype=float)
    if len(p) == 0:
        return 0.0
    if box is None:
        box = (p[:, 0].min() - radius, p[:, 1].min() - radius, p[:, 0].max() + radius, p[:, 1].max() + radius)
    xmin, ymin, xmax, ymax = box
    cell = cell or max(radius / 20, (xmax - xmin) / 500, (ymax - ymin) / 500)
    xs = np.arange(xmin + cell / 2, xmax, cell)
    ys = np.arange(ymin + cell / 2, ymax, cell)
    covered = np.zeros((len(ys), len(xs)), dtype=bool)
    r2 = radius * radius
    for x, y in p:
        ix = slice(max(0, int((x - radius - xmin) / cell)), min(len(xs), int((x + radius - xmin) / cell) + 2))
        iy = slice(max(0, int((y - radius - ymin) / cell)), min(len(ys), int((y + radius - ymin) / cell) + 2))
        gx, gy = np.meshgrid(xs[ix] - x, ys[iy] - y)
        covered[iy, ix] |= gx * gx + gy * gy <= r2
    return float(covered.sum() * cell * cell)


def drive(pos: NDArray[np.float64], th: NDArray[np.float64], targets: NDArray[np.float64], dt: float, vmax: float,
          wmax: float = math.radians(90), tolerance: float = 0.02, moving: NDArray[np.bool_] | None = None
          ) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
    """Step unicycles toward `targets` for dt; return (pos, th, speed): turn first, then drive."""
    rel = targets - pos
    dist = np.hypot(rel[:, 0], rel[:, 1])
    want = np.arctan2(rel[:, 1], rel[:, 0])
    err = (want - th + math.pi) % (2 * math.pi) - math.pi
    go = dist > tolerance
    if moving is not None:
        go &= moving
    turn = np.clip(err, -wmax * dt, wmax * dt) * go
    th = (th + turn + math.pi) % (2 * math.pi) - math.pi
    aligned = np.maximum(0.0, np.cos(err))  # slow down while badly aligned
    speed = np.where(go, np.minimum(vmax * aligned, dist / dt), 0.0)
    pos = pos + (speed * dt)[:, None] * np.stack([np.cos(th), np.sin(th)], axis=1)
    return pos, th, speed


@dataclass
class Track:
    """Every pose of every robot over time: t (T,), pos (T, N, 2), th (T, N), speed (T, N)."""

    t: list[float] = field(default_factory=list)
    pos: list[NDArray[np.float64]] = field(default_factory=list)
    th: list[NDArray[np.float64]] = field(default_factory=list)
    speed: list[NDArray[np.float64]] = field(default_factory=list)

    def add(self, t: float, pos: ArrayLike, th: ArrayLike, speed: ArrayLike) -> None:
        """Record one instant (arrays are copied)."""
        self.t.append(float(t))
        self.pos.append(np.array(pos, dtype=float))
        self.th.append(np.array(th, dtype=float))
        self.speed.append(np.array(speed, dtype=float))

    def arrays(self) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
        """Return (t, pos, th, speed) as numpy arrays."""
        return (np.array(self.t, dtype=float), np.array(self.pos, dtype=float), np.array(self.th, dtype=float),
                np.array(self.speed, dtype=float))

    def at(self, t: float) -> NDArray[np.float64]:
        """Positions (N, 2) at the recorded instant closest to `t`."""
        i = int(np.argmin(np.abs(np.array(self.t) - t)))
        return self.pos[i]


def convergence_time(t: NDArray[np.float64], speed: NDArray[np.float64], threshold: float) -> float | None:
    """First time after which every robot's speed stays below `threshold` (None if never)."""
    moving = (np.abs(speed) >= threshold).any(axis=1)
    if not moving.any():
        return float(t[0])
    last = int(np.flatnonzero(moving)[-1])
    return float(t[last + 1]) if last + 1 < len(t) else None


def blocked_by_walls(old: NDArray[np.float64], new: NDArray[np.float64], walls: ArrayLike) -> NDArray[np.bool_]:
    """Mask (N,) of robots whose straight move old -> new crosses any wall (K, 4: x1, y1, x2, y2)."""
    hit = np.zeros(len(old), dtype=bool)
    for x1, y1, x2, y2 in np.asarray(walls, dtype=float).reshape(-1, 4):
        a, b = np.array([x1, y1]), np.array([x2, y2])

        def orient(p: NDArray[np.float64], q: NDArray[np.float64], r: NDArray[np.float64]) -> NDArray[np.float64]:
            cross: NDArray[np.float64] = ((q[..., 0] - p[..., 0]) * (r[..., 1] - p[..., 1])
                                          - (q[..., 1] - p[..., 1]) * (r[..., 0] - p[..., 0]))
            return cross

        d1, d2 = orient(a, b, old), orient(a, b, new)
        d3, d4 = orient(old, new, a), orient(old, new, b)
        hit |= (np.sign(d1) != np.sign(d2)) & (np.sign(d3) != np.sign(d4)) & (d2 != 0)
    return hit
