"""The world as agents see it, published beside tasks: where each robot is (`Pose`) and what the
network subsystem says (`NetInfo`, made of `Neighbor`, `Link`, `Route` and `Position` rows).

`erni.blackboard.tasks` re-exports each of them (its import paths keep working).
"""

from __future__ import annotations

from collections.abc import Callable, Container, Iterable
from typing import Any

from pydantic import ConfigDict, Field, model_validator

from erni.blackboard.clock import wall
from erni.blackboard.objects import BBObject, Model
from erni.blackboard.text import Name

__all__ = ["Link", "Neighbor", "NetInfo", "Pose", "Position", "Route", "best_links"]


class Pose(BBObject):
    """Where a robot is and how it is doing; one per robot, changed in place (`pose:<robot>`)."""

    robot: Name
    x: float = 0.0
    y: float = 0.0
    theta: float = Field(0.0, description="heading (rad, counter-clockwise from +x)")
    v: float = Field(0.0, description="linear velocity (m/s)")
    w: float = Field(0.0, description="angular velocity (rad/s)")
    battery: float | None = Field(None, description="battery voltage (V)")
    stall_left: bool = False
    stall_right: bool = False
    bumpers: int = 0
    motors_enabled: bool = True
    sonar: list[float] = Field(default_factory=list, description="sonar ranges (m)")
    stamp: float = Field(default_factory=wall)

    @model_validator(mode="before")
    @classmethod
    def _stable_uid(cls, data: Any) -> Any:
        if isinstance(data, dict) and "uid" not in data and "robot" in data:
            return {**data, "uid": f"pose:{data['robot']}"}
        return data

    @property
    def stalled(self) -> bool:
        """True when either wheel is stalled."""
        return self.stall_left or self.stall_right


class Neighbor(Model):
    """A one-hop neighbour as the network subsystem reports it."""

    model_config = ConfigDict(frozen=True, extra="forbid")

    name: str
    address: str = ""
    quality: float = Field(0.0, ge=0.0, le=1.0, description="link delivery ratio")
    symmetric: bool = True
    metric: int | None = None
    recent: float | None = Field(None, ge=0.0, le=1.0, description="delivery over the last few Hellos only "
                                 "(the newest evidence, noisier than quality); None when the source has none")


class Link(Model):
    """An edge of the network topology."""

    model_config = ConfigDict(frozen=True, extra="forbid")

    a: str
    b: str
    quality: float = Field(0.0, ge=0.0, le=1.0)
    metric: int | None = None


class Route(Model):
    """A route from this node: next hop, hop count and path cost."""

    model_config = ConfigDict(frozen=True, extra="forbid")

    destination: str
    next_hop: str = ""
    hops: int = 0
    cost: float = 0.0


class Position(Model):
    """A node position as the network knows it (m, deg)."""

    model_config = ConfigDict(frozen=True, extra="forbid")

    x: float
    y: float
    heading: float = 0.0


class NetInfo(BBObject):
    """Network state answering one NetWatch preposition; `degraded` when the source failed."""

    node: Name
    kind: str = Field(description="the NetWatch preposition this answers")
    task: str | None = Field(None, description="uid of the NetWatch task")
    neighbors: list[Neighbor] = Field(default_factory=list)
    links: list[Link] = Field(default_factory=list)
    routes: list[Route] = Field(default_factory=list)
    positions: dict[str, Position] = Field(default_factory=dict)
    articulation_points: list[str] = Field(default_factory=list)
    degraded: bool = False
    message: str = ""
    stamp: float = Field(default_factory=wall)
    provenance: dict[str, str] = Field(
        default_factory=dict,
        description="field name -> where its data came from (source and table, e.g. "
                    "'snmp 127.0.0.1:1162 OLSRv2-MIB olsrv2TibRoutingSetTable'), or "
                    "'missing: <why>' when the source does not provide it")


def best_links(infos: Iterable[NetInfo], placed: Container[str], lost: Callable[[str], bool],
               max_age: float, now: float) -> dict[tuple[str, str], tuple[float, bool]]:
    """The links between `placed` nodes that NetInfo reports (its links and its node's neighbours),
    the best of each pair: `{(a, b): (quality, stale)}` with a < b; a link is stale when its NetInfo
    is older than `max_age` s (0: never) or an end is `lost`. A fresh link beats a stale one, then
    the better quality wins. Degraded NetInfo is left out."""
    best: dict[tuple[str, str], tuple[float, bool]] = {}
    for info in infos:
        if info.degraded:
            continue
        old = bool(max_age) and now - info.stamp > max_age
        pairs = [(link.a, link.b, link.quality) for link in info.links]
        pairs += [(info.node, n.name, n.quality) for n in info.neighbors]
        for a, b, q in pairs:
            if a == b or a not in placed or b not in placed:
                continue
            key = (min(a, b), max(a, b))
            stale = old or lost(a) or lost(b)
            if key not in best or (best[key][1], -best[key][0]) > (stale, -q):
                best[key] = (q, stale)
    return best
