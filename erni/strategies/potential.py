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
ENGAGE = ("instant", "rest")
Links = dict[tuple[int, int], float]  # engage = "rest": (i, j), i < j -> the spring's rest length (m)


@dataclass
class SpreadMemory:
    """What a team's deployment carries from one step to the next when cfg.engage = "rest" or
    cfg.stick > 0 (the paper's law needs none): each spring's rest length, each link's hysteresis
    state and the time (s)."""

    links: Links = dataclasses.field(default_factory=dict)
    seen: dict[tuple[int, int], list[float]] = dataclasses.field(default_factory=dict)
    t: float = 0.0
    triangles: NDArray[np.intp] | None = None  # cfg.flip_margin > 0: the triangulation kept (T, 3), counter-clockwise
    effective: dict[tuple[int, int], float] = dataclasses.field(default_factory=dict)  # links in effect: rest length
    retriangulated: int = 0    # cfg.flip_margin > 0: how often the kept triangulation started afresh
    switched_on: float = 0.0   # J: the energy springs held at the instant a change switched them on, summed
    switched_off: float = 0.0  # J: ... and at the instant one switched them off

    def account(self, pos: NDArray[np.float64], nbrs: list[NDArray[np.intp]], rest: NDArray[np.float64] | None,
                cfg: SpreadConfig) -> None:
        """Count the springs this step switches on and off against the last (none at the start)."""
        flat = [(i, int(j)) for i, js in enumerate(nbrs) for j in js]
        rests = [cfg.distance] * len(flat) if rest is None else rest.tolist()
        now = {(i, j): r for (i, j), r in zip(flat, rests) if i < j}

        def energy(key: tuple[int, int], r: float) -> float:
            return cfg.weight * (float(np.hypot(*(pos[key[1]] - pos[key[0]]))) - r) ** 2 / 2

        if self.t > 0:
            self.switched_on += sum(energy(k, r) for k, r in now.items() if k not in self.effective)
            self.switched_off += sum(energy(k, r) for k, r in self.effective.items() if k not in now)
        self.effective = now


def _ccw(p: NDArray[np.float64], tri: NDArray[np.intp]) -> NDArray[np.float64]:
    """Twice the signed area of each triangle (positive: counter-clockwise)."""
    a, b, c = p[tri[:, 0]], p[tri[:, 1]], p[tri[:, 2]]
    out: NDArray[np.float64] = (b[:, 0] - a[:, 0]) * (c[:, 1] - a[:, 1]) - (b[:, 1] - a[:, 1]) * (c[:, 0] - a[:, 0])
    return out


def kept_delaunay(pos: ArrayLike, triangles: NDArray[np.intp] | None, margin: float
                  ) -> NDArray[np.intp] | None:
    """A Delaunay triangulation kept from step to step, with hysteresis: an edge flips only once
    the two angles opposite it sum to more than 180 + `margin` degrees (the Delaunay test is
    180), so after a flip the robots must move the angles by 2 `margin` before it flips back.
    Start (`triangles` None), or when a robot crossed an edge of its triangles: triangulated
    afresh. Returns the triangles (T, 3), counter-clockwise, or None where Qhull cannot
    triangulate (fewer than 3 robots, all on one line, coincident robots)."""
    from scipy.spatial import Delaunay, QhullError

    p = np.asarray(pos, dtype=float)
    n = len(p)
    if triangles is not None and len(triangles) and (_ccw(p, triangles) <= 1e-12).any():
        triangles = _repair(p, triangles)
    if triangles is not None and len(np.unique(triangles)) < n:  # a robot left without a triangle
        triangles = None
    if triangles is None or len(triangles) == 0:
        if n < 3:
            return None
        try:
            tri = Delaunay(p)
        except (QhullError, ValueError):
            return None
        if len(np.unique(tri.simplices)) < n:  # a robot Qhull dropped (coincident)
            return None
        t = np.array(tri.simplices, dtype=np.intp)
        flip = _ccw(p, t) < 0
        t[flip] = t[flip][:, [0, 2, 1]]
        return t
    t = triangles.copy()
    limit = math.pi + math.radians(margin)
    for _ in range(50):
        edges: dict[tuple[int, int], list[tuple[int, int]]] = {}
        for k, (a, b, c) in enumerate(t.tolist()):
            for u, v, w in ((a, b, c), (b, c, a), (c, a, b)):
                edges.setdefault((u, v) if u < v else (v, u), []).append((k, w))
        touched: set[int] = set()
        flipped = False
        for (u, v), both in edges.items():
            if len(both) != 2:
                continue
            (k1, w1), (k2, w2) = both
            if k1 in touched or k2 in touched:
                continue
            angles = 0.0
            for w in (w1, w2):
                e1, e2 = p[u] - p[w], p[v] - p[w]
                angles += math.atan2(abs(e1[0] * e2[1] - e1[1] * e2[0]), e1[0] * e2[0] + e1[1] * e2[1])
            if angles <= limit:
                continue
            new = np.array([[u, w2, w1], [v, w1, w2]], dtype=np.intp)
            area = _ccw(p, new)
            if area[0] * area[1] <= 1e-24:  # u and v on one side of w1-w2 (or on it): the quad is not convex
                continue
            new[area < 0] = new[area < 0][:, [0, 2, 1]]
            if (_ccw(p, new) <= 1e-12).any():
                continue
            t[k1], t[k2] = new[0], new[1]
            touched |= {k1, k2}
            flipped = True
        if not flipped:
            break
    return t


def _repair(p: NDArray[np.float64], t: NDArray[np.intp]) -> NDArray[np.intp] | None:
    """Mend a kept triangulation in which robots crossed edges: an inverted triangle's edge is
    flipped with the triangle across it where both new triangles come out counter-clockwise; an
    inverted triangle on the team's edge (an edge no other triangle shares) is dropped, as its
    robot has left the hull. None where that does not mend it (triangulate afresh)."""
    t = t.copy()
    for _ in range(20):
        bad = np.flatnonzero(_ccw(p, t) <= 1e-12)
        if len(bad) == 0:
            return t
        owner: dict[tuple[int, int], list[tuple[int, int]]] = {}
        for k, (a, b, c) in enumerate(t.tolist()):
            for u, v, w in ((a, b, c), (b, c, a), (c, a, b)):
                owner.setdefault((u, v) if u < v else (v, u), []).append((k, w))
        drop: set[int] = set()
        touched: set[int] = set()
        for k in bad.tolist():
            if k in touched:
                continue
            a, b, c = t[k].tolist()
            mended = False
            for u, v, w in ((a, b, c), (b, c, a), (c, a, b)):
                both = owner[(u, v) if u < v else (v, u)]
                if len(both) == 1:
                    continue
                (k2, w2) = next(x for x in both if x[0] != k)
                if k2 in touched:
                    continue
                new = np.array([[u, w2, w], [v, w, w2]], dtype=np.intp)
                area = _ccw(p, new)
                new[area < 0] = new[area < 0][:, [0, 2, 1]]
                if area[0] * area[1] > 1e-24 and (_ccw(p, new) > 1e-12).all():
                    t[k], t[k2] = new[0], new[1]
                    touched |= {k, k2}
                    mended = True
                    break
            if not mended and any(len(owner[(u, v) if u < v else (v, u)]) == 1 for u, v in ((a, b), (b, c), (c, a))):
                drop.add(k)
                touched.add(k)
        if not touched:
            return None
        if drop:
            t = np.delete(t, sorted(drop), axis=0)
    return None


def triangle_neighbours(triangles: NDArray[np.intp], n: int) -> list[NDArray[np.intp]]:
    """Each robot's neighbours along the edges of `triangles`."""
    out: list[set[int]] = [set() for _ in range(n)]
    for a, b, c in triangles.tolist():
        out[a] |= {b, c}
        out[b] |= {a, c}
        out[c] |= {a, b}
    return [np.array(sorted(x), dtype=np.intp) for x in out]


def team_neighbourhoods(pos: ArrayLike, cfg: SpreadConfig, memory: SpreadMemory | None = None
                        ) -> list[NDArray[np.intp]]:
    """Each robot's neighbours under `cfg`: the neighbourhood itself (a Delaunay triangulation kept
    with cfg.flip_margin when `memory` is given), links longer than cfg.reach dropped, and the
    hysteresis of cfg.stick (with `memory`)."""
    p = np.asarray(pos, dtype=float)
    nbrs: list[NDArray[np.intp]] | None = None
    if memory is not None and cfg.neighbourhood == "delaunay" and cfg.flip_margin > 0:
        tri = memory.triangles
        if tri is not None and (_ccw(p, tri) <= 1e-12).any():  # a robot crossed an edge: mend, else afresh
            tri = _repair(p, tri)
            if tri is None or len(np.unique(tri)) < len(p):
                memory.retriangulated += 1
                tri = None
        memory.triangles = kept_delaunay(p, tri, cfg.flip_margin)
        if memory.triangles is not None:
            nbrs = triangle_neighbours(memory.triangles, len(p))
            # every Delaunay triangulation links each robot to its nearest robot; the kept one links
            # it too once closer than d / 2, or two robots whose edge it lacks could close unfelt;
            # and a link in effect shorter than d stays until it reaches d, where its push ends
            from scipy.spatial import cKDTree

            gap, near = cKDTree(p).query(p, k=2)
            extra = {(min(i, j), max(i, j)) for i, j in enumerate(near[:, 1].tolist()) if gap[i, 1] < cfg.distance / 2}
            extra |= {key for key in memory.effective if np.hypot(*(p[key[1]] - p[key[0]])) < cfg.distance}
            for i, j in extra:
                if j not in nbrs[i]:
                    nbrs[i] = np.sort(np.append(nbrs[i], j))
                    nbrs[j] = np.sort(np.append(nbrs[j], i))
            if cfg.reach is not None:  # with a margin: a link in effect goes only past 1.1 reach
                held = memory.effective
                nbrs = [js[[np.hypot(*(p[j] - p[i])) <= cfg.reach * (1.1 if (min(i, j), max(i, j)) in held else 1.0)
                            for j in js.tolist()]] if len(js) else js for i, js in enumerate(nbrs)]
    if nbrs is None:
        nbrs = neighbourhoods(p, cfg.neighbourhood, cfg.range, cfg.reach)
    if memory is not None and cfg.stick > 0:
        nbrs = hysteresis(nbrs, memory.seen, memory.t, cfg.stick)
    return nbrs


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
    engage: str = "instant"        # a new neighbour's spring: "instant" (at d, the paper's) or "rest" (at its length)
    relax: float = 5.0             # engage = "rest": time constant (s) of a spring's rest length going to d
    stick: float = 0.0             # hysteresis (s): a neighbour joins or leaves once the change has held this long
    reach: float | None = None     # topological neighbourhoods: links longer than this (m) dropped; None: none
    flip_margin: float = 0.0       # Delaunay kept from step to step: an edge flips once its opposite angles
                                   # sum to more than 180 degrees plus this (deg); 0: triangulated afresh each step

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
        if self.engage not in ENGAGE:
            raise UsageError(f"engage: expected one of {', '.join(ENGAGE)}, got {self.engage!r}")
        if not self.relax > 0:
            raise UsageError(f"relax: expected a positive number, got {self.relax!r}")
        if self.reach is not None and not self.reach > 0:
            raise UsageError(f"reach: expected a positive number or None, got {self.reach!r}")
        if not 0 <= self.flip_margin < 90:
            raise UsageError(f"flip_margin: expected degrees in [0, 90), got {self.flip_margin!r}")
        if not self.stick >= 0:
            raise UsageError(f"stick: expected a number of seconds >= 0, got {self.stick!r}")


def wrap(a: NDArray[np.float64] | float) -> NDArray[np.float64] | np.float64:
    """Wrap angles (rad) into [-pi, pi)."""
    return (np.asarray(a) + math.pi) % (2 * math.pi) - math.pi


def neighbourhoods(pos: ArrayLike, mode: str = "physical", rng: float = 15.0,
                   reach: float | None = None) -> list[NDArray[np.intp]]:
    """Return, for each robot, the indices of its neighbours (physical: within `rng`; Delaunay; Gabriel).

    `reach`: a topological neighbour further than this (m) is dropped (the long links a Delaunay
    triangulation gives robots on the team's edge, which no radio of range `reach` carries).
    """
    p = np.asarray(pos, dtype=float)
    if reach is not None and mode != "physical":
        full = neighbourhoods(p, mode, rng)
        return [js[np.hypot(*(p[js] - p[i]).T) <= reach] if len(js) else js for i, js in enumerate(full)]
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
           walls: ArrayLike | None = None, nbrs: list[NDArray[np.intp]] | None = None,
           rest: NDArray[np.float64] | None = None) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Return (-dU/dp (N, 2), -dU/dtheta (N,)): the potential's force and torque on each robot.

    `rest`: each neighbour's desired distance, in the order of `nbrs` flattened (robot by robot);
    None: cfg.distance for every one.
    """
    p = np.asarray(pos, dtype=float)
    th = np.asarray(theta, dtype=float)
    n = len(p)
    obs = np.zeros((0, 3)) if obstacles is None or np.size(obstacles) == 0 else np.asarray(obstacles, float).reshape(-1, 3)
    wal = np.zeros((0, 4)) if walls is None or np.size(walls) == 0 else np.asarray(walls, float).reshape(-1, 4)
    if nbrs is None:
        nbrs = neighbourhoods(p, cfg.neighbourhood, cfg.range, cfg.reach)
    # Every (robot, point it feels, distance it wants, weight) in flat arrays: neighbours, then the
    # nearest point of each obstacle and wall within range; sums per robot by bincount.
    w = cfg.weight
    sensing = cfg.range if cfg.sensing is None else cfg.sensing
    degree = np.array([len(x) for x in nbrs], dtype=int)
    wobj = (np.full(n, float(cfg.obstacle_weight)) if cfg.obstacle_weight is not None
            else np.maximum(1, degree).astype(float) * w)  # w_ij of an obstacle or wall, per robot
    owner = [np.repeat(np.arange(n), degree)]
    pts = [p[np.concatenate(nbrs)] if n and len(owner[0]) else np.zeros((0, 2))]
    want = [np.full(len(owner[0]), cfg.distance) if rest is None else np.asarray(rest, dtype=float)]
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


def engage_links(pos: NDArray[np.float64], nbrs: list[NDArray[np.intp]], links: Links, cfg: SpreadConfig,
                 start: bool = False) -> NDArray[np.float64]:
    """Springs that engage at rest (engage = "rest"): a link new in `nbrs` gets its current length
    as rest length, a link gone from `nbrs` is dropped (in `links`, in place); return each
    neighbour's rest length in the order of `nbrs` flattened, for `forces`.

    A spring switched on at its current length holds no energy and pushes nothing, so a change of
    neighbourhood (a Delaunay flip, a robot crossing a range) puts no energy in at once;
    `relax_links` then moves the rest length to d, smoothly. At the `start` every spring is at
    d, as the paper's.
    """
    now: set[tuple[int, int]] = set()
    out = np.empty(sum(len(x) for x in nbrs))
    k = 0
    for i, js in enumerate(nbrs):
        for j in js.tolist():
            key = (i, j) if i < j else (j, i)
            now.add(key)
            if key not in links:
                links[key] = cfg.distance if start else float(np.hypot(*(pos[j] - pos[i])))
            out[k] = links[key]
            k += 1
    for key in links.keys() - now:
        del links[key]
    return out


def hysteresis(nbrs: list[NDArray[np.intp]], seen: dict[tuple[int, int], list[float]], t: float,
               hold: float) -> list[NDArray[np.intp]]:
    """Neighbourhoods that change only after a change has held for `hold` s: a link joins once it
    has been in `nbrs` for `hold` s without a break, and leaves once it has been out of it for
    `hold` s; a link that flips back and forth faster than that keeps its state.

    `seen` (kept by the caller, empty at the start): (i, j), i < j -> [since, in effect], where
    `since` is when the link last changed between in `nbrs` and out of it (1.0 / 0.0 in effect).
    """
    now = {(i, j) if i < j else (j, i) for i, js in enumerate(nbrs) for j in js.tolist()}
    for key in now - seen.keys():
        seen[key] = [t, 1.0 if t == 0 else 0.0]  # the first neighbourhoods are in effect at once
    out: list[set[int]] = [set() for _ in nbrs]
    for key in list(seen):
        state = seen[key]
        present = key in now
        if present == bool(state[1]):
            state[0] = t  # nothing to change: the clock of a change restarts
        elif t - state[0] >= hold:
            state[1] = 1.0 if present else 0.0
            state[0] = t
        if state[1]:
            out[key[0]].add(key[1])
            out[key[1]].add(key[0])
        elif not present:
            del seen[key]
    return [np.array(sorted(x), dtype=np.intp) for x in out]


def relax_links(links: Links, cfg: SpreadConfig, dt: float) -> None:
    """Move every rest length toward d with time constant cfg.relax, for dt seconds (in place)."""
    f = math.exp(-dt / cfg.relax)
    for key, r in links.items():
        links[key] = cfg.distance + (r - cfg.distance) * f


def spread_step(pos: ArrayLike, theta: ArrayLike, vel: ArrayLike, omega: ArrayLike, cfg: SpreadConfig,
                obstacles: ArrayLike | None = None, walls: ArrayLike | None = None,
                memory: SpreadMemory | None = None, nbrs: list[NDArray[np.intp]] | None = None
                ) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
    """Advance every robot one period `cfg.dt` by equation (15) or (16); return (pos, theta, vel, omega).

    With cfg.engage = "rest" or cfg.stick > 0, `memory` (kept by the caller from step to step,
    new at the start) holds each spring's rest length (`engage_links`) and each link's hysteresis
    (`hysteresis`). `nbrs`: the neighbourhoods to use (default: from `pos` by cfg.neighbourhood
    and cfg.range, through the hysteresis when cfg.stick > 0).
    """
    p = np.asarray(pos, dtype=float)
    th = np.asarray(theta, dtype=float)
    v = np.asarray(vel, dtype=float).reshape(-1, 2)
    om = np.asarray(omega, dtype=float)
    if not (len(p) == len(th) == len(v) == len(om)):
        raise UsageError("spread_step: pos, theta, vel and omega must describe the same robots")
    if (cfg.engage == "rest" or cfg.stick > 0 or cfg.flip_margin > 0) and memory is None:
        raise UsageError("spread_step: engage = 'rest', stick > 0 and flip_margin > 0 need `memory`, kept "
                         "between steps")
    if nbrs is None:
        nbrs = team_neighbourhoods(p, cfg, memory)
    rest = None
    if memory is not None:
        if cfg.engage == "rest":
            rest = engage_links(p, nbrs, memory.links, cfg, memory.t == 0)
        memory.account(p, nbrs, rest, cfg)
    # substeps keep the stiffest neighbourhood's spring stable: h * sqrt(n w / m) <= 0.5
    degree = max((len(x) for x in nbrs), default=0)
    wobj = cfg.obstacle_weight if cfg.obstacle_weight is not None else max(1, degree) * cfg.weight
    stiffness = degree * cfg.weight + 2 * wobj  # robots, plus about two obstacles or walls
    substeps = min(50, max(1, math.ceil(cfg.dt * math.sqrt(stiffness / cfg.mass) / 0.5)))
    h = cfg.dt / substeps
    for _ in range(substeps):
        p, th, v, om = _integrate(p, th, v, om, cfg, h, obstacles, walls, nbrs, rest)
    if memory is not None:
        if rest is not None:
            relax_links(memory.links, cfg, cfg.dt)
            memory.effective = {key: memory.links[key] for key in memory.effective}
        memory.t += cfg.dt
    return p, th, v, om


def _integrate(p: NDArray[np.float64], th: NDArray[np.float64], v: NDArray[np.float64], om: NDArray[np.float64],
               cfg: SpreadConfig, dt: float, obstacles: ArrayLike | None, walls: ArrayLike | None,
               nbrs: list[NDArray[np.intp]], rest: NDArray[np.float64] | None = None
               ) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
    f, tq = forces(p, th, cfg, obstacles, walls, nbrs, rest)
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
    memory = SpreadMemory()
    for _ in range(round(seconds / cfg.dt)):
        p, th, v, om = spread_step(p, th, v, om, cfg, obstacles, walls, memory)
    return p, th
