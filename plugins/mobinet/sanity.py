"""Plausibility limits on what a network source reports: a row outside them is dropped, not believed.

An agent may answer anything its types allow: a position of -2147483.648 m, a heading of
-21474836.48 deg, a route of 4294967295 hops. Such a row says nothing true about the network.
A source drops it and records an `Absurd` in `NetView.dropped`; the NetInfo of that part is
then degraded (its good rows kept), and MobiNetResource warns at most once a minute per agent
and column, naming the agent, the OID and the value.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

WORLD_BOUND = 10_000.0     # m: no robot of a team is farther from the origin than this
MAX_HOPS = 64              # no route of a robot mesh is longer
TURN = 360.0               # deg: a heading reads within one turn either way


@dataclass(frozen=True)
class Absurd:
    """One dropped row: `agent` (e.g. "snmp 127.0.0.1:1162"), the NetView `part` it belonged to
    (a PARTS name, or "names"), its `column` (e.g. "erniPositionX") and what was wrong, with the
    OID or line and the value (`message`)."""

    agent: str
    part: str
    column: str
    message: str

    def __str__(self) -> str:
        return f"{self.agent}: dropped {self.message}"


@dataclass(frozen=True)
class Limits:
    """The physical ranges a reading must fall in; each check returns why a value is not plausible
    (the caller names the value), or None when it is."""

    world_bound: float = WORLD_BOUND
    max_hops: int = MAX_HOPS

    def coordinate(self, metres: float) -> str | None:
        """A position coordinate (m) within ±world_bound."""
        if not math.isfinite(metres) or abs(metres) > self.world_bound:
            return f"beyond the world bound of ±{self.world_bound:g} m (MobiNet setting world_bound)"
        return None

    @staticmethod
    def heading(degrees: float) -> str | None:
        """A heading (deg) within one turn either way."""
        if not math.isfinite(degrees) or abs(degrees) > TURN:
            return f"outside one turn (-{TURN:g}..{TURN:g} deg)"
        return None

    @staticmethod
    def quality(ratio: float) -> str | None:
        """A link quality (delivery ratio) in 0..1."""
        if not 0.0 <= ratio <= 1.0:
            return "a link quality outside 0..1"
        return None

    def hops(self, hops: int) -> str | None:
        """The hop count of a route to another node: 1..max_hops."""
        if hops <= 0:
            return "a route to another node has at least 1 hop"
        if hops > self.max_hops:
            return f"more hops than the {self.max_hops} allowed (MobiNet setting max_hops)"
        return None
