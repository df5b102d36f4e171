"""The floor plan drawn under the robots: walls, round and polygonal obstacles, room bounds.

It reads the world files of the simulator (`examples/world-*.toml`: `bounds`, `[[wall]]`,
`[[circle]]`, `[[polygon]]`); other keys (robot starts, names) are ignored, so a floor plan
written for a real arena needs only the obstacles.
"""

from __future__ import annotations

import tomllib
from pathlib import Path
from typing import Any

from pydantic import BaseModel, ConfigDict, Field, ValidationError

Point = tuple[float, float]


class _Shape(BaseModel):
    model_config = ConfigDict(extra="ignore", frozen=True)


class Wall(_Shape):
    a: Point
    b: Point


class Circle(_Shape):
    center: Point
    radius: float = Field(gt=0)


class Polygon(_Shape):
    points: list[Point] = Field(min_length=3)


class FloorPlan(_Shape):
    """Obstacles in metres, as the page draws them."""

    bounds: tuple[float, float, float, float] | None = None
    wall: list[Wall] = Field(default_factory=list)
    circle: list[Circle] = Field(default_factory=list)
    polygon: list[Polygon] = Field(default_factory=list)


def load_floorplan(path: str | Path) -> dict[str, Any]:
    """Return a floor plan file as JSON-ready data, or raise ValueError naming the file and field."""
    path = Path(path)
    try:
        data = tomllib.loads(path.read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise ValueError(f"{path}: no such floor plan file") from None
    except (OSError, UnicodeDecodeError, tomllib.TOMLDecodeError) as err:
        raise ValueError(f"{path}: not a readable TOML floor plan ({err})") from None
    try:
        return FloorPlan.model_validate(data).model_dump(mode="json")
    except ValidationError as err:
        problems = [f"{'.'.join(str(p) for p in e['loc'])}: {e['msg']}" for e in err.errors()]
        raise ValueError(f"{path}: " + "; ".join(problems)) from None
