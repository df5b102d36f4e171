"""Network-aware behaviour (paper 004, 4.2.3): is this robot's connectivity at risk, and since when.

The guard reads the NetInfo of two NetWatch tasks of the mission: `network_topology` (its links,
with their quality where the routing metric tells it) and `link_quality` (the delivery ratio of
this robot's one-hop links). A link below `min_quality` is about to go, so the topology is judged
without such links: connectivity is at risk when the robot is a cut vertex of what is left (if
`articulation` is on: would the network split without it?), when a weak link of its own is all
that joins its part of the network to another (robots walking off together each keep a weak link
to the control node, and none of them is a cut vertex until the last link is gone), or when its
best link is below `min_quality`.

Readings come late: a routing daemon's link quality is an average over its last Hellos (babeld:
about twelve), MobiNet polls it, and a robot driving at 1 m/s covers metres in that time and
more while it brakes. So the guard also predicts. For each *critical* link (one whose loss would
cut this robot off from its neighbour, the link that holds it to the team: a bridge of the graph
of every known link), while the robot moves away from that neighbour, it projects the link's
quality over the horizon H = `latency` + braking time (speed / `braking`) + 0.2 s, two ways, and
takes the lower:

- the trend: the least-squares slope of the link's readings over the last `trend_window`
  seconds, applied from the newest reading over H;
- the motion: once the link shows loss (a reading below 0.98), the speed away from the neighbour
  times H, over `fade_distance`, the distance in which a link's quality falls from 1 to 0 (the
  guard's model of the radio; short is cautious).

A projection below `min_quality` is a risk ("the link to N is predicted to fall below ..."),
so the robot stands while the link still carries packets. With no critical link (several links
hold the robot), the risk is every link's projection (or reading, for a neighbour it does not
move away from) below `min_quality`: the best link going too. A risk is declared at once; it
clears only after every reading has stayed free of risk, with every critical link (with none:
the best link) at least `resume_quality`, for `resume_after` seconds (hysteresis: a momentary better reading clears
nothing). A remote goto or forward that takes the robot away from the neighbour of a critical link
is driven no faster than `safe_speed()`: fast enough to stand within half of `fade_distance`
after the first sign of loss, however late the readings bring it (loss-free readings tell
nothing of where the lossy band begins). Clearing is not resuming: the mission resumes a held motion only when it does not take
the robot further from a neighbour that showed loss lately over a critical link, or over the
link whose quality last held it (`away`; a hold for being an articulation point alone names no
link); a motion that
improves connectivity is always allowed. Degraded readings (the network subsystem did not
answer) change nothing. The guard also keeps a trail of positions where connectivity was good;
the `retreat` policy goes back along it (`retreat_point`).

Pure decision code: every time is passed in (`now`, seconds on any one clock).
"""

from __future__ import annotations

import math
from collections import deque
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
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
    critical: dict[str, float] = field(default_factory=dict)  # neighbour of a critical link -> its quality
    closing: dict[str, float] = field(default_factory=dict)   # neighbour -> speed away from it (m/s; < 0: nearer)


@dataclass
class Reading:
    """One link-quality reading of one link."""

    t: float
    quality: float


class NetGuard:
    """Turns topology and link-quality readings into `at risk` / `clear` transitions."""

    def __init__(self, me: str, *, min_quality: float = 0.3, articulation: bool = True,
                 resume_after: float = 3.0, resume_quality: float | None = None, latency: float = 2.5,
                 braking: float = 0.5, fade_distance: float = 4.0, trend_window: float = 4.0,
                 predict: bool = True) -> None:
        self.me = me
        self.min_quality = min_quality
        self.use_articulation = articulation
        self.resume_after = resume_after
        self.resume_quality = min(1.0, min_quality + 0.2) if resume_quality is None else resume_quality
        self.latency = latency
        self.braking = braking
        self.fade_distance = fade_distance
        self.trend_window = trend_window
        self.predict = predict
        self.state = GuardState()
        self.readings: dict[str, deque[Reading]] = {}   # neighbour -> its link's recent readings
        self.moves: deque[tuple[float, float, float]] = deque(maxlen=50)  # (t, x, y) of this robot
        self.where: dict[str, tuple[float, float]] = {}  # neighbours' latest known positions
        self.lossy: dict[str, float] = {}  # neighbour -> when its link last read below 0.98
        self.cause = ""                    # the neighbour over the link whose quality last held the robot
        self.loss_memory = 10.0            # s: a link that showed loss this recently has no room to stretch
        self.prediction = ""
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
        s.articulation, mine = self._judge(rows)
        across = [(link.quality, link.b if link.a == self.me else link.a) for link in links
                  if self.me in (link.a, link.b)]  # this robot's links: (quality, the other end)
        quality, other = max(((q, n) for q, n in across if n not in mine), default=(0.0, ""))
        s.bridge = f"{other} ({quality:.2f})" if other else ""
        edges = tuple((link.a, link.b) for link in links)
        if edges != self._edges:  # which links exist changed: find the critical ones again
            self._edges, self._critical = edges, _bridges(self.me, edges)

    def _judge(self, links: list[Link]) -> tuple[bool, set[str]]:
        """Whether this robot is an articulation point of the graph of good links (those whose quality is
        known, any above 0, and not below `min_quality`), and the nodes it reaches over them; the graph
        work is done again only when which links are good changed."""
        known = any(link.quality > 0 for link in links)
        good = [link for link in links if not known or link.quality >= self.min_quality]
        key = (tuple((link.a, link.b) for link in good), len(links))
        if key != self._judged[0]:
            adj = netgraph.from_edges(((link.a, link.b) for link in good),
                                      nodes=[self.me, *(n for link in links for n in (link.a, link.b))])
            mine = next(c for c in netgraph.connected_components(adj) if self.me in c)
            self._judged = (key, self.me in netgraph.articulation_points(adj), mine)
        return self._judged[1], self._judged[2]

    _critical: set[str] | None = None  # neighbours over critical links (None: no topology read yet)
    _edges: tuple[tuple[str, str], ...] | None = None

    def quality(self, qualities: Mapping[str, float] | Sequence[float], now: float | None = None) -> None:
        """Take in a link-quality reading: the delivery ratios of this robot's one-hop links, by
        neighbour (a bare list judges the best link only: nothing to predict per link)."""
        values = list(qualities.values()) if isinstance(qualities, Mapping) else list(qualities)
        self.state.best = max(values, default=0.0)
        if now is None or not isinstance(qualities, Mapping):
            return
        for name in [n for n in self.readings if n not in qualities]:
            del self.readings[name]
        for name, q in qualities.items():
            rows = self.readings.setdefault(name, deque(maxlen=64))
            rows.append(Reading(now, q))
            if q < 0.98:
                self.lossy[name] = now
            while rows and now - rows[0].t > max(self.trend_window, 1.0) * 2:
                rows.popleft()

    def positions(self, where: Mapping[str, tuple[float, float]]) -> None:
        """Take in the neighbours' latest known positions (x, y) in m."""
        self.where = {n: (p[0], p[1]) for n, p in where.items() if n != self.me}

    def critical(self) -> list[str]:
        """The neighbours over this robot's critical links: the links whose loss would cut it off
        from that neighbour (with no topology read yet: its only neighbour, if it has one)."""
        if self._critical is not None:
            return sorted(n for n in self._critical if n in self.readings) or sorted(self._critical)
        return list(self.readings) if len(self.readings) == 1 else []

    def away_speed(self, name: str) -> float | None:
        """How fast this robot moves away from neighbour `name` (m/s, negative: nearer), over the
        last half second of its positions; None when unknown."""
        there, span = self.where.get(name), self._span()
        if there is None or span is None:
            return None
        (t0, x0, y0), (t1, x1, y1) = span
        return (math.dist((x1, y1), there) - math.dist((x0, y0), there)) / (t1 - t0)

    def projected(self, name: str, now: float) -> tuple[float, str] | None:
        """The quality the link to `name` is projected to reach before the robot can stand, and
        how it was projected; None when it is not moving away or nothing was read."""
        rows = self.readings.get(name)
        if not rows:
            return None
        away = self.away_speed(name)
        speed = self._speed() if away is None else away
        if speed is None or speed <= 0.02:
            return None
        horizon = self.latency + speed / self.braking + 0.2
        last = rows[-1].quality
        best = (last, "")
        recent = [r for r in rows if now - r.t <= self.trend_window]
        if len(recent) >= 3 and recent[-1].t - recent[0].t >= 0.5:
            slope = _slope([(r.t, r.quality) for r in recent])
            if slope < 0:
                fit = sum(r.quality for r in recent) / len(recent) + slope * (recent[-1].t - _mean_t(recent))
                q = fit + slope * (now - recent[-1].t + horizon)
                if q < best[0]:
                    best = (q, f"falling {-slope:.2f}/s")
        if last < 0.98:
            q = last - speed * horizon / self.fade_distance
            if q < best[0]:
                best = (q, f"moving away at {speed:.2f} m/s")
        return best

    def _cause(self, reason: str) -> str:
        """The neighbour over the link a link-quality risk is about ("" when none is known)."""
        s = self.state
        if s.bridge and "weak link to" in reason:
            return s.bridge.split(" (")[0]
        for name in self.readings:
            if f"the link to {name} (" in reason:
                return name
        best = self._best()
        return next(iter(best), "")

    def _best(self) -> dict[str, float]:
        """The neighbour over the best link and its quality ({} when nothing was read)."""
        rows = {n: r[-1].quality for n, r in self.readings.items() if r}
        if not rows:
            return {}
        best = max(rows, key=lambda n: rows[n])
        return {best: rows[best]}

    def _span(self) -> tuple[tuple[float, float, float], tuple[float, float, float]] | None:
        """This robot's (t, x, y) about half a second ago and now; None with less than 0.2 s of positions."""
        if len(self.moves) < 2:
            return None
        now = self.moves[-1]
        old = next((m for m in reversed(self.moves) if now[0] - m[0] >= 0.5), self.moves[0])
        return None if now[0] - old[0] < 0.2 else (old, now)

    def _speed(self) -> float | None:
        span = self._span()
        if span is None:
            return None
        (t0, x0, y0), (t1, x1, y1) = span
        return math.dist((x1, y1), (x0, y0)) / (t1 - t0)

    def safe_speed(self) -> float:
        """The fastest this robot may drive away from the neighbour of a critical link: the speed v
        at which it stands within half of `fade_distance` after the first sign of loss, however
        late that sign comes, v (latency + 0.2) + v^2 / (2 braking) = fade_distance / 2 (m/s)."""
        a, b, c = 1.0 / (2.0 * self.braking), self.latency + 0.2, -self.fade_distance / 2.0
        return (-b + math.sqrt(b * b - 4.0 * a * c)) / (2.0 * a)

    def leaving(self, here: tuple[float, float], target: tuple[float, float]) -> str:
        """The neighbour of a critical link, lossy or not, that going from `here` towards `target`
        takes this robot further from ("" when none, or when no neighbour's position is known)."""
        for name in self.critical():
            there = self.where.get(name)
            if there is not None and _further(here, target, there):
                return name
        return ""

    def away(self, here: tuple[float, float], target: tuple[float, float]) -> str:
        """The neighbour of a critical link that showed loss lately which going from `here` towards
        `target` would take this robot further from ("" when none: the motion may go on)."""
        names = self.critical() + ([self.cause] if self.cause and self.cause not in self.critical() else [])
        for name in names:
            rows, there = self.readings.get(name), self.where.get(name)
            if not rows or rows[-1].t - self.lossy.get(name, -math.inf) > self.loss_memory:
                continue  # no loss for `loss_memory` s: the link has room to stretch
            if there is None:
                return name  # where it is is not known: no motion can be shown to keep the link
            if _further(here, target, there):
                return name
        return ""

    def risk(self) -> str:
        """Why connectivity is at risk now ("" when it is not, or nothing was read yet)."""
        s = self.state
        if self.use_articulation and s.articulation:
            return f"{self.me} is an articulation point of the network"
        if self.use_articulation and s.bridge:
            return f"{self.me}'s weak link to {s.bridge} alone joins it to the rest of the network"
        if s.best is not None and s.best < self.min_quality:
            return f"best link quality {s.best:.2f} is below {self.min_quality:.2f}"
        return self.prediction

    def update(self, now: float, position: tuple[float, float] | None) -> str | None:
        """Re-evaluate; return "risk" or "clear" on a transition, else None."""
        s = self.state
        if position is not None and (not self.moves or self.moves[-1][0] < now):
            self.moves.append((now, position[0], position[1]))
        self.prediction = ""
        s.critical = {n: self.readings[n][-1].quality for n in self.critical() if self.readings.get(n)}
        anchors = dict(s.critical) or self._best()
        s.closing = {n: v for n in s.critical if (v := self.away_speed(n)) is not None}
        if self.predict:
            self.prediction = self._predicted(now)
        reason = self.risk()
        if reason and not reason.endswith("is an articulation point of the network"):
            self.cause = self._cause(reason)  # the link whose state held the robot: no resuming away from it
        weak = any(q < self.resume_quality for q in anchors.values())
        if reason:
            s.ok_since = None
            s.reason = reason
            if not s.at_risk:
                s.at_risk = True
                return "risk"
            return None
        return self._recovered(now, position, weak)

    def _predicted(self, now: float) -> str:
        """Why the links are predicted to fail before the robot can stand ("" when they are not): a
        critical link's, or (no bridge) every link's."""
        for name in self.state.critical:
            got = self.projected(name, now)
            if got is not None and got[0] < self.min_quality:
                q = self.readings[name][-1].quality
                return (f"the link to {name} ({q:.2f}) is predicted to fall below "
                        f"{self.min_quality:.2f} before {self.me} can stand ({got[1]})")
        if self.readings:  # no bridge: is the best link going too?
            future = {n: (rows[-1].quality if (got := self.projected(n, now)) is None else got[0])
                      for n, rows in self.readings.items() if rows}
            best = max(self.readings, key=lambda n: self.readings[n][-1].quality)
            if future and max(future.values()) < self.min_quality <= self.readings[best][-1].quality:
                return (f"every link of {self.me} is predicted to fall below {self.min_quality:.2f} "
                        f"before it can stand (the best now: {best}, "
                        f"{self.readings[best][-1].quality:.2f})")
        return ""

    def _recovered(self, now: float, position: tuple[float, float] | None, weak: bool) -> str | None:
        """No risk now: keep the good-position trail, and clear once every anchor link has been back above
        `resume_quality` (not `weak`) for `resume_after` s; "clear" then, else None."""
        s = self.state
        if position is not None and s.best is not None and not s.at_risk:
            self.last_good = position
            if not self.trail or math.dist(self.trail[-1], position) >= 0.2:
                self.trail.append(position)
        if not s.at_risk:
            return None
        if weak:  # hysteresis: every critical link back above the higher threshold first
            s.ok_since = None
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


def _further(here: tuple[float, float], target: tuple[float, float], there: tuple[float, float]) -> bool:
    """Whether going from `here` towards `target` takes a robot further from `there`: its first
    0.3 m, or its end."""
    step = math.dist(here, target)
    if step < 1e-6:
        return False
    k = min(1.0, 0.3 / step)
    ahead = (here[0] + (target[0] - here[0]) * k, here[1] + (target[1] - here[1]) * k)
    now = math.dist(here, there)
    return math.dist(ahead, there) > now + 0.02 or math.dist(target, there) > now + 0.1


def _bridges(me: str, edges: Sequence[tuple[str, str]]) -> set[str]:
    """The neighbours of `me` over links whose loss would separate `me` from that neighbour."""
    adj: dict[str, set[str]] = {}
    for a, b in edges:
        if a != b:
            adj.setdefault(a, set()).add(b)
            adj.setdefault(b, set()).add(a)
    out = set()
    for n in adj.get(me, ()):
        seen, todo = {me}, [me]  # who `me` reaches without its link to n
        while todo:
            x = todo.pop()
            for m in adj[x]:
                if (x == me and m == n) or m in seen:
                    continue
                seen.add(m)
                todo.append(m)
        if n not in seen:
            out.add(n)
    return out


def _mean_t(rows: Sequence[Reading]) -> float:
    return sum(r.t for r in rows) / len(rows)


def _slope(points: Sequence[tuple[float, float]]) -> float:
    """Least-squares slope of y on x."""
    mx = sum(x for x, _ in points) / len(points)
    my = sum(y for _, y in points) / len(points)
    sxx = sum((x - mx) ** 2 for x, _ in points)
    return 0.0 if sxx <= 0 else sum((x - mx) * (y - my) for x, y in points) / sxx
