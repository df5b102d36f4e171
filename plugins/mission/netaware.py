"""Network-aware behaviour (paper 004, 4.2.3): is this robot's connectivity at risk, and since when.

The guard reads the NetInfo of two NetWatch tasks of the mission: `network_topology` (its links,
with their quality where the routing metric tells it) and `link_quality` (the delivery ratio of
this robot's one-hop links). A link below `min_quality` is about to go, so the topology is judged
without such links: connectivity is at risk when the robot is a cut vertex of what is left (if
`articulation` is on: would the network split without it?), when a weak link of its own is all
that joins its part of the network to another (robots walking off together each keep a weak link
to the control node, and none of them is a cut vertex until the last link is gone), or when its
best link is below `min_quality`. A risk is declared
at once; it is cleared only after `resume_after` seconds without risk (hysteresis, so a robot
on the edge does not stutter). Degraded readings (the network subsystem did not answer)
change nothing. The guard also keeps a trail of positions where connectivity was good; the
`retreat` policy goes back along it (`retreat_point`).
"""

from __future__ import annotations

import math
from collections import deque
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

from erni import netgraph
from erni.blackboard.tasks import Link


@dataclass
class GuardState:
    """The latest readings and the decision derived from them."""

    articulation: bool | None = None
    bridge: str = ""        # the weak link of this robot that alone joins its part to another
    best: float | None = None
    at_risk: bool = False
    reason: str = ""
    ok_since: float | None = None


class NetGuard:
    """Turns topology and link-quality readings into `at risk` / `clear` transitions."""

    def __init__(self, me: str, *, min_quality: float = 0.3, articulation: bool = True,
                 resume_after: float = 1.0) -> None:
        self.me = me
        self.min_quality = min_quality
        self.use_articulation = articulation
        self.resume_after = resume_after
        self.state = GuardState()
        self._judged: tuple[Any, bool, set[str]] = (None, False, set())  # (good links, cut vertex, my part)
        self._rows: list[Link] | None = None  # the links of the last reading
        self.last_good: tuple[float, float] | None = None
        self.trail: deque[tuple[float, float]] = deque(maxlen=200)  # good positions, 0.2 m apart

    def topology(self, links: Sequence[Link]) -> None:
        """Take in a topology reading: its links. Links whose quality is known (any above 0) and
        below `min_quality` are left out of the graph the risk is judged on."""
        rows = list(links)
        if rows == self._rows:
            return  # the very rows of the last reading (a walk not redone; compared by identity): judged
        self._rows = rows
        s = self.state
        known = any(link.quality > 0 for link in links)
        good = [link for link in links if not known or link.quality >= self.min_quality]
        key = (tuple((link.a, link.b) for link in good), len(links))
        if key != self._judged[0]:  # the graph work only when which links are good changed
            adj = netgraph.from_edges(((link.a, link.b) for link in good),
                                      nodes=[self.me, *(n for link in links for n in (link.a, link.b))])
            mine = next(c for c in netgraph.connected_components(adj) if self.me in c)
            self._judged = (key, self.me in netgraph.articulation_points(adj), mine)
        _, s.articulation, mine = self._judged
        across = [(link.quality, link.b if link.a == self.me else link.a) for link in links
                  if self.me in (link.a, link.b)]  # this robot's links: (quality, the other end)
        quality, other = max(((q, n) for q, n in across if n not in mine), default=(0.0, ""))
        s.bridge = f"{other} ({quality:.2f})" if other else ""

    def quality(self, qualities: list[float]) -> None:
        """Take in a link-quality reading: the delivery ratios of this robot's one-hop links."""
        self.state.best = max(qualities, default=0.0)

    def risk(self) -> str:
        """Why connectivity is at risk now ("" when it is not, or nothing was read yet)."""
        s = self.state
        if self.use_articulation and s.articulation:
            return f"{self.me} is an articulation point of the network"
        if self.use_articulation and s.bridge:
            return f"{self.me}'s weak link to {s.bridge} alone joins it to the rest of the network"
        if s.best is not None and s.best < self.min_quality:
            return f"best link quality {s.best:.2f} is below {self.min_quality:.2f}"
        return ""

    def update(self, now: float, position: tuple[float, float] | None) -> str | None:
        """Re-evaluate; return "risk" or "clear" on a transition, else None."""
        reason = self.risk()
        s = self.state
        if reason:
            s.ok_since = None
            s.reason = reason
            if not s.at_risk:
                s.at_risk = True
                return "risk"
            return None
        if position is not None and s.best is not None and not s.at_risk:
            self.last_good = position
            if not self.trail or math.dist(self.trail[-1], position) >= 0.2:
                self.trail.append(position)
        if not s.at_risk:
            return None
        if s.ok_since is None:
            s.ok_since = now
        if now - s.ok_since >= self.resume_after:
            s.at_risk = False
            s.reason = ""
            s.ok_since = None
            return "clear"
        return None

    def pending_clear_in(self, now: float) -> float | None:
        """Seconds until a pending clear is due (None when none is pending)."""
        s = self.state
        if s.at_risk and s.ok_since is not None:
            return max(0.0, self.resume_after - (now - s.ok_since))
        return None

    def retreat_point(self, here: tuple[float, float], distance: float) -> tuple[float, float] | None:
        """The latest good position at least `distance` m from `here` (else the oldest); None if none."""
        for point in reversed(self.trail):
            if math.dist(point, here) >= distance:
                return point
        return self.trail[0] if self.trail else None
