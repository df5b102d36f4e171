"""Creeping out of radio range: does the network guard stop a robot before its only link breaks?

The test bed is scenario `creep` (a star: the control node in the middle, spokes of a relay
5.5 m out and an end robot 6 m beyond it). In one round every end robot gets a remote goto
straight away from its relay, each at its own speed, through the lossy band towards the range
limit; the round watches the simulator's truth at 20 Hz until every end robot has stood for
`observe` seconds (a guard that resumes on a momentary better reading shows here), has reached
its goal, or has left the radio range of its relay. Then the tasks are cancelled and the robots
put back for the next round.

Per trial (one end robot in one round):

- `partitioned`: the end robot was, at some sample, beyond the radio range of its relay (its
  only link: the team split);
- `closest`: the closest approach to the range limit, `comm_range` minus the largest distance
  from the relay (m; negative when it crossed);
- `stop_after_crossing`: from the moment the robot crossed the distance where the radio's
  delivery ratio falls to the guard's `min_link_quality` to the moment it stood (s; negative
  when it stood before crossing; None when it never stood);
- `crept_on`: how far it moved away from the relay after it first stood (m), which is what a
  release on a flicker costs;
- `top_speed`: the fastest it drove (m/s): the mission drives a robot away from its only link
  no faster than the guard's `safe_speed` (0.61 m/s at the defaults), whatever speed was asked.

The radio's range and its quality-against-distance line are inputs (the scenario's), not
findings; the guard never sees them, only what MobiNet reads (SNMP on the loopback tier,
babeld on the real-mesh tier).
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any

from erni.blackboard.errors import ErniError
from erni.sim.manet import RadioModel
from erni.sim.team import Team

SPEEDS = (0.1, 0.3, 0.5, 1.0)
STILL = 0.02           # m/s: a robot slower than this stands
SAMPLE = 0.05          # s between samples of the truth


@dataclass
class Spoke:
    """One relay and the end robot that drives away from it."""

    relay: str
    end: str
    home: tuple[float, float]     # the end robot's start
    heading: float                # deg: straight away from the relay
    speed: float = 0.0


@dataclass
class Trial:
    """One end robot creeping away in one round."""

    round: int
    robot: str
    speed: float
    partitioned: bool
    closest: float
    stop_after_crossing: float | None
    crept_on: float
    held: str = ""                # the last message of its task that said why it held
    resumed: int = 0              # how often its task said it resumed
    top_speed: float = 0.0        # the fastest it drove (m/s): the guard slows a robot leaving its only link
    track: list[tuple[float, float]] = field(default_factory=list)  # (t, distance from the relay)

    def row(self) -> dict[str, Any]:
        return {"round": self.round, "robot": self.robot, "speed": self.speed, "partitioned": self.partitioned,
                "closest_m": round(self.closest, 3),
                "stop_after_crossing_s": None if self.stop_after_crossing is None else round(self.stop_after_crossing, 2),
                "crept_on_m": round(self.crept_on, 3), "held": self.held, "resumed": self.resumed,
                "top_speed": round(self.top_speed, 3)}


def spokes(team: Team) -> list[Spoke]:
    """The spokes of the creep scenario: robots in pairs (relay, end), in order."""
    names = team.names
    if len(names) % 2:
        raise CreepError(f"scenario {team.scenario.name}: expected robots in pairs (relay, end), got {len(names)}")
    out = []
    for relay, end in zip(names[0::2], names[1::2]):
        r, e = team.robot(relay), team.robot(end)
        heading = math.degrees(math.atan2(e.start[1] - r.start[1], e.start[0] - r.start[0]))
        out.append(Spoke(relay, end, (e.start[0], e.start[1]), heading))
    return out


def threshold_distance(team: Team, min_quality: float) -> float:
    """The distance at which the scenario's radio delivers `min_quality` (an input of the bed)."""
    r = team.scenario.radio
    return RadioModel(r.comm_range, r.lossless_range, r.min_quality).range_for(min_quality)


def run_round(team: Team, number: int, speeds: Sequence[float], *, min_quality: float = 0.3,
              observe: float = 12.0, goal: float = 8.0, limit: float = 120.0,
              messages: Callable[[str], list[str]] | None = None) -> list[Trial]:
    """One round: every spoke's end robot drives away at its speed (`speeds`, one per spoke,
    None-free); return one Trial per spoke. `goal` is how far beyond the range limit the goto
    points; `messages(uid)` (optional) gives the task's result messages so far."""
    comm = team.scenario.radio.comm_range
    cross = threshold_distance(team, min_quality)
    sp = spokes(team)[:len(speeds)]
    uids = []
    for s, v in zip(sp, speeds):
        s.speed = v
        r = team.robot(s.relay)
        a = math.radians(s.heading)
        gx, gy = r.x + (comm + goal) * math.cos(a), r.y + (comm + goal) * math.sin(a)
        uids.append(team.send_task(s.end, "RemoteBotMotion", "goto", x=round(gx, 2), y=round(gy, 2),
                                   speed=v, tolerance=0.3).uid)
    t0 = time.monotonic()
    watches = [_Watch() for _ in sp]
    while True:
        now = time.monotonic() - t0
        for w, s in zip(watches, sp):
            e, r = team.robot(s.end), team.robot(s.relay)
            w.sample(now, math.dist((e.x, e.y), (r.x, r.y)), abs(e.v), cross, comm)
        settled = all(w.gone or (w.stood is not None and now - w.stood >= observe) for w in watches)
        if settled or now > limit:
            break
        time.sleep(SAMPLE)
    trials = []
    for uid, w, s in zip(uids, watches, sp):
        trials.append(w.trial(number, s, cross, comm, messages(uid) if messages is not None else []))
    for uid, s in zip(uids, sp):
        team.send_task(s.end, "RemoteBotMotion", "cancel", task=uid)
    return trials


@dataclass
class _Watch:
    """One end robot watched through a round: its track (t, distance from its relay, speed), when it
    last began to stand, when it first stood (for half a second), when it crossed the link-quality
    threshold and whether it left its relay's range."""

    track: list[tuple[float, float, float]] = field(default_factory=list)
    stood: float | None = None
    first_stand: float | None = None
    crossed: float | None = None
    gone: bool = False

    def sample(self, now: float, d: float, v: float, cross: float, comm: float) -> None:
        """Take the sample at `now`: `d` m from the relay, driving at `v` m/s."""
        self.track.append((now, d, v))
        if self.crossed is None and d >= cross:
            self.crossed = now
        if d >= comm:
            self.gone = True
        moved = d > self.track[0][1] + 0.1
        if v < STILL and moved:
            since = self.stood
            if since is None:
                since = self.stood = now
            if self.first_stand is None and now - since >= 0.5:
                self.first_stand = since
        else:
            self.stood = None

    def trial(self, number: int, s: Spoke, cross: float, comm: float, said: list[str]) -> Trial:
        """The round's Trial of this robot, `said` its task's result messages."""
        track = self.track
        far = max(d for _, d, _ in track)
        stand = self.first_stand
        after = None
        if stand is not None:
            c = self.crossed if self.crossed is not None else next((t for t, d, _ in track if d >= cross), None)
            # stood before crossing: how long before the robot would have crossed at its speed
            after = stand - c if c is not None else -((cross - _at(track, stand)) / max(s.speed, 1e-9))
        at_stand = _at(track, stand) if stand is not None else far
        held = next((m for m in reversed(said) if m.startswith("holding")), "")
        return Trial(number, s.end, s.speed, self.gone, comm - far, after, max(0.0, far - at_stand), held,
                     sum(m.startswith("resumed") for m in said), max(v for _, _, v in track),
                     [(round(t, 2), round(d, 3)) for t, d, _ in track[::4]])


def _at(track: list[tuple[float, float, float]], t: float | None) -> float:
    """The distance at time `t` of a track (its last sample before)."""
    d = track[0][1]
    for ts, dist, _ in track:
        if t is not None and ts > t:
            break
        d = dist
    return d


def peers_up(team: Team) -> bool:
    """Whether the control node lists every robot of the team as up."""
    peers = team.peers(1.0)
    return set(team.names) <= set(peers) and all(peers[name].up for name in team.names)


def reset(team: Team, settle: Callable[[], bool], *, rest: float = 3.0, timeout: float = 60.0) -> None:
    """Put every end robot back at its start, let the network readings recover for `rest` s (a
    routing daemon remembers the lost Hellos of the last round), and wait until `settle()` says
    the team is whole."""
    sp = spokes(team)
    for s in sp:
        team.teleport(s.end, s.home[0], s.home[1], s.heading)
    deadline = time.monotonic() + timeout
    while any(math.dist((team.robot(s.end).x, team.robot(s.end).y), s.home) > 0.05 for s in sp):
        if time.monotonic() > deadline:
            raise CreepError(f"creep: the end robots were not back at their starts within {timeout:g} s")
        time.sleep(0.1)
    time.sleep(rest)
    while time.monotonic() < deadline:
        if team.status.components == 1 and settle():
            return
        time.sleep(0.2)
    raise CreepError(f"creep: the team was not whole again within {timeout:g} s of the reset")


class CreepError(ErniError):
    """The creep test bed could not be set up for a round."""
