"""The simulated world: walls, circular and polygonal obstacles in metres, loaded from TOML.

A world file looks like this (every table is optional)::

    name = "lab"
    bounds = [-5.0, -5.0, 5.0, 5.0]        # xmin, ymin, xmax, ymax: four enclosing walls

    [[wall]]                               # a segment from a to b
    a = [2.0, -1.0]
    b = [2.0, 1.0]

    [[circle]]                             # a pillar, a bin, a person
    center = [0.0, 3.0]
    radius = 0.3

    [[polygon]]                            # a closed outline (last point joins the first)
    points = [[-3, -3], [-2, -3], [-2, -2]]

    [[robot]]                              # where simulated robots start
    name = "robot1"
    x = 0.0
    y = 0.0
    heading = 0.0                          # degrees, counter-clockwise from +x

Geometry queries (`ray`, `clearance`, `crossings`) serve the robot's sonar and bumpers, and
the radio model (walls between two nodes).
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Iterator
from pathlib import Path
from typing import Any

from pydantic import ConfigDict, Field, ValidationError

from erni.blackboard.errors import ConfigError, describe_validation
from erni.blackboard.objects import Model
from erni.blackboard.schemas import FloorPlan, Point, read_toml

Segment = tuple[Point, Point]


class WorldError(ConfigError):
    """A world file is missing, unreadable or invalid."""


class _Model(Model):
    model_config = ConfigDict(frozen=True, extra="forbid")


class RobotStart(_Model):
    """The initial pose of a simulated robot (m, m, degrees)."""

    name: str = ""
    x: float = 0.0
    y: float = 0.0
    heading: float = 0.0


class World(FloorPlan):
    """Obstacles (the floor plan) and robot start poses; all coordinates in metres."""

    name: str = "world"
    robot: list[RobotStart] = Field(default_factory=list)

    # --- loading ------------------------------------------------------------------------

    @classmethod
    def load(cls, path: str | Path) -> World:
        """Read a world TOML file; raise WorldError naming the file and the bad field."""
        return cls.from_dict(read_toml(path, "world", WorldError), source=str(path))

    @classmethod
    def from_dict(cls, data: dict[str, Any], source: str = "world") -> World:
        """Validate a world from plain data; raise WorldError with one line per problem."""
        try:
            return cls.model_validate(data)
        except ValidationError as err:
            raise WorldError(describe_validation(err, source)) from None

    def start_pose(self, index: int, name: str = "") -> RobotStart:
        """Return the start pose for robot `name` (or the index-th start, or the origin)."""
        for start in self.robot:
            if name and start.name == name:
                return start
        if index < len(self.robot):
            return self.robot[index]
        return RobotStart(name=name, x=float(index), y=0.0)

    # --- geometry -----------------------------------------------------------------------

    def segments(self) -> Iterator[Segment]:
        """Yield every blocking segment: walls, bounds and polygon edges."""
        if self.bounds is not None:
            xmin, ymin, xmax, ymax = self.bounds
            corners = [(xmin, ymin), (xmax, ymin), (xmax, ymax), (xmin, ymax)]
            for i in range(4):
                yield corners[i], corners[(i + 1) % 4]
        for w in self.wall:
            yield w.a, w.b
        for poly in self.polygon:
            pts = poly.points
            for i in range(len(pts)):
                yield pts[i], pts[(i + 1) % len(pts)]

    def ray(self, x: float, y: float, angle: float, max_range: float,
            extra: Iterable[tuple[Point, float]] = ()) -> float:
        """Return the distance along a ray from (x, y) at `angle` (rad) to the first obstacle, capped."""
        dx, dy = math.cos(angle), math.sin(angle)
        best = max_range
        for a, b in self.segments():
            d = _ray_segment(x, y, dx, dy, a, b)
            if d is not None and d < best:
                best = d
        for c in self.circle:
            d = _ray_circle(x, y, dx, dy, c.center, c.radius)
            if d is not None and d < best:
                best = d
        for center, radius in extra:
            d = _ray_circle(x, y, dx, dy, center, radius)
            if d is not None and d < best:
                best = d
        return best

    def clearance(self, x: float, y: float, extra: Iterable[tuple[Point, float]] = ()) -> float:
        """Return the distance from (x, y) to the nearest obstacle surface (0 inside a solid)."""
        best = math.inf
        for a, b in self.segments():
            best = min(best, _point_segment(x, y, a, b))
        for c in self.circle:
            best = min(best, max(0.0, math.hypot(x - c.center[0], y - c.center[1]) - c.radius))
        for center, radius in extra:
            best = min(best, max(0.0, math.hypot(x - center[0], y - center[1]) - radius))
        for poly in self.polygon:
            if _inside(x, y, poly.points):
                return 0.0
        return best

    def crossings(self, p: Point, q: Point) -> int:
        """Return how many walls, polygon edges and circles the segment p-q passes through."""
        n = 0
        for a, b in self.segments():
            if _segments_cross(p, q, a, b):
                n += 1
        for c in self.circle:
            if _point_segment(c.center[0], c.center[1], p, q) < c.radius:
                n += 1
        return n

    def line_of_sight(self, p: Point, q: Point) -> bool:
        """True when nothing blocks the straight line between p and q."""
        return self.crossings(p, q) == 0


def _ray_segment(x: float, y: float, dx: float, dy: float, a: Point, b: Point) -> float | None:
    ex, ey = b[0] - a[0], b[1] - a[1]
    denom = dx * ey - dy * ex
    if abs(denom) < 1e-12:
        return None
    ax, ay = a[0] - x, a[1] - y
    t = (ax * ey - ay * ex) / denom
    u = (ax * dy - ay * dx) / denom
    if t >= 0.0 and 0.0 <= u <= 1.0:
        return t
    return None


def _ray_circle(x: float, y: float, dx: float, dy: float, c: Point, r: float) -> float | None:
    fx, fy = x - c[0], y - c[1]
    b = fx * dx + fy * dy
    cc = fx * fx + fy * fy - r * r
    disc = b * b - cc
    if disc < 0:
        return None
    s = math.sqrt(disc)
    t = -b - s
    if t >= 0:
        return t
    t = -b + s
    return 0.0 if t >= 0 else None  # starting inside the circle: touching


def _point_segment(x: float, y: float, a: Point, b: Point) -> float:
    ex, ey = b[0] - a[0], b[1] - a[1]
    length2 = ex * ex + ey * ey
    t = 0.0 if length2 == 0 else max(0.0, min(1.0, ((x - a[0]) * ex + (y - a[1]) * ey) / length2))
    return math.hypot(x - (a[0] + t * ex), y - (a[1] + t * ey))


def _orient(p: Point, q: Point, r: Point) -> float:
    return (q[0] - p[0]) * (r[1] - p[1]) - (q[1] - p[1]) * (r[0] - p[0])


def _segments_cross(p: Point, q: Point, a: Point, b: Point) -> bool:
    d1, d2 = _orient(a, b, p), _orient(a, b, q)
    d3, d4 = _orient(p, q, a), _orient(p, q, b)
    return ((d1 > 0) != (d2 > 0)) and ((d3 > 0) != (d4 > 0)) and d1 != 0 and d2 != 0


def _inside(x: float, y: float, pts: list[Point]) -> bool:
    inside = False
    j = len(pts) - 1
    for i in range(len(pts)):
        xi, yi = pts[i]
        xj, yj = pts[j]
        if (yi > y) != (yj > y) and x < (xj - xi) * (y - yi) / (yj - yi) + xi:
            inside = not inside
        j = i
    return inside
