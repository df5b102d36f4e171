"""Shapes of data that pass between the layers of ERNI, declared once and imported by both sides.

- `Peer` (peer.py) and the transport's messages (messages.py), re-exported here.
- Floor-plan geometry in metres: `Wall`, `Circle`, `Polygon`, `FloorPlan`. The simulator's
  world extends `FloorPlan` with robot start poses; the GUI draws a `FloorPlan`.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from pydantic import ConfigDict, Field, ValidationError, model_validator

from erni.blackboard import tomlfile
from erni.blackboard.errors import ConfigError, describe_validation
from erni.blackboard.messages import Beacon as Beacon
from erni.blackboard.messages import Cancel as Cancel
from erni.blackboard.messages import Fresh as Fresh
from erni.blackboard.messages import PeerList as PeerList
from erni.blackboard.messages import ResultUpdate as ResultUpdate
from erni.blackboard.messages import StatusRemoved as StatusRemoved
from erni.blackboard.messages import StatusResend as StatusResend
from erni.blackboard.messages import TaskQuery as TaskQuery
from erni.blackboard.messages import TaskRescind as TaskRescind
from erni.blackboard.messages import TaskUnknown as TaskUnknown
from erni.blackboard.messages import WatchEvent as WatchEvent
from erni.blackboard.messages import WatchRequest as WatchRequest
from erni.blackboard.objects import Model
from erni.blackboard.peer import Peer as Peer

# --- floor-plan geometry --------------------------------------------------------------------

Point = tuple[float, float]


class _Shape(Model):
    model_config = ConfigDict(frozen=True, extra="forbid")


class Wall(_Shape):
    """A straight wall from `a` to `b` (m)."""

    a: Point
    b: Point


class Circle(_Shape):
    """A round obstacle (m)."""

    center: Point
    radius: float = Field(gt=0)


class Polygon(_Shape):
    """A closed polygonal obstacle; its edges block like walls and its inside is solid."""

    points: list[Point] = Field(min_length=3)


class FloorPlan(_Shape):
    """Obstacles and room bounds in metres: what a map shows and a simulated world is made of."""

    bounds: tuple[float, float, float, float] | None = Field(
        None, description="xmin, ymin, xmax, ymax: adds four enclosing walls")
    wall: list[Wall] = Field(default_factory=list)
    circle: list[Circle] = Field(default_factory=list)
    polygon: list[Polygon] = Field(default_factory=list)

    @model_validator(mode="after")
    def _check_bounds(self) -> FloorPlan:
        if self.bounds is not None:
            xmin, ymin, xmax, ymax = self.bounds
            if not (xmin < xmax and ymin < ymax):
                raise ValueError(f"bounds {list(self.bounds)}: expected xmin < xmax and ymin < ymax")
        return self


def read_toml(path: str | Path, what: str, error: type[ConfigError] = ConfigError) -> dict[str, Any]:
    """Return a TOML file's table, or raise `error` naming the file and saying what was expected."""
    path = Path(path)
    return tomlfile.loads(tomlfile.read_text(path, what, error), str(path), error)


def load_floorplan(path: str | Path) -> FloorPlan:
    """Read the obstacles of a floor plan or world file (other tables, such as robot starts, are
    ignored); raise ConfigError naming the file and the bad field."""
    data = read_toml(path, "floor plan")
    shapes = {key: data[key] for key in FloorPlan.model_fields if key in data}
    try:
        return FloorPlan.model_validate(shapes)
    except ValidationError as err:
        raise ConfigError(describe_validation(err, str(path))) from None
