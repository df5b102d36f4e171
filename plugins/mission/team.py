"""What the mission knows about the team: positions (Pose and NetWatch node_position) and patrol heartbeats.

`TeamView` keeps the newest known position of every robot, from `Pose` objects on the
blackboard (this robot's own, and peers' poses shared by the transport) and from the
positions MobiNet reports for a NetWatch `node_position` task; a position older than
`timeout` seconds is forgotten. It also keeps, per robot, since when its position has stayed
within `still_tolerance` m (`settled`): a deployment step decided on settled positions only
is decided on the snapshot the synchronous algorithms assume. `Territory` is the patrol heartbeat a robot publishes (uid
`territory:<robot>`), shared with the other robots by the transport (`share` setting).
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING

from pydantic import Field

from erni.blackboard import BBObject, NetInfo, Pose
from erni.blackboard.clock import SYSTEM, Clock, wall

if TYPE_CHECKING:
    import numpy as np
    from numpy.typing import NDArray


class Territory(BBObject):
    """A patrolling robot's heartbeat: its block, the robots whose blocks it holds, its claims."""

    robot: str
    task: str = ""
    block: tuple[float, float, float, float]
    holds: list[str] = Field(default_factory=list)
    claims: dict[str, float] = Field(default_factory=dict, description="silent robot -> claim time (s)")
    beat: int = 0
    stamp: float = Field(default_factory=wall)


try:  # the transport carries the heartbeat between robots when it knows the type
    from erni.transport.wire import register_type
except ImportError:  # pragma: no cover - the transport is part of the distribution
    pass
else:
    register_type(Territory)


class TeamView:
    """Newest known (x, y, heading rad) of each robot, with the time it was learned."""

    def __init__(self, me: str, timeout: float = 5.0, still_tolerance: float = 0.03, *,
                 clock: Clock = SYSTEM) -> None:
        self.me = me
        self.clock = clock  # its wall reading is "now" for a caller that gives none (stamps are wall-clock)
        self.timeout = timeout
        self.still_tolerance = still_tolerance
        self.where: dict[str, tuple[float, float, float, float]] = {}  # name -> (x, y, theta, stamp)
        self.anchor: dict[str, tuple[float, float, float]] = {}  # name -> (x, y, stamp): where it stopped, since
        self.roles: dict[str, str] = {}  # agent name -> transport role ("robot", "control", ...), when known

    def pose(self, pose: Pose) -> None:
        """Take in a Pose (newest stamp wins)."""
        self._put(pose.robot, pose.x, pose.y, pose.theta, pose.stamp)

    def netinfo(self, info: NetInfo) -> None:
        """Take in the positions of a node_position NetInfo (never overriding this robot's own Pose)."""
        if info.degraded:
            return
        for name, p in info.positions.items():
            if name == self.me and self.me in self.where:
                continue
            self._put(name, p.x, p.y, math.radians(p.heading), info.stamp)

    def _put(self, name: str, x: float, y: float, theta: float, stamp: float) -> None:
        old = self.where.get(name)
        if old is None or stamp >= old[3]:
            self.where[name] = (x, y, theta, stamp)
            still = self.anchor.get(name)
            if still is None or math.hypot(x - still[0], y - still[1]) > self.still_tolerance:
                self.anchor[name] = (x, y, stamp)

    def settled(self, name: str, fresh_after: float, still_for: float) -> bool:
        """True when `name`'s newest position was learned after `fresh_after` and had not moved
        (beyond `still_tolerance`) for at least `still_for` s before that (times in s, epoch)."""
        w, still = self.where.get(name), self.anchor.get(name)
        if w is None or still is None:
            return False
        return w[3] >= fresh_after and w[3] - still[2] >= still_for

    def fresh(self, now: float | None = None) -> dict[str, tuple[float, float, float]]:
        """Positions learned within `timeout` seconds (this robot's own is always kept)."""
        now = self.clock.wall() if now is None else now
        return {n: (x, y, th) for n, (x, y, th, s) in self.where.items()
                if n == self.me or now - s <= self.timeout}

    def mine(self) -> tuple[float, float, float] | None:
        """This robot's (x, y, theta), or None before its first Pose."""
        w = self.where.get(self.me)
        return None if w is None else w[:3]

    def role(self, name: str, role: str) -> None:
        """Remember that agent `name` has transport role `role` (from its Peer object)."""
        self.roles[name] = role

    def is_robot(self, name: str) -> bool:
        """Whether `name` is a robot: its role says so, or is not known yet."""
        return self.roles.get(name, "robot") == "robot"

    def array(self, now: float | None = None, *, everyone: bool = False,
              robots_only: bool = False) -> tuple[list[str], NDArray[np.float64]]:
        """Names and an (N, 2) array of fresh positions (or all known with `everyone`), this robot first.

        `robots_only` leaves out the nodes known not to be robots (a control node, by its role).
        """
        if everyone:
            known = {n: w[:3] for n, w in self.where.items()}
        else:
            known = self.fresh(now)
        if robots_only:
            known = {n: w for n, w in known.items() if self.is_robot(n) or n == self.me}
        import numpy as np  # a deployment strategy asks: numpy is imported then, not at agent start

        names = [self.me] + sorted(n for n in known if n != self.me) if self.me in known else sorted(known)
        return names, np.array([known[n][:2] for n in names], dtype=float).reshape(-1, 2)

    def stale(self, names: list[str], now: float | None = None) -> list[str]:
        """The robots among `names` (this one excepted) whose position is older than `timeout`."""
        now = self.clock.wall() if now is None else now
        return [n for n in names if n != self.me and n in self.where and now - self.where[n][3] > self.timeout]
