"""Potential-field self-deployment (paper 001, section 3, equations 6, 8, 15 and 16).

Each robot i is a point mass m with moment of inertia I, pose (x, y, theta). Its artificial
potential is U_i = sum_j w/2 (|p_j - p_i| - d_ij)^2 + chi/2 (phi_i - theta_i)^2, where the
sum runs over its neighbourhood (robots, plus the nearest point of each obstacle and wall in
sensing range, with desired distances d_ij = a, b or c) and phi_i is the direction of the
neighbourhood's weighted centre s_i = (1/n) sum_j w (p_j - p_i). With Rayleigh damping k:
- holonomic (15):    m a = -dU/dp - k v,         I theta'' = -dU/dtheta - k theta'
- nonholonomic (16): the velocity stays along the heading h = (cos theta, sin theta):
                     m v' = (-dU/dp) . h - k v,  I theta'' = -dU/dtheta - k theta'
Integration is semi-implicit Euler with period dt.

Neighbourhoods: "physical" (robots within `range`), "delaunay" (one-hop neighbours of the
Delaunay triangulation of all robots, scipy.spatial.Delaunay) or "gabriel" (one-hop neighbours of
the Gabriel graph, the other topological graph paper 001 names in 3.2: the Delaunay edges whose
closed diametral disc holds no other robot, so a boundary robot has no long edges across the hull
that a Delaunay neighbourhood gives it). Obstacles and walls count only
within the sensing range `sensing` (paper 001, section 3.3: "an obstacle or the boundary is
considered belonging to the neighborhood of Ri only when it is inside the sensing range";
None: `range`), each as one object at its nearest point with desired distance b or c and
weight `obstacle_weight` (the paper's w_ij; "a larger w_ij means a bigger influence"). With
`sensing` = c the wall term only pushes and is continuous where it starts; sensed from
further out, the spring pulls a robot toward the wall from the edge of the range, with a
jump of w (sensing - c) in force. With w = 1 for a wall, a crowd of neighbours pressing a
robot toward it outweighs the wall's push (at most w c) and pins the robot there;
`obstacle_weight = None` weighs an obstacle or wall as much as all the robots in the
neighbourhood together, a weight that jumps whenever a neighbour comes or goes.

Inputs (pure, numpy): `pos` (N, 2) m; `theta` (N,) rad; `vel` (N, 2) m/s (for nonholonomic
robots the velocity along the heading times h); `omega` (N,) rad/s; `obstacles` (M, 3) circles
(x, y, r) m; `walls` (K, 4) segments (x1, y1, x2, y2) m. Output of `spread_step`: the next
(pos, theta, vel, omega). Scenario constants of the paper: d = 5, k = 2, chi = w = 1, dt = 0.2,
120 robots starting in [-1, 1]^2; corridor walls at y = +-15.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from erni.blackboard.errors import UsageError

EPS = 1e-9
NEIGHBOURHOODS = ("physical", "delaunay", "gabriel")


@dataclass(frozen=True)
class SpreadConfig:
    """Constants of the deployment motion (units: m, s, kg, kg m^2)."""

    distance: float = 5.0          # desired robot-robot distance a (m)
    obstacle_distance: float = 2.0  # desired robot-obstacle distance b (m)
    wall_distance: float = 2.5     # desired robot-wall distance c (m)
    gain: float = 2.0              # viscous damping k (kx = ky = ktheta)
    dt: float = 0.2                # integration period (s)
    range: float = 15.0            # physical neighbourhood: robots within this range (m)
    sensing: float | None = None   # obstacles and walls count within this range (m); None: `range`
    neighbourhood: str = "physical"  # "physical", "delaunay" or "gabriel"
    model: str = "holonomic"       # "holonomic" or "nonholonomic"
    chi: float = 1.0               # weight of the heading term
    weight: float = 1.0            # w_ij of a robot
    obstacle_weight: float | None = 1.0  # w_ij of an obstacle or wall; None: as many robots as are in the neighbourhood
    mass: float = 1.0
    inertia: float = 1.0
    vmax: float | None = None      # speed limit (m/s), None = unlimited
    wmax: float | None = None      # turn-rate limit (rad/s), None = unlimited

    def __post_init__(self) -> None:
        for name in ("distance", "gain", "dt", "range", "mass", "inertia"):
            if not getattr(self, name) > 0:
                raise UsageError(f"{name}: expected a positive number, got {getattr(self, name)!r}")
        if self.sensing is not None and not self.sensing > 0:
            raise UsageError(f"sensing: expected a positive number or None, got {self.sensing!r}")
        if self.neighbourhood not in NEIGHBOURHOODS:
            raise UsageError(f"neighbourhood: expected one of {', '.join(NEIGHBOURHOODS)}, got {self.neighbourhood!r}")
        if self.model not in ("holonomic", "nonholonomic"):
            raise UsageError(f"model: expected 'holonomic' or 'nonholonomic', got {self.model!r}")


def wrap(a: NDArray[np.float64] | float) -> NDArray[np.float64] | np.float64:
    """Wrap angles (rad) into [-pi, pi)."""
    return (np.asarray(a) + math.pi) % (2 * math.pi) - math.pi


def neighbourhoods(pos: ArrayLike, mode: str = "physical", rng: float = 15.0) -> list[NDArray[np.intp]]:
    """Return, for each robot, the indices of its neighbours (physical: within `rng`; Delaunay; Gabriel)."""
    p = np.asarray(pos, dtype=float)
    n = len(p)
    if mode == "physical":
        from scipy.spatial import cKDTree

        if n == 0:
            return []
        near = cKDTree(p).query_ball_point(p, rng, return_sorted=True)
        return [np.array([j for j in near[i] if j != i], dtype=np.intp) for i in range(n)]
    if mode not in NEIGHBOURHOODS:
        raise UsageError(f"mode: expected one of {', '.join(NEIGHBOURHOODS)}, got {mode!r}")
    if n < 2:
        return [np.zeros(0, dtype=int) for _ in range(n)]
    try:
        from scipy.spatial import Delaunay, QhullError

        tri = Delaunay(p)
    except (QhullError, ValueError):  # fewer than 3 points or all on one line: the chain along it
        out = _chain(p)
        return gabriel(p, out) if mode == "gabriel" else out
    indptr, indices = tri.vertex_neighbor_vertices
    out = [np.sort(indices[indptr[i]:indptr[i + 1]]) for i in range(n)]
    # points Qhull dropped as coincident get the neighbours of the point they coincide with
    for i in range(n):
        if len(out[i]) == 0:
            j = tri.coplanar[tri.coplanar[:, 0] == i, 2] if len(tri.coplanar) else np.zeros(0, dtype=int)
            out[i] = np.array(sorted(set(out[int(j[0])]) | {int(j[0])} - {i}), dtype=int) if len(j) else \
                np.delete(np.arange(n), i)
    return gabriel(p, out) if mode == "gabriel" else out


def _chain(p: NDArray[np.float64]) -> list[NDArray[np.intp]]:
    """The Delaunay graph of points on one line: each point and the next along it."""
    far = p[int(np.argmax(np.hypot(*(p - p[0]).T)))] - p[0]
    order = np.argsort((p - p[0]) @ far, kind="stable")
    out: list[list[int]] = [[] for _ in range(len(p))]
    for a, b in zip(order[:-1], order[1:]):
        out[int(a)].append(int(b))
        out[int(b)].append(int(a))
    return [np.array(sorted(s), dtype=np.intp) for s in out]


def gabriel(p: NDArray[np.float64], delaunay: list[NDArray[np.intp]]) -> list[NDArray[np.intp]]:
    """Keep the Delaunay edges (i, j) with no other point in the closed disc on the diameter
    p_i p_j (such an edge is in every Delaunay triangulation, so only those are tried; a point on
    the circle excludes the edge, so four robots on a circle get no diagonal)."""
    from scipy.spatial import cKDTree

    n = len(p)
    edges = np.array([(i, int(j)) for i in range(n) for j in delaunay[i] if i < j], dtype=np.intp).reshape(-1, 2)
    if len(edges) == 0:
        return delaunay
    mid = (p[edges[:, 0]] + p[edges[:, 1]]) / 2
    radius = np.hypot(*(p[edges[:, 0]] - p[edges[:, 1]]).T) / 2
    tree = cKDTree(p)
    inside = tree.query_ball_point(mid, radius * (1 + 1e-9) + 1e-12)  # on the circle too (the ends are)
    keep = [k for k, (i, j) in enumerate(edges) if not (set(inside[k]) - {int(i), int(j)})]
    out: list[set[int]] = [set() for _ in range(n)]
    for i, j in edges[keep]:
        out[int(i)].add(int(j))
        out[int(j)].add(int(i))
    return [np.array(sorted(s), dtype=np.intp) for s in out]


def nearest_on_segments(p: ArrayLike, walls: NDArray[np.float64]) -> NDArray[np.float64]:
    """Return the nearest point (K, 2) on each wall segment (x1, y1, x2, y2) to point p."""
    out: NDArray[np.float64] = _nearest_on_segments(np.asarray(p, dtype=float).reshape(1, 2), walls)[0]
    return out


def nearest_on_circles(p: ArrayLike, obstacles: NDArray[np.float64]) -> NDArray[np.float64]:
    """Return the nearest point (M, 2) on each circle (x, y, r) to point p (p itself if it is inside)."""
    out: NDArray[np.float64] = _nearest_on_circles(np.asarray(p, dtype=float).reshape(1, 2), obstacles)[0]
    return out


def _nearest_on_circles(p: NDArray[np.float64], obstacles: NDArray[np.float64]) -> NDArray[np.float64]:
    """The nearest point on each circle to each point p (N, 2): (N, M, 2); p itself if it is inside."""
    c, r = obstacles[None, :, :2], obstacles[None, :, 2]
    off = p[:, None, :] - c
    dist = np.hypot(off[..., 0], off[..., 1])
    unit = np.where(dist[..., None] > EPS, off / np.where(dist > EPS, dist, 1.0)[..., None], 0.0)
    out: NDArray[np.float64] = c + unit * np.minimum(r, dist)[..., None]
    return out


def _nearest_on_segments(p: NDArray[np.float64], walls: NDArray[np.float64]) -> NDArray[np.float64]:
    """The nearest point on each segment to each point p (N, 2): (N, K, 2)."""
    a, ab = walls[None, :, :2], walls[None, :, 2:] - walls[None, :, :2]
    length2 = np.einsum("ijk,ijk->ij", ab, ab)
    along = np.einsum("ijk,ijk->ij", p[:, None, :] - a, ab)
    t = np.where(length2 > EPS, along / np.where(length2 > EPS, length2, 1.0), 0.0)
    out: NDArray[np.float64] = a + np.clip(t, 0.0, 1.0)[..., None] * ab
    return out


def forces(pos: ArrayLike, theta: ArrayLike, cfg: SpreadConfig, obstacles: ArrayLike | None = None,
           walls: ArrayLike | None = None, nbrs: list[NDArray[np.intp]] | None = None
           ) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Return (-dU/dp (N, 2), -dU/dtheta (N,)): the potential's force and torque on each robot."""
    p = np.asarray(pos, dtype=float)
    th = np.asarray(theta, dtype=float)
    n = len(p)
    obs = np.zeros((0, 3)) if obstacles is None or np.size(obstacles) == 0 else np.asarray(obstacles, float).reshape(-1, 3)
    wal = np.zeros((0, 4)) if walls is None or np.size(walls) == 0 else np.asarray(walls, float).reshape(-1, 4)
    if nbrs is None:
        nbrs = neighbourhoods(p, cfg.neighbourhood, cfg.range)
    # Every (robot, point it feels, distance it wants, weight) in flat arrays: neighbours, then the
    # nearest point of each obstacle and wall within range; sums per robot by bincount.
    w = cfg.weight
    sensing = cfg.range if cfg.sensing is None else cfg.sensing
    degree = np.array([len(x) for x in nbrs], dtype=int)
    wobj = (np.full(n, float(cfg.obstacle_weight)) if cfg.obstacle_weight is not None
            else np.maximum(1, degree).astype(float) * w)  # w_ij of an obstacle or wall, per robot
    owner = [np.repeat(np.arange(n), degree)]
    pts = [p[np.concatenate(nbrs)] if n and len(owner[0]) else np.zeros((0, 2))]
    want = [np.full(len(owner[0]), cfg.distance)]
    weights = [np.full(len(owner[0]), w)]
    for q, dist_wanted in ((_nearest_on_circles(p, obs), cfg.obstacle_distance) if len(obs) else (None, 0.0),
                           (_nearest_on_segments(p, wal), cfg.wall_distance) if len(wal) else (None, 0.0)):
        if q is None:
            continue
        near = np.hypot(q[..., 0] - p[:, None, 0], q[..., 1] - p[:, None, 1]) <= sensing
        i, k = np.nonzero(near)
        owner.append(i)
        pts.append(q[i, k])
        want.append(np.full(len(i), dist_wanted))
        weights.append(wobj[i])
    who = np.concatenate(owner)
    rel = np.concatenate(pts) - p[who]
    dij = np.concatenate(want)
    wij = np.concatenate(weights)
    dist = np.hypot(rel[:, 0], rel[:, 1])
    ok = dist > EPS
    unit = np.zeros_like(rel)
    unit[ok] = rel[ok] / dist[ok, None]
    if not ok.all():  # coincident: push apart in a direction fixed by the robot's index
        ang = 2.0 * math.pi * ((who[~ok] * 0.618034) % 1.0)
        unit[~ok] = np.column_stack([np.cos(ang), np.sin(ang)])
    pull = wij * (dist - dij)
    force = np.column_stack([np.bincount(who, pull * unit[:, 0], minlength=n),
                             np.bincount(who, pull * unit[:, 1], minlength=n)]).astype(float)
    # heading term: turn toward the neighbourhood's weighted centre s = mean(w (p_j - p_i))
    count = np.bincount(who, minlength=n)
    felt = count > 0
    s = np.zeros((n, 2))
    s[felt] = np.column_stack([np.bincount(who, wij * rel[:, 0], minlength=n),
                               np.bincount(who, wij * rel[:, 1], minlength=n)]).astype(float)[felt] / count[felt, None]
    wmean = np.zeros(n)
    wmean[felt] = np.bincount(who, wij, minlength=n)[felt] / count[felt]
    s2 = np.einsum("ij,ij->i", s, s)
    turn = s2 > 1e-6
    s2 = np.maximum(s2, (0.1 * cfg.distance) ** 2)  # regularised: |s| floored at d / 10
    err = np.where(turn, wrap(np.arctan2(s[:, 1], s[:, 0]) - th), 0.0)
    torque: NDArray[np.float64] = cfg.chi * err
    force += (cfg.chi * err * wmean / s2)[:, None] * np.column_stack([-s[:, 1], s[:, 0]])
    return force, torque


def _clip_norm(v: NDArray[np.float64], vmax: float | None) -> NDArray[np.float64]:
    if vmax is None:
        return v
    speed = np.hypot(v[:, 0], v[:, 1])
    scale = np.where(speed > vmax, vmax / np.where(speed > 0, speed, 1.0), 1.0)
    return v * scale[:, None]


def spread_step(pos: ArrayLike, theta: ArrayLike, vel: ArrayLike, omega: ArrayLike, cfg: SpreadConfig,
                obstacles: ArrayLike | None = None, walls: ArrayLike | None = None
                ) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
    """Advance every robot one period `cfg.dt` by equation (15) or (16); return (pos, theta, vel, omega)."""
    p = np.asarray(pos, dtype=float)
    th = np.asarray(theta, dtype=float)
    v = np.asarray(vel, dtype=float).reshape(-1, 2)
    om = np.asarray(omega, dtype=float)
    if not (len(p) == len(th) == len(v) == len(om)):
        raise UsageError("spread_step: pos, theta, vel and omega must describe the same robots")
    nbrs = neighbourhoods(p, cfg.neighbourhood, cfg.range)
    # substeps keep the stiffest neighbourhood's spring stable: h * sqrt(n w / m) <= 0.5
    degree = max((len(x) for x in nbrs), default=0)
    wobj = cfg.obstacle_weight if cfg.obstacle_weight is not None else max(1, degree) * cfg.weight
    stiffness = degree * cfg.weight + 2 * wobj  # robots, plus about two obstacles or walls
    substeps = min(50, max(1, math.ceil(cfg.dt * math.sqrt(stiffness / cfg.mass) / 0.5)))
    h = cfg.dt / substeps
    for _ in range(substeps):
        p, th, v, om = _integrate(p, th, v, om, cfg, h, obstacles, walls, nbrs)
    return p, th, v, om


def _integrate(p: NDArray[np.float64], th: NDArray[np.float64], v: NDArray[np.float64], om: NDArray[np.float64],
               cfg: SpreadConfig, dt: float, obstacles: ArrayLike | None, walls: ArrayLike | None,
               nbrs: list[NDArray[np.intp]]
               ) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
    f, tq = forces(p, th, cfg, obstacles, walls, nbrs)
    k = cfg.gain
    om = om + dt * (tq - k * om) / cfg.inertia
    if cfg.wmax is not None:
        om = np.clip(om, -cfg.wmax, cfg.wmax)
    th = np.asarray(wrap(th + dt * om))
    if cfg.model == "holonomic":
        v = _clip_norm(v + dt * (f - k * v) / cfg.mass, cfg.vmax)
    else:
        hd = np.stack([np.cos(th), np.sin(th)], axis=1)
        speed = np.einsum("ij,ij->i", v, hd)  # keep the longitudinal part only
        speed = speed + dt * (np.einsum("ij,ij->i", f, hd) - k * speed) / cfg.mass
        if cfg.vmax is not None:
            speed = np.clip(speed, -cfg.vmax, cfg.vmax)
        v = speed[:, None] * hd
    return p + dt * v, th, v, om


def robot_command(pos: ArrayLike, theta: float, speed: float, omega: float, i: int, cfg: SpreadConfig,
                  obstacles: ArrayLike | None = None, walls: ArrayLike | None = None) -> tuple[float, float]:
    """Return robot i's (v m/s, w rad/s) command: the velocity equation (15)/(16) settles to under the current force.

    On a real robot the lower-level controller owns acceleration, so the command is the terminal
    velocity of m a = F - k v (v = F / k): along the heading for the nonholonomic model
    (v = F.h / k, w = torque / k_theta); for the holonomic model the wheeled robot steers toward
    F / k (driving backwards rather than turning around). The holonomic model's theta is free of
    the wheels: equation (15) settles it at the neighbourhood's centre, where the heading term's
    force is zero, so F leaves that term out; the wheeled robot's own heading (pointing where it
    drives) would otherwise keep the term's sideways force alive and the robot never still.
    `speed` and `omega` (the robot's measured velocities) are accepted for interface stability
    and ignored. Limits: cfg.vmax, cfg.wmax.
    """
    p = np.asarray(pos, dtype=float)
    th = np.zeros(len(p))
    th[i] = theta
    f, tq = forces(p, th, dataclasses.replace(cfg, chi=0.0) if cfg.model == "holonomic" else cfg,
                   obstacles, walls)
    h = np.array([math.cos(theta), math.sin(theta)])
    if cfg.model == "holonomic":
        u = f[i] / cfg.gain
        sp = float(np.hypot(*u))
        if sp < 1e-3:
            return 0.0, 0.0
        err = float(wrap(math.atan2(u[1], u[0]) - theta))
        if abs(err) > math.pi / 2:  # drive backwards rather than turn around
            err = float(wrap(err + math.pi))
            sp = -sp
        sp *= max(0.0, math.cos(err))
        out_w = err / max(cfg.dt, 1.0)
    else:
        sp = float(f[i] @ h) / cfg.gain
        out_w = float(tq[i]) / cfg.gain
    if cfg.vmax is not None:
        sp = max(-cfg.vmax, min(cfg.vmax, sp))
    if cfg.wmax is not None:
        out_w = max(-cfg.wmax, min(cfg.wmax, out_w))
    return float(sp), float(out_w)


def mean_nn_distance(pos: ArrayLike) -> float:
    """Return the mean distance (m) from each robot to its nearest other robot."""
    p = np.asarray(pos, dtype=float)
    if len(p) < 2:
        return 0.0
    d = np.hypot(*(p[:, None, :] - p[None, :, :]).transpose(2, 0, 1))
    np.fill_diagonal(d, math.inf)
    return float(d.min(axis=1).mean())


def simulate(pos: ArrayLike, theta: ArrayLike, cfg: SpreadConfig, seconds: float,
             obstacles: ArrayLike | None = None, walls: ArrayLike | None = None
             ) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Run the deployment from rest for `seconds`; return the final (pos, theta)."""
    p = np.asarray(pos, dtype=float).copy()
    th = np.asarray(theta, dtype=float).copy()
    v = np.zeros_like(p)
    om = np.zeros(len(p))
    for _ in range(round(seconds / cfg.dt)):
        p, th, v, om = spread_step(p, th, v, om, cfg, obstacles, walls)
    return p, th
