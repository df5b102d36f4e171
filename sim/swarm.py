"""Many simulated robots at once: one physics step and one sonar round for a whole host, in numpy.

`RobotHost` steps its robots through `advance()` here. Each robot's controllers (watchdog,
velocity ramps, MOVE and HEAD) stay the robot's own scalar code (`SimRobot.propose` and
`commit`); what costs the square of the team size when done robot by robot is done here for
all robots at once:

- collisions: the clearance of every moving robot before and after its proposed move, against
  the world's walls, circles and polygons (arrays) and against the other robots found through a
  k-d tree (`scipy.spatial.cKDTree`) within the only distance that can change the answer;
- sonar: every transducer due in this round, three rays each, cast against the walls and
  circles and against the robots the tree finds within sonar range.

Every robot sees the others where they stood at the start of the round (the robot-by-robot
loop let a robot see the ones stepped before it at their new place). For the same state each
number is the one `SimRobot.step` and `SimRobot.sonar_reading` give, by the same arithmetic:
sonar ranges are bit for bit equal; clearances may differ in the last bit (numpy's hypot
against Python's), which never moves a reported millimetre.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import NDArray
from scipy.spatial import cKDTree

from erni.sim.world import World

if TYPE_CHECKING:
    from erni.plugins.motion.robots import Transducer
    from erni.sim.robot import ArcosFirmware, SimRobot

SPREADS = (-0.13, 0.0, 0.13)
"""The three rays (rad, off the transducer's axis) that make one sonar cone, as `SimRobot.sonar_reading`."""
CONE_SIN = math.sin(max(abs(s) for s in SPREADS))


class WorldArrays:
    """A world's obstacles as arrays: `rays` and `clearances` answer for many rays or points at once.

    Each element gives the same number as `World.ray` / `World.clearance` without `extra`, by the
    same arithmetic (clearances may differ in the last bit: numpy's hypot against Python's).
    """

    def __init__(self, world: World) -> None:
        segs = [(a[0], a[1], b[0], b[1]) for a, b in world.segments()]
        self.segments: NDArray[np.float64] = np.array(segs, dtype=float).reshape(-1, 4)
        circles = [(c.center[0], c.center[1], c.radius) for c in world.circle]
        self.circles: NDArray[np.float64] = np.array(circles, dtype=float).reshape(-1, 3)
        self.polygons = [np.array(poly.points, dtype=float).reshape(-1, 2) for poly in world.polygon]

    def rays(self, x: NDArray[np.float64], y: NDArray[np.float64], angle: NDArray[np.float64],
             max_range: NDArray[np.float64] | float) -> NDArray[np.float64]:
        """Distances (M,) along rays from (x, y) at `angle` (rad) to the first obstacle, capped at max_range."""
        dx, dy = np.cos(angle), np.sin(angle)
        best = np.broadcast_to(np.asarray(max_range, dtype=float), x.shape).copy()
        if len(self.segments):
            best = np.minimum(best, ray_segments(x, y, dx, dy, self.segments).min(axis=1))
        if len(self.circles):
            c = self.circles
            t = ray_circles(x[:, None], y[:, None], dx[:, None], dy[:, None], c[None, :, 0], c[None, :, 1],
                            c[None, :, 2])
            best = np.minimum(best, t.min(axis=1))
        return best

    def clearances(self, x: NDArray[np.float64], y: NDArray[np.float64], circles: bool = True) -> NDArray[np.float64]:
        """Distances (M,) from the points to the nearest obstacle surface (0 inside a solid, inf if none);
        circles=False leaves the circles out (the caller measures them through an index)."""
        best = np.full(x.shape, np.inf)
        if len(self.segments):
            s = self.segments
            ax, ay, ex, ey = s[:, 0], s[:, 1], s[:, 2] - s[:, 0], s[:, 3] - s[:, 1]
            length2 = ex * ex + ey * ey
            with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
                t = ((x[:, None] - ax) * ex + (y[:, None] - ay) * ey) / length2
            t = np.where(length2 == 0, 0.0, np.maximum(0.0, np.minimum(1.0, t)))
            d = np.hypot(x[:, None] - (ax + t * ex), y[:, None] - (ay + t * ey))
            best = np.minimum(best, d.min(axis=1))
        if circles and len(self.circles):
            c = self.circles
            d = np.maximum(0.0, np.hypot(x[:, None] - c[:, 0], y[:, None] - c[:, 1]) - c[:, 2])
            best = np.minimum(best, d.min(axis=1))
        for pts in self.polygons:
            best[inside(x, y, pts)] = 0.0
        return best


def ray_segments(x: NDArray[np.float64], y: NDArray[np.float64], dx: NDArray[np.float64],
                 dy: NDArray[np.float64], segs: NDArray[np.float64]) -> NDArray[np.float64]:
    """Distances (M, K) along M rays (origin x, y; unit direction dx, dy) to K segments; inf on a miss."""
    ex, ey = segs[:, 2] - segs[:, 0], segs[:, 3] - segs[:, 1]
    denom = dx[:, None] * ey - dy[:, None] * ex
    ax, ay = segs[:, 0] - x[:, None], segs[:, 1] - y[:, None]
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        t = (ax * ey - ay * ex) / denom
        u = (ax * dy[:, None] - ay * dx[:, None]) / denom
    hit = (np.abs(denom) >= 1e-12) & (t >= 0.0) & (u >= 0.0) & (u <= 1.0)
    return np.where(hit, t, np.inf)


def ray_circles(x: NDArray[np.float64], y: NDArray[np.float64], dx: NDArray[np.float64], dy: NDArray[np.float64],
                cx: NDArray[np.float64], cy: NDArray[np.float64], r: NDArray[np.float64]) -> NDArray[np.float64]:
    """Distances along rays to circles (broadcast together); 0 from inside a circle, inf on a miss."""
    fx, fy = x - cx, y - cy
    b = fx * dx + fy * dy
    cc = fx * fx + fy * fy - r * r
    disc = b * b - cc
    s = np.sqrt(np.maximum(disc, 0.0))
    near, far = -b - s, -b + s
    t = np.where(near >= 0, near, np.where(far >= 0, 0.0, np.inf))
    return np.where(disc < 0, np.inf, t)


def inside(x: NDArray[np.float64], y: NDArray[np.float64], pts: NDArray[np.float64]) -> NDArray[np.bool_]:
    """Mask of the points inside the closed outline `pts` (K, 2), by the same even-odd rule as `World`."""
    result = np.zeros(x.shape, dtype=bool)
    j = len(pts) - 1
    for i in range(len(pts)):
        (xi, yi), (xj, yj) = pts[i], pts[j]
        straddle = (yi > y) != (yj > y)
        with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
            result ^= straddle & (x < (xj - xi) * (y - yi) / (yj - yi) + xi)
        j = i
    return result


def _near(x: NDArray[np.float64], y: NDArray[np.float64], tree: cKDTree,
          cutoff: float) -> tuple[NDArray[np.intp], NDArray[np.intp]]:
    """Every (point k, tree point j) no farther apart than `cutoff`."""
    if len(x) == 0 or tree.n == 0:
        empty = np.zeros(0, dtype=np.intp)
        return empty, empty
    m = cKDTree(np.column_stack([x, y])).sparse_distance_matrix(tree, cutoff, output_type="ndarray")
    return m["i"].astype(np.intp), m["j"].astype(np.intp)


class Swarm:
    """The robots of one host and their world, stepped and sensed together."""

    def __init__(self, world: World) -> None:
        self.world = world
        self.arrays = WorldArrays(world)
        self._transducers: dict[tuple[Transducer | None, ...], tuple[NDArray[np.float64], NDArray[np.bool_]]] = {}

    def _discs(self, xs: NDArray[np.float64], ys: NDArray[np.float64],
               radius: NDArray[np.float64]) -> tuple[NDArray[np.float64], cKDTree]:
        """The world's circles then the robots, as (x, y, r) rows, and a k-d tree of their centres."""
        discs = np.concatenate([self.arrays.circles, np.column_stack([xs, ys, radius])])
        return discs, cKDTree(discs[:, :2])

    def step(self, robots: Sequence[SimRobot], dt: float, now: float) -> None:
        """Advance every robot by dt, as `SimRobot.step` does one, against a snapshot of the others."""
        if dt <= 0 or not robots:
            return
        n = len(robots)
        xs = np.array([r.x for r in robots])
        ys = np.array([r.y for r in robots])
        radius = np.array([r.config.radius for r in robots])
        proposals = [r.propose(dt, now) for r in robots]
        movers = np.array([i for i, r in enumerate(robots) if abs(r.v) > 1e-9], dtype=np.intp)
        blocked = [False] * n
        if len(movers):
            nx = np.array([proposals[i][1] for i in movers])
            ny = np.array([proposals[i][2] for i in movers])
            here = self.arrays.clearances(xs[movers], ys[movers], circles=False)
            there = self.arrays.clearances(nx, ny, circles=False)
            discs, tree = self._discs(xs, ys, radius)
            # Only a disc nearer than (own radius + step + its radius) can make a move blocked:
            # `there` matters only below the own radius, and `here` <= `there` + step.
            steps = np.hypot(nx - xs[movers], ny - ys[movers])
            cutoff = float(radius.max() + steps.max() + discs[:, 2].max()) + 1e-6
            own = len(self.arrays.circles) + movers
            for points, out in (((xs[movers], ys[movers]), here), ((nx, ny), there)):
                query, disc = _near(points[0], points[1], tree, cutoff)
                keep = disc != own[query]
                query, disc = query[keep], disc[keep]
                if len(query):
                    d = np.maximum(0.0, np.hypot(points[0][query] - discs[disc, 0], points[1][query] - discs[disc, 1])
                                   - discs[disc, 2])
                    np.minimum.at(out, query, d)
            for k, i in enumerate(movers.tolist()):
                blocked[i] = robots[i].blocked(float(here[k]), float(there[k]))
        for r, (tv, px, py, th2), b in zip(robots, proposals, blocked):
            r.commit(dt, tv, px, py, th2, b)

    def fire(self, firmwares: Sequence[ArcosFirmware], now: float) -> None:
        """Fire every transducer due by `now` on every robot, as `ArcosFirmware` does robot by robot."""
        owners: list[int] = []
        nums: list[int] = []
        due_of: list[tuple[ArcosFirmware, list[int]]] = []
        for i, fw in enumerate(firmwares):
            due = fw.due_firings(now)
            if due:
                due_of.append((fw, due))
                owners += [i] * len(due)
                nums += due
        if not owners:
            return
        ranges = self.sonar([fw.robot for fw in firmwares], owners, nums)
        k = 0
        for fw, due in due_of:
            fw.record_firings(due, ranges[k:k + len(due)])
            k += len(due)

    def sonar(self, robots: Sequence[SimRobot], owners: Sequence[int], nums: Sequence[int]) -> list[float | None]:
        """The range (m) each transducer nums[k] of robots[owners[k]] reads now (None: not fitted)."""
        xs = np.array([r.x for r in robots])
        ys = np.array([r.y for r in robots])
        th = np.array([r.th for r in robots])
        radius = np.array([r.config.radius for r in robots])
        reach = np.array([r.config.sonar_range for r in robots])
        own = np.asarray(owners, dtype=np.intp)
        pose = np.zeros((len(own), 3))
        fitted = np.zeros(len(own), dtype=bool)
        tables: dict[int, tuple[NDArray[np.float64], NDArray[np.bool_]]] = {}
        for k, (i, num) in enumerate(zip(owners, nums)):
            if i not in tables:
                tables[i] = self._table(robots[i].config.sonar)
            table, ok = tables[i]
            if 0 <= num < len(ok) and ok[num]:
                pose[k] = table[num]
                fitted[k] = True
        c, s = np.cos(th[own]), np.sin(th[own])
        sx, sy = pose[:, 0], pose[:, 1]
        ox = xs[own] + c * sx - s * sy
        oy = ys[own] + s * sx + c * sy
        a = th[own] + pose[:, 2]
        rng = reach[own]
        best = rng.copy()
        if len(self.arrays.segments):
            for spread in SPREADS:
                ang = a + spread
                hit = ray_segments(ox, oy, np.cos(ang), np.sin(ang), self.arrays.segments).min(axis=1)
                best = np.minimum(best, hit)
        discs, tree = self._discs(xs, ys, radius)
        query, disc = _near(ox, oy, tree, float(reach.max() + discs[:, 2].max()) + 1e-6)
        # Keep only the discs a ray of the cone can reach before the nearest echo so far: not the
        # robot itself, nearer than that echo, ahead of the transducer, within the cone's spread.
        cx, cy, rj = discs[disc, 0], discs[disc, 1], discs[disc, 2]
        fx, fy = cx - ox[query], cy - oy[query]
        ux, uy = np.cos(a[query]), np.sin(a[query])
        along = fx * ux + fy * uy
        across = np.abs(fx * uy - fy * ux)
        d2 = fx * fx + fy * fy
        near = best[query] + rj
        keep = ((disc != len(self.arrays.circles) + own[query]) & (d2 < near * near) & (along > -rj)
                & (across <= rj + np.sqrt(d2) * CONE_SIN + 1e-9))
        query, cx, cy, rj = query[keep], cx[keep], cy[keep], rj[keep]
        if len(query):
            for spread in SPREADS:
                ang = a[query] + spread
                np.minimum.at(best, query, ray_circles(ox[query], oy[query], np.cos(ang), np.sin(ang), cx, cy, rj))
        return [float(b) if f else None for b, f in zip(best.tolist(), fitted.tolist())]

    def _table(self, sonar: tuple[Transducer | None, ...]) -> tuple[NDArray[np.float64], NDArray[np.bool_]]:
        """A sonar ring's transducer poses (x m, y m, rad) and which sonar numbers are fitted."""
        if sonar not in self._transducers:
            table = np.array([(t[0], t[1], math.radians(t[2])) if t is not None else (0.0, 0.0, 0.0)
                              for t in sonar], dtype=float).reshape(-1, 3)
            self._transducers[sonar] = (table, np.array([t is not None for t in sonar], dtype=bool))
        return self._transducers[sonar]
