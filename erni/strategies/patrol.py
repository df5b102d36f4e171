"""Territory patrol with failure takeover (paper 002, sections II.C and II.D).

Each robot patrols its own rectangular block (xmin, ymin, xmax, ymax), in m, along a fixed
sweep path, and sends a heartbeat every period carrying its name, its block and the blocks
it has taken over. When a neighbour (a robot whose block touches one of ours) has been silent
for `silence` seconds, every neighbour starts a back-off timer; the first whose timer expires
claims the silent robot's block and says so in its next heartbeat; the others give up on
hearing the claim. Every neighbour ranks the candidates the same way (touching blocks,
nearest first, then by name) and waits base * (1 + rank), so with `base` above one heartbeat
period plus the delivery latency exactly one claim happens; claims that still cross (lost
heartbeats) are settled by the earlier (claim time, name), and the loser yields. A silent
robot heard again gets its block back.

Pure parts (no blackboard, no clock of their own; times in s are passed in):
- `split(territory, nx, ny)` -> list of blocks; `sweep_path(block, spacing, margin)` ->
  (K, 2) waypoints; `touching(a, b)` -> bool; `claim_order(failed, candidates)` -> names;
  `backoff(rank, base)` -> s.
- `TakeoverTable`: the decision state of one robot; feed it heartbeats with `heard(...)`, ask
  it what to do with `tick(now)`; its `holds` are the robots whose blocks it patrols.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import TypedDict

import numpy as np
from numpy.typing import NDArray

from erni.blackboard.errors import UsageError

Block = tuple[float, float, float, float]


def check_block(block: Block) -> Block:
    """Return the block as floats, or raise ValueError if it is not xmin < xmax, ymin < ymax."""
    xmin, ymin, xmax, ymax = (float(v) for v in block)
    if not (xmin < xmax and ymin < ymax):
        raise UsageError(f"block: expected xmin < xmax and ymin < ymax, got {block!r}")
    return (xmin, ymin, xmax, ymax)


def split(territory: Block, nx: int, ny: int) -> list[Block]:
    """Cut a territory into nx * ny equal blocks, row by row from (xmin, ymin)."""
    xmin, ymin, xmax, ymax = check_block(territory)
    if nx < 1 or ny < 1:
        raise UsageError(f"split: expected nx, ny >= 1, got {nx}, {ny}")
    w, h = (xmax - xmin) / nx, (ymax - ymin) / ny
    return [(xmin + i * w, ymin + j * h, xmin + (i + 1) * w, ymin + (j + 1) * h)
            for j in range(ny) for i in range(nx)]


def centre(block: Block) -> NDArray[np.float64]:
    """The centre (2,) of a block."""
    xmin, ymin, xmax, ymax = block
    return np.array([(xmin + xmax) / 2, (ymin + ymax) / 2])


def touching(a: Block, b: Block, slack: float = 1e-6) -> bool:
    """True when two blocks share an edge or a corner (or overlap)."""
    return (a[0] <= b[2] + slack and b[0] <= a[2] + slack and a[1] <= b[3] + slack and b[1] <= a[3] + slack)


def sweep_path(block: Block, spacing: float = 1.0, margin: float = 0.3) -> NDArray[np.float64]:
    """Return lawnmower waypoints (K, 2) covering the block, lanes `spacing` m apart, `margin` m inside."""
    xmin, ymin, xmax, ymax = check_block(block)
    if not spacing > 0:
        raise UsageError(f"spacing: expected a positive lane spacing (m), got {spacing!r}")
    x0, x1 = xmin + margin, xmax - margin
    y0, y1 = ymin + margin, ymax - margin
    if x0 > x1:
        x0 = x1 = (xmin + xmax) / 2
    if y0 > y1:
        y0 = y1 = (ymin + ymax) / 2
    lanes = max(1, math.floor((y1 - y0) / spacing) + 1)
    ys = np.linspace(y0, y1, lanes) if lanes > 1 else np.array([(y0 + y1) / 2])
    pts: list[tuple[float, float]] = []
    for k, y in enumerate(ys):
        xs = (x0, x1) if k % 2 == 0 else (x1, x0)
        pts.extend([(xs[0], float(y)), (xs[1], float(y))])
    return np.array(pts, dtype=float)


def claim_order(failed: Block, candidates: dict[str, Block]) -> list[str]:
    """Rank the robots that may take over block `failed`: touching blocks only, nearest first, then by name."""
    near = [(float(np.hypot(*(centre(b) - centre(failed)))), n) for n, b in candidates.items() if touching(b, failed)]
    return [n for _, n in sorted(near)]


def backoff(rank: int, base: float = 1.0) -> float:
    """Back-off (s) of the claimant ranked `rank` (0 = first): base * (1 + rank).

    Claims happen once when `base` exceeds one heartbeat period plus the delivery latency:
    the next claimant then hears the first claim before its own back-off expires.
    """
    if rank < 0 or not base > 0:
        raise UsageError(f"backoff: expected rank >= 0 and base > 0, got {rank}, {base}")
    return base * (1 + rank)


class Heartbeat(TypedDict):
    """What a robot's heartbeat says (`TakeoverTable.heartbeat()`)."""

    robot: str
    block: list[float]          # xmin, ymin, xmax, ymax (m)
    holds: list[str]            # the robots whose blocks it patrols (itself included)
    claims: dict[str, float]    # silent robot -> claim time (s)


@dataclass
class PeerState:
    """What a robot knows about another patrolling robot."""

    block: Block
    last_heard: float
    holds: tuple[str, ...] = ()
    claims: dict[str, float] = field(default_factory=dict)


@dataclass(frozen=True)
class Event:
    """A decision of the table: `silent`, `claim`, `yield` or `return` (about robot `about`)."""

    kind: str
    about: str


class TakeoverTable:
    """One robot's view of its patrolling neighbours and its takeover decisions."""

    def __init__(self, me: str, block: Block, *, silence: float = 5.0, base: float = 1.0) -> None:
        self.me = me
        self.block = check_block(block)
        self.silence = silence
        self.base = base
        self.peers: dict[str, PeerState] = {}
        self.holds: dict[str, Block] = {me: self.block}   # robot -> block patrolled by me
        self.claims: dict[str, float] = {}                 # silent robot -> my claim time
        self.pending: dict[str, float] = {}                # silent robot -> when I would claim
        self.silent: set[str] = set()

    def neighbour(self, name: str) -> bool:
        """True when robot `name`'s block touches one of the blocks I patrol."""
        peer = self.peers.get(name)
        return peer is not None and any(touching(b, peer.block) for b in self.holds.values())

    def heard(self, name: str, block: Block, now: float, holds: tuple[str, ...] = (),
              claims: dict[str, float] | None = None) -> list[Event]:
        """Take in a heartbeat of robot `name`; return the events it causes (yield, return)."""
        if name == self.me:
            return []
        events: list[Event] = []
        claims = dict(claims or {})
        self.peers[name] = PeerState(check_block(block), now, tuple(holds), claims)
        if name in self.silent:
            self.silent.discard(name)
            self.pending.pop(name, None)
            if name in self.holds and name != self.me:
                del self.holds[name]
                self.claims.pop(name, None)
                events.append(Event("return", name))
        for failed, stamp in claims.items():
            if failed == self.me:
                continue
            if failed in self.pending:
                del self.pending[failed]
                events.append(Event("yield", failed))
            mine = self.claims.get(failed)
            if mine is not None and (stamp, name) < (mine, self.me):
                del self.claims[failed]
                self.holds.pop(failed, None)
                events.append(Event("yield", failed))
        return events

    def tick(self, now: float) -> list[Event]:
        """Detect silent neighbours, start their back-offs, and claim when a back-off expires."""
        events: list[Event] = []
        for name, peer in self.peers.items():
            if name in self.silent or now - peer.last_heard <= self.silence:
                continue
            self.silent.add(name)
            events.append(Event("silent", name))
            taken = any(name in p.claims for n, p in self.peers.items() if n != name and n not in self.silent)
            if self.neighbour(name) and not taken:
                alive = {n: p.block for n, p in self.peers.items() if n != name and n not in self.silent}
                alive[self.me] = self.block
                order = claim_order(peer.block, alive)
                if self.me in order:
                    self.pending[name] = now + backoff(order.index(self.me), self.base)
        for name, when in list(self.pending.items()):
            if now >= when:
                del self.pending[name]
                self.claims[name] = now
                self.holds[name] = self.peers[name].block
                events.append(Event("claim", name))
        return events

    def heartbeat(self) -> Heartbeat:
        """What my heartbeat says: my block, the robots whose blocks I hold, my claims."""
        return {"robot": self.me, "block": list(self.block), "holds": sorted(self.holds),
                "claims": dict(self.claims)}
