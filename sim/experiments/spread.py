"""Paper 001: potential-field self-deployment, open field and corridor, run until the team settles.

Kinematic mode (the default for the paper's 120 robots): the mission's `potential.spread_step`
(equations 15 and 16) moves every robot each dt = 0.2 s, for each variant the paper shows
(holonomic or nonholonomic robots, physical or Delaunay neighbourhood; and the Gabriel graph,
the other topological neighbourhood paper 001 names in 3.2), until every robot has
been slower than `still_speed` for `hold` seconds (converged) or `duration` runs out. Walls are
solid (a move through one is refused) and repel as paper 001's boundary term does: one object
at the wall's nearest point with desired distance c, felt within the sensing range `sensing`
(paper 001, 3.3), weighted (w_ij) by `obstacle_weight` (a number, or "neighbourhood": as many
robots as are in the neighbourhood). With `range_sweep`, the physical variants run again at
each of those neighbourhood ranges R, for the settled spacing against R / d.

Why a run does or does not converge (measured on the 120-robot scenarios; the residual of
every run is in its metrics: neighbourhood links made or broken per second, the largest move
and the largest unbalanced force at the end). No zero-energy mode creeps: the centroid moves
less than 2 m in 600 s and a converged team's fastest robot slows exponentially (1e-9 m/s
by 600 s). What keeps a team moving is the discontinuity of the neighbourhood itself: an
edge of the Delaunay triangulation switches a spring on or off at its current length L
(energy w (L - d)^2 / 2), and in the corridor the near-straight rows along the walls flip
24-37 edges a second, 30 % of them longer than 7.5 m (up to 34 m, the long boundary links the
paper itself notes): between 300 and 400 s the flips put in 14 500 J, the heading term's
force 2 100 J, the damping took out 18 000 J. dt = 0.05 s or chi = 0 change nothing, so this
is the Delaunay field's nature, not the integration. The Gabriel graph keeps only the Delaunay
edges whose closed diametral disc holds no other robot, which drops the long boundary links:
in the open field both Gabriel variants converge (holonomic at 69 s, nonholonomic at 279 s,
where the nonholonomic Delaunay team did not by 600 s), in the corridor the holonomic one does
(124 s) and the nonholonomic one does not. Nonholonomic Gabriel teams do not stay still, for a
reason of the model, not of the heading term or the walls: with the neighbourhoods frozen at
300 s both nonholonomic corridor teams settle (Gabriel by 348 s, Delaunay by 342 s), and
dt = 0.1 or 0.05 s leaves the Gabriel team moving (0.63 and 0.48 m in the last 10 s).
Equation (16) lets a robot rest under a force across its wheels (the corridor team at 600 s:
25 robots held by more than 1 N, up to 4.0 N, and 144 of its 310 links shorter than 0.8 d;
the holonomic team: no force left, 19 of 319 links), and a link shorter than d whose diametral
circle passes through a third robot switches itself off (its push lengthens it and the circle
grows over that robot) and, without its push, back on: over the last 300 s 2.2 link changes a
second on 164 links, 75 % of them shorter than d, the third robot at 90 degrees (median). The
wall plays no part in that (20 % of the changes have a robot within its 2.5 m sensing range,
where 21 % of the robots are; 12 crossings of that range in 300 s; for Delaunay 51 % against
12 %). Over seeds 1-5 one nonholonomic Gabriel corridor team settles (seed 4, 542 s), none in
the open field for good (seed 1's, still at 279 s, moves again from 467 s); some only jitter in
place (seed 3, corridor: two links switching every one or two control periods keep two robots
at 0.1 m/s, 4 mm net in 10 s; reported as settled in place, every robot within 0.1 m, from 458 s).
A physical neighbourhood switches a
neighbour on at R with a force w (R - d): a robot held at that edge jumps by it each control
period. Walls sensed at the 6 m neighbourhood range (ours until the sensing range was used)
pulled every robot within 6 m toward them: half of the corridor team stood in rows within
3.6 m of a wall, and in the crowd there a nonholonomic robot on a neighbour's range edge
kept jumping at 0.1-0.24 m/s in place, so that run never settled. Why teams settle short of d:
every robot within R pulls or pushes toward d, so with R > d the neighbours between d and R
pull the team in; the mean nearest-neighbour distance against R / d (open field, holonomic /
nonholonomic): 1.0: 5.12 / 5.08 m, 1.1: 4.80 / 4.41, 1.2: 4.35 / 3.02, 1.3: 2.18 / 1.92,
1.5: 0.76 / 0.64 (from R = 1.5 d the start bunch never leaves everyone's range). A settled
nonholonomic robot may still feel a force, across its heading: equation (16) turns it only
toward its neighbourhood's centre, and its wheels take the rest (3.3 N in the open field).

Agents mode (the default for teams of at most 12, such as `spread-paths`): `agent_robots`
robot agent processes, started on a small grid, each given `Deploy spread` by the control node;
each robot's mission plugin turns equation (15)/(16) into BotMotion velocity commands from
the positions its agent learns through MobiNet; the simulator records the truth. The command
is the velocity the equation settles to, F / k, so a Delaunay flip changes it at once: the
nonholonomic Delaunay team keeps driving at the speed limit (stepped in numpy with the same
command, with or without the heading term alike).

Metrics per variant: time to converge; for a team that does not, when it settled in place
(every robot within `still_radius` m of where it was for `hold` s: a team kept above the still
speed only by links switching on and off each control period); final mean and smallest nearest-neighbour distance
against the desired d (an input), the same at t = 30 s (the paper's figures), robots ending
within `pinned` m of a wall, share of robots in the largest radio component, energy per robot
(paper 000's model on each track). `spread-paths` draws each robot's path with arrows for
its heading (paper 001, Figs 6 and 7).
"""

from __future__ import annotations

import math
import random
from collections import deque
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from erni.sim import kinematic
from erni.sim.experiments import Experiment, Progress, Result
from erni.sim.experiments.plots import color, draw_world, headings, map_axes, time_axes
from erni.sim.scenario import Scenario, ScenarioError
from erni.strategies import energy as energy_model
from erni.strategies.potential import (
    SpreadConfig,
    SpreadMemory,
    forces,
    mean_nn_distance,
    neighbourhoods,
    spread_step,
    team_neighbourhoods,
)

VARIANTS = ["holonomic/physical", "holonomic/delaunay", "nonholonomic/physical", "nonholonomic/delaunay"]
EXTRA_VARIANTS = ["holonomic/gabriel", "nonholonomic/gabriel"]  # paper 001's other topological graph (3.2)


CHANGES_WINDOW = 100.0  # s: the link changes at the end of a run are told apart over this long


@dataclass
class Change:
    """One link made (`on`) or broken at time `t` between robots i < j, `length` m apart then, and
    what kind of change it was (the kinds overlap; `_change_kinds`)."""

    t: float
    on: bool
    i: int
    j: int
    length: float
    flip: bool      # one of the two diagonals of a quadrilateral of the triangulation swapped in one step
    edge: bool      # on the team's edge: a side of only one triangle of the triangulation, or a link it
                    # lacks between two robots on a side of one triangle (or in none)
    reach: bool     # at the radio reach: longer than 0.9 of it (a link in effect leaves past 1.1 of it)
    wall: bool      # a robot of it within the wall sensing range of a wall
    short: bool     # shorter than 1.05 d (a link in effect shorter than d stays until its push ends at d)


@dataclass
class Run:
    """One variant's run: the track (every `sample` s) and when it converged."""

    variant: str
    t: NDArray[np.float64]      # (T,) s
    pos: NDArray[np.float64]    # (T, N, 2) m
    th: NDArray[np.float64]     # (T, N) rad
    speed: NDArray[np.float64]  # (T, N) m/s
    converged: float            # s (NaN: not within the run)
    churn: float = math.nan     # neighbourhood links made or broken per s over the last `hold` s
    force: float = math.nan     # largest unbalanced force on a robot at the end (N, m = 1 kg)
    across: float = math.nan    # ... its part across the robot's heading (nonholonomic: held by the wheels)
    # energy balance, cumulative at each sample of `t` (J, m = 1 kg): the springs' energy at the
    # instant a neighbourhood change switched them on, and off; what the damping took out
    switched_on: NDArray[np.float64] | None = None
    switched_off: NDArray[np.float64] | None = None
    damped: NDArray[np.float64] | None = None
    # every link made or broken over the last `CHANGES_WINDOW` s of the run (see `_change_kinds`)
    changes: list[Change] | None = None


def robot_limits(scenario: Scenario) -> tuple[float, float]:
    """The top speed (m/s) and turn rate (rad/s) of the scenario's robot model, as the simulator builds it.

    Agents mode drives `SimRobot`s of this model (`Team` builds them the same way), which never
    exceed these; the kinematic mode holds every robot to them too.
    """
    from erni.sim.robot import SimRobotConfig

    cfg = SimRobotConfig.amigobot() if scenario.robots.model == "amigobot" else SimRobotConfig()
    return cfg.max_v, math.radians(cfg.max_rv)


SETTLE = "+settle"  # a variant's suffix: the paper's law with the settling changes of `strategy.settle`


def _settle(scenario: Scenario) -> dict[str, Any]:
    """The settling changes (`strategy.settle`): springs that engage at their length, a Delaunay
    triangulation kept with a flip margin (hysteresis on flips), no topological link longer than the
    radio range, optionally a hysteresis in time on every neighbour change."""
    got = dict(scenario.strategy.get("settle", {}))
    unknown = set(got) - {"engage", "relax", "stick", "reach", "flip_margin"}
    if unknown:
        raise ScenarioError(f"strategy.settle: unknown keys {', '.join(sorted(unknown))}; "
                            "expected engage, relax, stick, reach, flip_margin")
    out = {"engage": "rest", "relax": 5.0, "flip_margin": 10.0, "stick": 0.0, "reach": scenario.radio.comm_range,
           **got}
    if not out["reach"]:  # 0: no reach limit
        out["reach"] = None
    return out


def _config(scenario: Scenario, variant: str) -> SpreadConfig:
    s = dict(scenario.strategy)
    if variant.endswith(SETTLE):
        variant = variant[:-len(SETTLE)]
        s.update(_settle(scenario))
    model, _, neighbourhood = variant.partition("/")
    vmax, wmax = robot_limits(scenario)
    weight = s.get("obstacle_weight", "neighbourhood")
    sensing = s.get("sensing")
    return SpreadConfig(distance=float(s.get("distance", 5.0)), gain=float(s.get("gain", 2.0)),
                        dt=float(s.get("dt", 0.2)), range=float(s.get("range", 6.0)),
                        sensing=None if sensing is None else float(sensing),
                        obstacle_distance=float(s.get("obstacle_distance", 2.0)),
                        wall_distance=float(s.get("wall_distance", 2.5)),
                        obstacle_weight=None if weight == "neighbourhood" else float(weight),
                        neighbourhood=neighbourhood, model=model, vmax=vmax, wmax=wmax,
                        engage=str(s.get("engage", "instant")), relax=float(s.get("relax", 5.0)),
                        stick=float(s.get("stick", 0.0)),
                        reach=None if s.get("reach") is None else float(s["reach"]),
                        flip_margin=float(s.get("flip_margin", 0.0)))


def _obstacles(scenario: Scenario) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    walls = np.array([[a[0], a[1], b[0], b[1]] for a, b in scenario.world.segments()], dtype=float).reshape(-1, 4)
    circles = np.array([[c.center[0], c.center[1], c.radius] for c in scenario.world.circle],
                       dtype=float).reshape(-1, 3)
    return circles, walls


def run(scenario: Scenario, progress: Progress, *, experiment: Experiment, mode: str,
        variants: list[str] | None = None, seeds: int | None = None, **_: Any) -> Result:
    """Run every variant until it converges; return figure and metrics. `seeds` (else the
    scenario's `strategy.seeds`, else 1) repeats each variant from `scenario.seed` on."""
    variants = variants or list(scenario.strategy.get("variants", VARIANTS))
    for v in variants:
        if v.removesuffix(SETTLE) not in VARIANTS + EXTRA_VARIANTS:
            raise ScenarioError(f"strategy.variants: unknown variant {v!r}; expected some of "
                                f"{', '.join(VARIANTS + EXTRA_VARIANTS)}, each also with {SETTLE} (kinematic mode)")
    if mode == "agents":  # the settling changes live in the kinematic stepping only
        variants = [v for v in variants if not v.endswith(SETTLE)]
    if seeds is None:
        seeds = int(scenario.strategy.get("seeds", 1))
    if seeds < 1:
        raise ScenarioError(f"seeds: expected at least 1, got {seeds}")
    base = scenario
    over_seeds: list[list[Run]] = []
    for n in range(seeds):
        scenario = base.model_copy(update={"seed": base.seed + n})
        if mode == "agents":
            scenario = _agent_team(scenario)
        runs = []
        for k, v in enumerate(variants):
            label = f"{v} ({k + 1}/{len(variants)})" + (f", seed {scenario.seed} ({n + 1}/{seeds})" if seeds > 1 else "")
            runs.append(_agents(scenario, progress, v, label) if mode == "agents" else
                        _kinematic(scenario, progress, v, label))
        over_seeds.append(runs)
    scenario, runs = (_agent_team(base) if mode == "agents" else base), over_seeds[0]
    sweep = _range_sweep(scenario, progress) if mode == "kinematic" else []
    return _result(scenario, experiment, mode, runs, sweep, over_seeds if seeds > 1 else None)


def _range_sweep(scenario: Scenario, progress: Progress) -> list[tuple[float, Run]]:
    """The physical variants run again at each neighbourhood range R of `strategy.range_sweep`."""
    sweep: list[tuple[float, Run]] = []
    ranges = [float(r) for r in scenario.strategy.get("range_sweep", [])]
    for k, (r, v) in enumerate((r, v) for r in ranges for v in ("holonomic/physical", "nonholonomic/physical")):
        data = scenario.model_dump()
        data["strategy"] = {**scenario.strategy, "range": r}
        sweep.append((r, _kinematic(type(scenario).model_validate(data), progress, v,
                                    f"{v}, range {r:g} m ({k + 1}/{2 * len(ranges)})")))
    return sweep


def _agent_team(scenario: Scenario) -> Scenario:
    """The team agents mode runs: `agent_robots` robots on a jittered grid `agent_spacing` m apart."""
    s = scenario.strategy
    n = min(scenario.count, int(s.get("agent_robots", 12)))
    spacing = float(s.get("agent_spacing", 1.2))
    rng = random.Random(scenario.seed)
    cols = max(1, math.ceil(math.sqrt(n)))
    rows = math.ceil(n / cols)
    robots = []
    for i in range(n):
        x = (i % cols - (cols - 1) / 2) * spacing + rng.uniform(-0.15, 0.15)
        y = (i // cols - (rows - 1) / 2) * spacing + rng.uniform(-0.15, 0.15)
        robots.append({"name": f"robot{i + 1}", "x": round(x, 3), "y": round(y, 3),
                       "heading": round(rng.uniform(-180.0, 180.0), 1)})
    data = scenario.model_dump()
    data["robot"] = robots
    data["robots"]["count"] = n
    return type(scenario).model_validate(data)


def _still(t: NDArray[np.float64], speed: NDArray[np.float64], threshold: float, hold: float) -> float:
    """Start of the first stretch of `hold` s in which every robot stayed slower than `threshold`."""
    fast: list[bool] = np.any(np.abs(speed) >= threshold, axis=1).tolist()
    start: float | None = None
    for k in range(len(t)):
        if fast[k]:
            start = None
        elif start is None:
            start = float(t[k])
        if start is not None and t[k] - start >= hold:
            return start
    return math.nan


def _kinematic(scenario: Scenario, progress: Progress, variant: str, label: str) -> Run:
    s = scenario.strategy
    cfg = _config(scenario, variant)
    duration = scenario.duration or 600.0
    threshold = float(s.get("still_speed", 0.05))
    hold = float(s.get("hold", 10.0))
    sample = float(s.get("sample", 1.0))
    circles, walls = _obstacles(scenario)
    starts = scenario.starts()
    pos = np.array([[st.x, st.y] for st in starts])
    th = np.radians([st.heading for st in starts])
    vel, om = np.zeros_like(pos), np.zeros(len(pos))
    track = kinematic.Track()
    track.add(0.0, pos, th, np.zeros(len(pos)))
    every = max(1, int(round(sample / cfg.dt)))
    steps = int(round(duration / cfg.dt))
    still_since: float | None = None
    converged = math.nan
    links: list[tuple[float, set[tuple[int, int]]]] = []  # (t, neighbourhood links) every sample
    memory = SpreadMemory()  # rest lengths and hysteresis, when the variant has them
    freeze = float(s.get("freeze_links_at", math.inf))  # a probe: from then on the neighbourhoods stay as they are
    frozen: list[NDArray[np.intp]] | None = None
    on = off = damped = 0.0
    energy = [(0.0, 0.0, 0.0)]
    log = _ChangeLog(cfg.distance, cfg.reach if cfg.reach is not None else scenario.radio.comm_range, walls,
                     cfg.sensing if cfg.sensing is not None else cfg.range)
    for k in range(steps):
        if frozen is None:
            nb = team_neighbourhoods(pos, cfg, memory)
            if k * cfg.dt >= freeze:
                frozen = nb
        else:
            nb = frozen
        new, th, vel, om = spread_step(pos, th, vel, om, cfg, circles, walls, memory, nb)
        now = set(memory.effective)  # the links in effect this step (leaving ones too)
        log.update(k * cfg.dt, now, pos, memory.triangles)
        on, off = memory.switched_on, memory.switched_off  # a spring holds w (L - rest)^2 / 2 when switched
        stop = kinematic.blocked_by_walls(pos, new, walls)  # walls are solid: a robot stops at them
        pos = np.where(stop[:, None], pos, new)
        vel[stop] = 0.0
        t = (k + 1) * cfg.dt
        sp = np.hypot(vel[:, 0], vel[:, 1])
        damped += cfg.gain * float((sp * sp).sum() + (om * om).sum()) * cfg.dt  # Rayleigh: 2F = k v^2 (+ k w^2)
        if (k + 1) % every == 0:
            track.add(t, pos, th, sp)
            energy.append((on, off, damped))
            links.append((t, now))
            progress(label, round(t), round(duration))
        if float(sp.max()) < threshold:
            still_since = t if still_since is None else still_since
            if t - still_since >= hold:
                converged = still_since
                if (k + 1) % every:
                    track.add(t, pos, th, sp)
                    energy.append((on, off, damped))
                break
        else:
            still_since = None
    ts, ps, ths, sps = track.arrays()
    f, _ = forces(pos, th, cfg, circles, walls)
    across = np.abs(f[:, 0] * np.sin(th) - f[:, 1] * np.cos(th))
    e = np.array(energy)
    end = float(ts[-1])
    return Run(variant, ts, ps, ths, sps, converged, _churn(links, hold), float(np.hypot(f[:, 0], f[:, 1]).max()),
               float(across.max()), e[:, 0], e[:, 1], e[:, 2],
               [c for c in log.changes if c.t >= end - CHANGES_WINDOW])


class _ChangeLog:
    """The links made or broken over the last `CHANGES_WINDOW` s of a kinematic run, each of its kinds."""

    def __init__(self, distance: float, reach: float, walls: NDArray[np.float64], sensing: float) -> None:
        self.distance, self.reach, self.walls, self.sensing = distance, reach, walls, sensing
        self.before: set[tuple[int, int]] | None = None  # the links in effect the step before
        self.earlier: NDArray[np.intp] | None = None  # ... and the kept triangulation then
        self.changes: deque[Change] = deque()  # the last CHANGES_WINDOW s of them

    def update(self, t: float, now: set[tuple[int, int]], pos: NDArray[np.float64],
               triangles: NDArray[np.intp] | None) -> None:
        """Log the step at `t` whose links in effect are `now` (the team at `pos`, the kept triangulation)."""
        if self.before is not None and now != self.before:
            made, tri = _change_kinds(t, now - self.before, self.before - now, pos, triangles,
                                      self.distance, self.reach, self.walls, self.sensing, self.earlier)
            self.changes.extend(made)
            if triangles is None:  # the Delaunay triangulation changes only with the links
                self.earlier = tri
            while self.changes and self.changes[0].t < t - CHANGES_WINDOW:
                self.changes.popleft()
        self.before = now
        if triangles is not None:
            self.earlier = triangles


def _churn(links: list[tuple[float, set[tuple[int, int]]]], hold: float) -> float:
    """Neighbourhood links made or broken per s over the last `hold` s of the samples (NaN: too few)."""
    window = [(t, e) for t, e in links if t >= links[-1][0] - hold - 1e-9] if links else []
    return (sum(len(a ^ b) for (_, a), (_, b) in zip(window, window[1:])) / (window[-1][0] - window[0][0])
            if len(window) > 1 else math.nan)


def _change_kinds(t: float, added: set[tuple[int, int]], removed: set[tuple[int, int]], pos: NDArray[np.float64],
                  triangles: NDArray[np.intp] | None, d: float, reach: float, walls: NDArray[np.float64],
                  sensing: float, earlier: NDArray[np.intp] | None = None
                  ) -> tuple[list[Change], NDArray[np.intp] | None]:
    """Tell apart the links made (`added`) and broken (`removed`) in one step at the positions `pos`
    the step started from: a flip (a made link whose two opposite robots in the triangulation are the
    ends of a broken one, and that broken one), on the team's edge (a side of one triangle; a link the
    triangulation lacks, such as a physical neighbour's, when both its robots are on such a side or
    in no triangle; a broken link is judged in `earlier`, the triangulation the step before, when
    given), at the radio reach (longer than 0.9 `reach`), near a wall
    (a robot of it within `sensing` of one), shorter than d. `triangles`: the kept triangulation,
    else the Delaunay triangulation of `pos` (the paper's law and the physical neighbourhood).
    Returns the changes and the triangulation they were judged in."""
    if triangles is None and len(pos) >= 3:
        from scipy.spatial import Delaunay, QhullError

        try:
            triangles = np.asarray(Delaunay(pos).simplices, dtype=np.intp)
        except (QhullError, ValueError):
            triangles = None
    def sides(tri: NDArray[np.intp] | None) -> dict[tuple[int, int], list[int]]:
        out: dict[tuple[int, int], list[int]] = {}
        for a, b, c in ([] if tri is None else tri.tolist()):
            for u, v, w in ((a, b, c), (b, c, a), (c, a, b)):
                out.setdefault((min(u, v), max(u, v)), []).append(w)
        return out

    def rim(tri_sides: dict[tuple[int, int], list[int]], tri: NDArray[np.intp] | None) -> set[int]:
        """Robots on the team's edge: on a side of one triangle, or in no triangle."""
        inside = set() if tri is None else set(np.unique(tri).tolist())
        return {r for key, o in tri_sides.items() if len(o) == 1 for r in key} | (set(range(len(pos))) - inside)

    def on_edge(key: tuple[int, int], tri_sides: dict[tuple[int, int], list[int]], outer: set[int]) -> bool:
        if key in tri_sides:  # a side of the triangulation: of one triangle only
            return len(tri_sides[key]) == 1
        return key[0] in outer and key[1] in outer  # a link it lacks (physical, or dropped): both ends on the rim

    opposite = sides(triangles)
    was = opposite if earlier is None else sides(earlier)
    rim_now = rim(opposite, triangles)
    rim_was = rim_now if earlier is None else rim(was, earlier)
    flips: set[tuple[int, int]] = set()
    for key in added:
        other = opposite.get(key, [])
        if len(other) == 2 and (min(other), max(other)) in removed:
            flips |= {key, (min(other), max(other))}
    near = np.zeros(len(pos), dtype=bool)
    if len(walls):
        a, ab = walls[None, :, :2], walls[None, :, 2:] - walls[None, :, :2]
        along = np.clip(np.einsum("nkj,nkj->nk", pos[:, None, :] - a, ab)
                        / np.maximum(np.einsum("nkj,nkj->nk", ab, ab), 1e-12), 0, 1)
        gap = np.hypot(*(a + along[..., None] * ab - pos[:, None, :]).transpose(2, 0, 1))
        near = gap.min(axis=1) <= sensing
    out = []
    for made, keys in ((True, added), (False, removed)):
        for i, j in sorted(keys):
            length = float(np.hypot(*(pos[j] - pos[i])))
            out.append(Change(round(t, 6), made, i, j, length, (i, j) in flips,
                              on_edge((i, j), opposite, rim_now) if made else on_edge((i, j), was, rim_was),
                              length > 0.9 * reach, bool(near[i] or near[j]), length < 1.05 * d))
    return out, triangles


def _links(pos: NDArray[np.float64], cfg: SpreadConfig) -> set[tuple[int, int]]:
    """Every pair of robots that are neighbours (i < j)."""
    return {(i, int(j)) for i, js in enumerate(neighbourhoods(pos, cfg.neighbourhood, cfg.range, cfg.reach)) for j in js if i < j}


def _agents(scenario: Scenario, progress: Progress, variant: str, label: str) -> Run:
    """Agent processes given Deploy spread; positions from the simulator at 10 Hz."""
    from erni.sim.experiments.agents import TeamRun

    s = scenario.strategy
    model, _, neighbourhood = variant.partition("/")
    duration = float(s.get("agent_duration", 150.0))
    threshold = float(s.get("still_speed", 0.05))
    hold = float(s.get("hold", 10.0))
    weight = s.get("obstacle_weight", "neighbourhood")
    mission = {"speed": float(s.get("speed", 0.4)), "network_aware": False,
               "wall_distance": float(s.get("wall_distance", 2.5)),
               "obstacle_distance": float(s.get("obstacle_distance", 2.0)),
               **({} if s.get("sensing") is None else {"sensing_range": float(s["sensing"])}),
               **({} if weight == "neighbourhood" else {"obstacle_weight": float(weight)})}
    params = {"distance": float(s.get("distance", 5.0)), "gain": float(s.get("gain", 2.0)),
              "dt": float(s.get("dt", 0.2)), "range": float(s.get("range", 6.0)),
              "neighbourhood": neighbourhood, "model": model}
    names = scenario.robot_names()
    with TeamRun(scenario, lambda what, d, t: progress(f"{label}: {what}", d, t), mission=mission).start() as team:
        for name in names:
            team.send(name, "Deploy", "spread", **params)

        def settled() -> bool:  # judged as the figure judges it: on every sample
            got = team.samples()
            if not got or got[-1].t - got[0].t < hold + 5.0:
                return False
            return math.isfinite(_still(np.array([x.t for x in got]), np.array([x.v for x in got]), threshold, hold))

        team.wait("spreading", duration, settled)
        samples = team.samples()
    t = np.array([x.t for x in samples]) - samples[0].t
    every = max(1, int(round(0.5 / max(1e-3, float(np.median(np.diff(t))) if len(t) > 1 else 0.1))))
    pick = list(range(0, len(samples), every))
    ts = t[pick]
    ps = np.array([np.stack([samples[k].x, samples[k].y], axis=1) for k in pick])
    ths = np.array([samples[k].th for k in pick])
    sps = np.abs(np.array([samples[k].v for k in pick]))
    converged = _still(t, np.array([x.v for x in samples]), threshold, hold)  # every sample, as `settled`
    return Run(variant, ts, ps, ths, sps, converged)


def _in_place(t: NDArray[np.float64], pos: NDArray[np.float64], radius: float, hold: float) -> float:
    """Start of the first stretch of `hold` s in which no robot left a circle of `radius` round where it was.

    A team can be slower than the still speed on average and yet not under it at every sample: a
    link switching on and off each control period keeps its two robots moving at 0.1 m/s in place.
    This judges the track, not the speeds, so such a team counts as settled in place.
    """
    for k in range(len(t)):
        end = int(np.searchsorted(t, t[k] + hold - 1e-9))
        if end >= len(t):
            break
        if float(np.hypot(*(pos[k:end + 1] - pos[k]).transpose(2, 0, 1)).max()) < radius:
            return float(t[k])
    return math.nan


def _pinned(pos: NDArray[np.float64], walls: NDArray[np.float64], within: float) -> int:
    if len(walls) == 0:
        return 0
    a, b = walls[:, :2], walls[:, 2:]
    ab = b - a
    count = 0
    for p in pos:
        s = np.clip(np.einsum("ij,ij->i", p - a, ab) / np.maximum(np.einsum("ij,ij->i", ab, ab), 1e-12), 0, 1)
        near = a + s[:, None] * ab
        count += int(np.min(np.hypot(*(near - p).T)) <= within)
    return count


@dataclass(frozen=True)
class _Judge:
    """What a spread run is measured against: the desired distance, the radio reach, the wall
    pinning distance and the stillness the scenario asks for, and the walls."""

    d: float
    R: float
    pinned_within: float
    threshold: float
    hold: float
    radius: float
    walls: NDArray[np.float64]

    @classmethod
    def of(cls, scenario: Scenario) -> _Judge:
        s = scenario.strategy
        return cls(float(s.get("distance", 5.0)), scenario.radio.comm_range, float(s.get("pinned", 0.5)),
                   float(s.get("still_speed", 0.05)), float(s.get("hold", 10.0)), float(s.get("still_radius", 0.1)),
                   _obstacles(scenario)[1])


def _result(scenario: Scenario, experiment: Experiment, mode: str, runs: list[Run],
            sweep: list[tuple[float, Run]] | None = None, over_seeds: list[list[Run]] | None = None) -> Result:
    s = scenario.strategy
    judge = _Judge.of(scenario)
    n = runs[0].pos.shape[1]
    res = Result(experiment.name, experiment.title, mode)
    res.mode_note = (f"{n} robot agent processes per variant, each given Deploy spread by the control node; "
                     "velocity commands over ARCOS from positions learned through MobiNet"
                     if mode == "agents" else
                     f"{n} robots stepped in one process by the mission's spread_step (equations 15/16)"
                     + (", too many for one agent process per robot on this machine" if n > 12 else ""))
    finals = {}
    in_place: dict[str, float] = {}  # variant -> when a run that did not converge settled in place
    for r in runs:
        finals[r.variant] = _run_metrics(res, r, judge, in_place)
    _input_rows(res, s, n, judge)
    for r in runs:
        _variant_row(res, r, judge, finals[r.variant], in_place, experiment, scenario, bool(over_seeds))
    sweep = sweep or []
    if sweep:
        _sweep_rows(res, sweep, judge.d)
    if over_seeds:
        _seed_rows(res, over_seeds, judge.threshold, judge.hold, judge.d, scenario.seed)
    res.notes.append("paper 001 shows the teams at t = 30 s (Figs 2-5, 8-11) and the paths of 12 robots (Figs 6-7); "
                     "it gives no convergence times or distances")
    paths = experiment.name == "spread-paths"
    res.draw = lambda fig: (_draw_paths(fig, scenario, runs, res, mode) if paths else
                            _draw(fig, scenario, runs, res, mode, sweep))
    if not paths:  # a row of four maps per four variants, and the curves under them
        res.figure_height = 2.6 * math.ceil(len(runs) / 4) + 3.6
    else:  # square maps side by side
        res.figure_height = 5.0
    return res


def _run_metrics(res: Result, r: Run, judge: _Judge, in_place: dict[str, float]) -> NDArray[np.float64]:
    """One variant's metrics, series and energies per robot; when it did not converge, when it settled
    in place (into `in_place`). Returns the nearest-neighbour distances at the end."""
    v, n, hold = r.variant, r.pos.shape[1], judge.hold
    final = r.pos[-1]
    k30 = int(np.argmin(np.abs(r.t - 30.0)))
    nn = _nn(final)
    energies = [energy_model.track_energy(r.t, r.pos[:, i, 0], r.pos[:, i, 1])[0] for i in range(n)]
    res.metrics[f"{v}: converged at (all slower than {judge.threshold:g} m/s for {hold:g} s)"] = (r.converged, "s")
    if not math.isfinite(r.converged):  # a converged run stops: its track may end before such a stretch
        in_place[v] = _in_place(r.t, r.pos, judge.radius, hold)
        res.metrics[f"{v}: settled in place at (every robot within {judge.radius:g} m for {hold:g} s)"] = (
            in_place[v], "s")
    res.metrics[f"{v}: mean NN distance at the end (d = {judge.d:g})"] = (float(nn.mean()), "m")
    res.metrics[f"{v}: smallest NN distance at the end"] = (float(nn.min()), "m")
    res.metrics[f"{v}: mean NN distance at t = 30 s"] = (mean_nn_distance(r.pos[k30]), "m")
    res.metrics[f"{v}: largest radio component at the end (R = {judge.R:g} m)"] = (
        kinematic.largest_share(final, judge.R), "share")
    if len(judge.walls):
        res.metrics[f"{v}: robots within {judge.pinned_within:g} m of a wall at the end"] = (
            float(_pinned(final, judge.walls, judge.pinned_within)), "robots")
    res.metrics[f"{v}: run length"] = (float(r.t[-1]), "s")
    if math.isfinite(r.churn):
        res.metrics[f"{v}: neighbourhood links made or broken per s in the last {hold:g} s"] = (r.churn, "1/s")
        res.metrics[f"{v}: largest move of a robot in the last {hold:g} s"] = (_moved(r, hold), "m")
        res.metrics[f"{v}: largest unbalanced force at the end"] = (r.force, "N")
        res.metrics[f"{v}: ... of it across the heading"] = (r.across, "N")
    if r.switched_on is not None and r.switched_off is not None and r.damped is not None:
        k = int(np.searchsorted(r.t, r.t[-1] - 100.0))  # the last 100 s (or the whole run)
        last = f"{min(100.0, float(r.t[-1])):g} s"
        res.metrics[f"{v}: spring energy switched on by neighbourhood changes, last {last}"] = (
            float(r.switched_on[-1] - r.switched_on[k]), "J")
        res.metrics[f"{v}: ... switched off"] = (float(r.switched_off[-1] - r.switched_off[k]), "J")
        res.metrics[f"{v}: ... taken out by the damping"] = (float(r.damped[-1] - r.damped[k]), "J")
    if r.changes:
        _change_metrics(res, v, r.changes, float(r.t[-1]))
    res.metrics[f"{v}: energy per robot, mean"] = (float(np.mean(energies)), "J")
    stride = max(1, len(r.t) // 300)
    res.series[f"{v}/mean_nn_distance"] = (list(r.t[::stride]), [mean_nn_distance(p) for p in r.pos[::stride]],
                                           "m")
    res.series[f"{v}/largest_component"] = (list(r.t[::stride]),
                                            [kinematic.largest_share(p, judge.R) for p in r.pos[::stride]], "share")
    res.series[f"{v}/max_speed"] = (list(r.t[::stride]), list(r.speed[::stride].max(axis=1)), "m/s")
    for i, e in enumerate(energies):
        res.robots.setdefault(f"robot{i + 1}", {})[f"{v} energy_j"] = round(e, 2)
    return nn


def _input_rows(res: Result, s: dict[str, Any], n: int, judge: _Judge) -> None:
    """The comparison's rows of settings: the paper's against the scenario's."""
    weight = s.get("obstacle_weight", "neighbourhood")
    res.compare("robots / desired distance d / damping k / dt",
                "120 (12 for paths) / 5 m / 2 / 0.2 s",
                f"{n} / {judge.d:g} m / {s.get('gain', 2.0):g} / {s.get('dt', 0.2):g} s", "", "the paper's setting",
                "input")
    res.compare("physical neighbourhood range R", "not stated (sensing or radio range, d <= r_c)",
                f"{s.get('range', 6.0):g}", "m", "the scenario's setting (about 1.2 d)", "input")
    if len(judge.walls):
        res.compare("wall sensed within (sensing range)", "\"only when it is inside the sensing range\"",
                    f"{s['sensing']:g}" if s.get("sensing") is not None else f"{s.get('range', 6.0):g} (R)", "m",
                    "the scenario's setting", "input")
        res.compare("wall: desired distance c, weight w", "c not stated, w = 1",
                    f"{s.get('wall_distance', 2.5):g} m, "
                    + ("neighbourhood size" if weight == "neighbourhood" else f"{float(weight):g}"), "",
                    "the scenario's setting", "input")


def _variant_row(res: Result, r: Run, judge: _Judge, final_nn: NDArray[np.float64], in_place: dict[str, float],
                 experiment: Experiment, scenario: Scenario, seeded: bool) -> None:
    """One variant's row of the comparison: when it converged (or why not), its distances, the paper's figure."""
    v = r.variant
    corridor = len(judge.walls) > 0
    k30 = int(np.argmin(np.abs(r.t - 30.0)))
    still = (f"not by {r.t[-1]:.0f} s" + (f" ({r.churn:.2g} link changes/s)" if math.isfinite(r.churn) else "")
             + (f", in place from {in_place[v]:.0f} s" if math.isfinite(in_place.get(v, math.nan)) else ""))
    ours = ((f"{r.converged:.0f} s" if math.isfinite(r.converged) else still)
            + f"; {float(final_nn.mean()):.2f} ({float(final_nn.min()):.2f}) m; {mean_nn_distance(r.pos[k30]):.2f} m")
    paper = PAPER_FIGURES.get(v)
    fig_no = (f"; Fig. {6 if v.startswith('holonomic') else 7}, paths" if experiment.name == "spread-paths" else
              f"; Fig. {paper[1 if corridor else 0]} at 30 s" if paper else "")
    res.compare(f"{_name(v)}" + (f", seed {scenario.seed} (drawn)" if seeded else "")
                + ": converged at; NN at the end (smallest); NN at 30 s", "converges" + fig_no, ours, "",
                f"all < {judge.threshold:g} m/s for {judge.hold:g} s"
                + (f"; in place: all within {judge.radius:g} m for {judge.hold:g} s" if v in in_place else "")
                + (f"; pinned to a wall: {_pinned(r.pos[-1], judge.walls, judge.pinned_within)}" if corridor else ""))


def _sweep_rows(res: Result, sweep: list[tuple[float, Run]], d: float) -> None:
    """The metrics and comparison rows of the sweep over the neighbourhood range R."""
    for r_range, r in sweep:
        nn = _nn(r.pos[-1])
        res.metrics[f"{r.variant}, R = {r_range:g} m: mean NN distance at the end"] = (float(nn.mean()), "m")
        res.metrics[f"{r.variant}, R = {r_range:g} m: converged at"] = (r.converged, "s")
    text = "; ".join(
        f"{r_range / d:.2g} d: " + " / ".join(f"{float(_nn(r.pos[-1]).mean()):.2f}"
                                               for q, r in sweep if q == r_range)
        for r_range in dict.fromkeys(q for q, _ in sweep))
    res.compare("mean NN distance against R (holonomic / nonholonomic, physical)", "not stated", text, "m",
                "each run to convergence; every robot within R pulls or pushes toward d")
    for q, r in sweep:
        if any(math.isclose(q, f * d) for f in (1.0, 1.2)):
            k30 = int(np.argmin(np.abs(r.t - 30.0)))
            res.metrics[f"{r.variant}, R = {q:g} m: mean NN distance at t = 30 s"] = (
                mean_nn_distance(r.pos[k30]), "m")
    side = [(q, r) for q, r in sweep if any(math.isclose(q, f * d) for f in (1.0, 1.2))]

    def at30(r: Run) -> float:
        return mean_nn_distance(r.pos[int(np.argmin(np.abs(r.t - 30.0)))])

    def both(q: float) -> str:
        got = [r for q2, r in side if q2 == q]
        when = " / ".join(f"{r.converged:.0f}" if math.isfinite(r.converged) else "-" for r in got)
        return (f"R = {q / d:.2g} d: {when} s, NN " + " / ".join(f"{float(_nn(r.pos[-1]).mean()):.2f}" for r in got)
                + " m (" + " / ".join(f"{at30(r):.2f}" for r in got) + " at 30 s)")

    if side:
        res.compare("physical, R = d and 1.2 d (holonomic / nonholonomic): converged at; NN at the end (at 30 s)",
                    "R not stated", "; ".join(both(q) for q in dict.fromkeys(q for q, _ in side)), "",
                    "-: not settled by the end of the run")


def _seed_rows(res: Result, over_seeds: list[list[Run]], threshold: float, hold: float, d: float,
               first_seed: int = 1) -> None:
    """Per variant over the seeds: how many converged, when (mean [95 % CI] of those that did), the
    mean and smallest nearest-neighbour distance at the end, the fastest robot (m/s)."""
    from erni.sim.experiments.stats import fmt_ci, mean_ci, wilson

    n = len(over_seeds)
    for k, v in enumerate(r.variant for r in over_seeds[0]):
        got = [runs[k] for runs in over_seeds]
        times = [r.converged for r in got]
        done = sum(math.isfinite(x) for x in times)
        mean_nn = [float(_nn(r.pos[-1]).mean()) for r in got]
        least = [float(_nn(r.pos[-1]).min()) for r in got]
        fastest = max(float(r.speed.max()) for r in got)
        share, lo, hi = wilson(done, n)
        conv = mean_ci(times)
        res.metrics[f"{v}: seeds converged"] = (float(done), f"of {n}")
        res.metrics[f"{v}: converged at, mean over the seeds that did"] = (conv[0], "s")
        res.metrics[f"{v}: converged at, 95 % CI"] = (f"[{conv[1]:.1f}, {conv[2]:.1f}]", "s")
        for name, vals in (("mean NN distance at the end", mean_nn), ("smallest NN distance at the end", least)):
            m = mean_ci(vals)
            res.metrics[f"{v}: {name}, mean over {n} seeds"] = (m[0], "m")
            res.metrics[f"{v}: {name}, 95 % CI"] = (f"[{m[1]:.2f}, {m[2]:.2f}]", "m")
        res.metrics[f"{v}: fastest robot in any seed"] = (fastest, "m/s")
        for seed, r in enumerate(got, first_seed):
            if not math.isfinite(r.converged) and r.changes:
                c = change_summary(r.changes, float(r.t[-1]))
                res.metrics[f"{v}, seed {seed} (not converged): link changes in the last "
                            f"{min(CHANGES_WINDOW, float(r.t[-1])):g} s"] = (
                    f"{c['per_s']:.2f}/s; flips {c['flip']:.0%}, team's edge {c['edge']:.0%}, at the reach "
                    f"{c['reach']:.0%}, near a wall {c['wall']:.0%}, shorter than 1.05 d {c['short']:.0%}; "
                    f"{c['length'][0]:.1f}-{c['length'][2]:.1f} m (median {c['length'][1]:.1f}); {c['links']} links, "
                    f"the most changed {c['top'][1]} times; largest move in the last {hold:g} s "
                    f"{_moved(r, hold):.2f} m", "")
        res.series[f"{v}/converged_at_by_seed"] = (list(map(float, range(1, n + 1))), times, "s")
        res.compare(f"{_name(v)} over {n} seeds: converged; at; NN at the end (smallest); fastest robot",
                    "one run, no times", f"{done}/{n}; {fmt_ci(*conv, digits=1)} s; {fmt_ci(*mean_ci(mean_nn))} "
                    f"({fmt_ci(*mean_ci(least))}) m; {fastest:.2f} m/s", "",
                    f"mean [95 % CI] over the seeds (Student t); converged {done}/{n}: Wilson "
                    f"[{lo:.2f}, {hi:.2f}]; converged: all < {threshold:g} m/s for {hold:g} s")
        del share


def change_summary(changes: list[Change], end: float) -> dict[str, Any]:
    """What the link changes of a run's last `CHANGES_WINDOW` s were: how many a second, the share
    of each kind, their lengths, how many links changed and how often the most changed one did (a
    few links changing many times: a cycle between a few configurations)."""
    window = min(CHANGES_WINDOW, end)
    per_link: dict[tuple[int, int], int] = {}
    for c in changes:
        per_link[(c.i, c.j)] = per_link.get((c.i, c.j), 0) + 1
    top = max(per_link.items(), key=lambda x: x[1]) if per_link else ((-1, -1), 0)
    lengths = np.array([c.length for c in changes]) if changes else np.zeros(0)
    n = max(1, len(changes))
    return {"count": len(changes), "per_s": len(changes) / window if window > 0 else math.nan,
            **{kind: sum(getattr(c, kind) for c in changes) / n for kind in ("flip", "edge", "reach", "wall", "short")},
            "length": (float(lengths.min()), float(np.median(lengths)), float(lengths.max())) if len(lengths) else
            (math.nan, math.nan, math.nan),
            "links": len(per_link), "top": top, "robots": len({x for c in changes for x in (c.i, c.j)})}


def _change_metrics(res: Result, v: str, changes: list[Change], end: float) -> None:
    got = change_summary(changes, end)
    last = f"last {min(CHANGES_WINDOW, end):g} s"
    res.metrics[f"{v}: link changes, {last}"] = (float(got["count"]), "changes")
    for kind, what in (("flip", "flips of a quadrilateral's diagonal"), ("edge", "on the team's edge"),
                       ("reach", "at the radio reach (> 0.9 of it)"), ("wall", "with a robot near a wall"),
                       ("short", "shorter than 1.05 d")):
        res.metrics[f"{v}: ... share {what}"] = (got[kind], "share")
    lo, med, hi = got["length"]
    res.metrics[f"{v}: ... their length, min / median / max"] = (f"{lo:.2f} / {med:.2f} / {hi:.2f}", "m")
    (i, j), top = got["top"]
    res.metrics[f"{v}: ... links that changed; robots of them"] = (f"{got['links']}; {got['robots']}", "")
    res.metrics[f"{v}: ... most changes of one link"] = (f"{top} (robot{i + 1}-robot{j + 1})", "changes")


def _moved(r: Run, hold: float) -> float:
    """Largest distance a robot moved over the last `hold` s of the run."""
    k = int(np.searchsorted(r.t, r.t[-1] - hold))
    return float(np.hypot(*(r.pos[-1] - r.pos[k]).T).max())


def _nn(pos: NDArray[np.float64]) -> NDArray[np.float64]:
    d = kinematic.distances(pos)
    np.fill_diagonal(d, math.inf)
    return np.asarray(d.min(axis=1), dtype=float)


PAPER_FIGURES = {"holonomic/physical": (2, 8), "holonomic/delaunay": (3, 9), "nonholonomic/physical": (4, 10),
                 "nonholonomic/delaunay": (5, 11)}  # paper 001's figure of each variant at t = 30 s (open, corridor)


def _name(variant: str) -> str:
    base, settle = variant.removesuffix(SETTLE), variant.endswith(SETTLE)
    model, _, nb = base.partition("/")
    return f"{model}, {'Delaunay' if nb == 'delaunay' else nb}" + (" + settling" if settle else "")


def _draw(fig: Any, scenario: Scenario, runs: list[Run], res: Result, mode: str,
          sweep: list[tuple[float, Run]]) -> None:
    """The team of every variant at t = 30 s (the paper's figures), four maps a row; under them the
    spacing and the fastest robot over time, and the settled spacing against the range R."""
    cols = 4
    rows = math.ceil(len(runs) / cols)
    _, walls = _obstacles(scenario)
    corridor = len(walls) > 0
    gs = fig.add_gridspec(rows + 1, cols, height_ratios=[1.0] * rows + [1.25])
    at30 = [r.pos[int(np.argmin(np.abs(r.t - 30.0)))] for r in runs]
    xmax = max(float(np.abs(p[:, 0]).max()) for p in at30) + 2.5
    ymax = 16.5 if corridor else max(float(np.abs(p[:, 1]).max()) for p in at30) + 2.5
    xmax = max(xmax, ymax) if not corridor else xmax
    for k, r in enumerate(runs):
        ax = fig.add_subplot(gs[k // cols, k % cols])
        draw_world(ax, scenario.world)
        k30 = int(np.argmin(np.abs(r.t - 30.0)))
        ax.scatter(at30[k][:, 0], at30[k][:, 1], s=7, color=color(k), zorder=4, lw=0)
        headings(ax, at30[k], r.th[k30], 1.6, color=color(k), zorder=4)
        ax.set_xlim(-xmax, xmax)
        ax.set_ylim(-ymax, ymax)
        paper = PAPER_FIGURES.get(r.variant)
        end = f"converged at {r.converged:.0f} s" if math.isfinite(r.converged) else f"not settled by {r.t[-1]:.0f} s"
        map_axes(ax, "")
        ax.set_title(f"{_name(r.variant)}" + (f" (Fig. {paper[1 if corridor else 0]})" if paper else "")
                     + f"\nt = {r.t[k30]:.0f} s; {end}", fontsize=8.5)
        ax.tick_params(labelsize=7)
        ax.xaxis.label.set_size(8)
        ax.yaxis.label.set_size(8)
        if k % cols:
            ax.set_ylabel("")
    bottom = ([fig.add_subplot(gs[rows, c]) for c in range(cols)] if sweep else
              [fig.add_subplot(gs[rows, :2]), fig.add_subplot(gs[rows, 2:])])
    d = float(scenario.strategy.get("distance", 5.0))
    ax = bottom[0]
    for k, r in enumerate(runs):
        t, vals, _ = res.series[f"{r.variant}/mean_nn_distance"]
        ax.plot(t, vals, color=color(k), lw=1.1, ls="--" if r.variant.endswith(SETTLE) else "-",
                label=_name(r.variant))
    ax.axhline(d, color="#555555", ls=":", lw=1)
    ax.axvline(30, color="#aaaaaa", ls="--", lw=0.8)
    time_axes(ax, "Mean distance to the nearest robot", "distance (m)")
    ax.set_ylim(0, d * 1.2)
    ax = bottom[1]
    for k, r in enumerate(runs):
        t, vals, _ = res.series[f"{r.variant}/max_speed"]
        ax.semilogy(t, np.maximum(vals, 1e-4), color=color(k), lw=1.1, ls="--" if r.variant.endswith(SETTLE) else "-")
    threshold = float(scenario.strategy.get("still_speed", 0.05))
    ax.axhline(threshold, color="#555555", ls=":", lw=1)
    time_axes(ax, f"Fastest robot (still: < {threshold:g} m/s)", "speed (m/s)")
    ax.set_ylim(1e-4, 3)
    for ax in bottom[:2]:
        ax.title.set_size(9)
    if sweep:
        _draw_sweep(bottom[2], bottom[3], sweep, d)
    handles, labels = bottom[0].get_legend_handles_labels()
    handles.append(bottom[0].lines[len(runs)])
    labels.append(f"d = {d:g} m (input)")
    fig.legend(handles, labels, loc="outside lower center", ncol=min(5, len(labels)), fontsize=8, frameon=False)
    fig.suptitle(f"{scenario.title} ({mode} mode, {runs[0].pos.shape[1]} robots)", fontsize=11)


def _draw_sweep(top: Any, bottom: Any, sweep: list[tuple[float, Run]], d: float) -> None:
    """Mean nearest-neighbour distance and time to converge against the neighbourhood range R."""
    xs = [q / d for q, _ in sweep]
    if not any(math.isfinite(r.converged) for _, r in sweep):  # nothing to draw: say so, on the ranges' axis
        bottom.text(0.5, 0.5, "no run settled\nby the end of its run", transform=bottom.transAxes, ha="center",
                    va="center", fontsize=9, color="#555555")
    pad = max(0.05, (max(xs) - min(xs)) * 0.08) if xs else 0.05
    for ax in (top, bottom):
        if xs:
            ax.set_xlim(min(xs) - pad, max(xs) + pad)
    for k, v in enumerate(("holonomic/physical", "nonholonomic/physical")):
        got = [(q, r) for q, r in sweep if r.variant == v]
        x = [q / d for q, _ in got]
        top.plot(x, [float(_nn(r.pos[-1]).mean()) for _, r in got], "o-", color=color(2 * k), ms=4)
        bottom.plot(x, [r.converged if math.isfinite(r.converged) else np.nan for _, r in got], "o-",
                    color=color(2 * k), ms=4)
    top.axhline(d, color="#555555", ls=":", lw=1)
    top.set_title("Settled spacing against R (physical)", fontsize=9)
    top.set_xlabel("R / d (R an input)")
    top.set_ylabel("mean NN distance (m)")
    top.set_ylim(0, d * 1.2)
    top.grid(alpha=0.3)
    bottom.set_title("Time to converge against R (physical)", fontsize=9)
    bottom.set_xlabel("R / d (R an input)")
    bottom.set_ylabel("converged at (s)")
    bottom.set_ylim(bottom=0)
    bottom.grid(alpha=0.3)


def _draw_paths(fig: Any, scenario: Scenario, runs: list[Run], res: Result, mode: str) -> None:
    """Paper 001, Figs 6-7: every robot's path, arrows showing its heading along the way."""
    by_seed = [res.series.get(f"{r.variant}/converged_at_by_seed") for r in runs]
    cols = len(runs) + (1 if all(by_seed) else 0)
    gs = fig.add_gridspec(1, cols, width_ratios=[1.0] * len(runs) + [0.7] * (cols - len(runs)))
    extent = max(float(np.abs(r.pos).max()) for r in runs) + 1.5
    for k, r in enumerate(runs):
        ax = fig.add_subplot(gs[0, k])
        draw_world(ax, scenario.world)
        n = r.pos.shape[1]
        for i in range(n):
            ax.plot(r.pos[:, i, 0], r.pos[:, i, 1], color=color(i), lw=1.1, alpha=0.9)
            # an arrow every 0.8 m along the path, and at its end
            along = np.r_[0.0, np.cumsum(np.hypot(*np.diff(r.pos[:, i], axis=0).T))]
            marks = np.arange(0.0, along[-1], 0.8)
            idx = np.unique(np.r_[np.searchsorted(along, marks), len(r.t) - 1])
            ax.quiver(r.pos[idx, i, 0], r.pos[idx, i, 1], np.cos(r.th[idx, i]), np.sin(r.th[idx, i]),
                      color=color(i), angles="xy", scale_units="xy", scale=1.6, width=0.004, headwidth=4,
                      headlength=4.5, alpha=0.85)
            ax.plot(*r.pos[0, i], "o", color=color(i), mfc="white", ms=5)
        ax.set_xlim(-extent, extent)
        ax.set_ylim(-extent, extent)
        end = f"converged at {r.converged:.0f} s" if math.isfinite(r.converged) else f"{r.t[-1]:.0f} s"
        fig_no = "Fig. 6" if r.variant.startswith("holonomic") else "Fig. 7"
        map_axes(ax, f"{r.variant.replace('/', ', ')} ({fig_no}): {end}")
        ax.title.set_size(10)
    if cols > len(runs):
        from erni.sim.experiments.stats import mean_ci

        ax = fig.add_subplot(gs[0, len(runs)])
        for k, got in enumerate(by_seed):
            assert got is not None
            times = np.array(got[1], dtype=float)
            ok = np.isfinite(times)
            rng = np.random.default_rng(k)
            ax.plot(k + rng.uniform(-0.12, 0.12, ok.sum()), times[ok], "o", color=color(k), ms=4, alpha=0.7)
            m, lo, hi = mean_ci(times.tolist())
            if math.isfinite(lo):
                ax.errorbar([k + 0.3], [m], yerr=[[m - lo], [hi - m]], fmt="s", color="black", ms=4, capsize=3)
            ax.text(k, 0.02, f"{int(ok.sum())}/{len(times)} converged", transform=ax.get_xaxis_transform(),
                    ha="center", fontsize=8)
        ax.set_xticks(range(len(runs)), [r.variant.split("/")[0] for r in runs])
        ax.set_xlim(-0.6, len(runs) - 0.4)
        ax.set_ylim(bottom=0)
        ax.set_ylabel("converged at (s)")
        ax.set_title(f"Over {len(by_seed[0][1]) if by_seed[0] else 0} seeds: mean, 95 % CI", fontsize=10)
        ax.grid(axis="y", color="#e0e0e0", lw=0.6)
    fig.suptitle(f"{scenario.title} ({mode} mode): paths, arrows = heading (circles: start)", fontsize=13)
