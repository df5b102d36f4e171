"""Paper 002, section II.C: six robots patrol six territories; one fails and a neighbour takes over.

Each robot sweeps its block (`patrol.sweep_path`) and beacons a heartbeat every `heartbeat`
seconds; each keeps a `patrol.TakeoverTable`: when a neighbour falls silent for `silence`
seconds its neighbours back off by rank, the first claims the block and patrols it after its
own, the others yield on hearing the claim. The scenario's `[[failure]]` says who fails when.

Agents mode (default): six robot agent processes; the control node sends each `Deploy
patrol` with its block; heartbeats are `Territory` objects the transport carries between the
robots (UDP status, filtered by the simulated radio); at the failure time the failed robot's
agent process is killed (its robot stops on the ARCOS watchdog). Each robot's decisions
(silent, claim, yield) and their times come back in its task's result.

Kinematic mode: the same `TakeoverTable`s stepped in one process, heartbeats delivered to
every robot the radio connects (directly or over several hops).

Metrics: detection and takeover delays, claims made (exactly one is right), who took over,
the share of the territory visited within a sliding window over time.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import Any

import numpy as np
from numpy.typing import NDArray

from erni.sim import kinematic
from erni.sim.experiments import Experiment, Progress, Result
from erni.sim.experiments.plots import color, map_axes, time_axes
from erni.sim.scenario import Scenario, ScenarioError
from erni.strategies import energy as paper_energy
from erni.strategies import patrol


def run(scenario: Scenario, progress: Progress, *, experiment: Experiment, mode: str, **_: Any) -> Result:
    """Patrol, fail, detect, take over; return figure and metrics."""
    s = scenario.strategy
    xmin, ymin, xmax, ymax = (float(v) for v in s.get("territory", (0.0, 0.0, 30.0, 20.0)))
    territory: patrol.Block = (xmin, ymin, xmax, ymax)
    nx, ny = int(s.get("nx", 3)), int(s.get("ny", 2))
    blocks = patrol.split(territory, nx, ny)
    starts = scenario.starts()
    names = [st.name for st in starts]
    n = len(names)
    if n != len(blocks):
        raise ScenarioError(f"{scenario.name}: {n} robots for {len(blocks)} blocks; expected one robot per block")
    heartbeat = float(s.get("heartbeat", 1.0))
    silence = float(s.get("silence", 5.0))
    base = float(s.get("base", 1.5))
    window = float(s.get("window", 60.0))
    cell = float(s.get("cell", 1.0))
    duration = scenario.duration or 180.0
    fail_at = {f.robot: f.at for f in scenario.failure}
    if mode == "agents":
        ts, ps, events, holds = _agents(scenario, progress, blocks, fail_at, duration)
    else:
        ts, ps, events, holds = _kinematic(scenario, progress, blocks, fail_at, duration)
    alive_until = {i: fail_at.get(name, math.inf) for i, name in enumerate(names)}
    coverage_t, coverage_v = _visited_in_window(ts, ps, territory, cell, window, alive_until)
    res = Result(experiment.name, experiment.title, mode)
    res.mode_note = ("six robot agent processes given Deploy patrol by the control node; heartbeats are Territory "
                     "objects carried by the transport between robots; the failed robot's agent process is killed"
                     if mode == "agents" else "takeover tables stepped in one process; heartbeats delivered "
                     "to every robot the radio model connects")
    res.series["team/territory_visited_in_window"] = (coverage_t, coverage_v, "share")
    failed = [name for name in names if name in fail_at]
    for name in failed:
        _failure_metrics(res, name, fail_at[name], events)
    first_failure = min(fail_at.values(), default=duration)
    before = [v for t, v in zip(coverage_t, coverage_v) if t <= first_failure]
    res.metrics["territory visited within the window, before failure"] = (max(before) if before else math.nan, "share")
    res.metrics["territory visited within the window, at the end"] = (coverage_v[-1], "share")
    res.metrics["territory visited within the window, lowest after failure"] = (
        min((v for t, v in zip(coverage_t, coverage_v) if t > first_failure), default=math.nan), "share")
    for i, name in enumerate(names):
        dist = paper_energy.track_energy(ts, ps[:, i, 0], ps[:, i, 1])[1]
        res.robots[name] = {"block": i + 1, "distance_m": round(dist, 1), "holds": holds.get(name, 0)}
    _compare(res, failed, events, heartbeat=heartbeat, silence=silence, base=base, mode=mode)
    res.notes.append(f"window for 'visited': the last {window:g} s")
    res.notes.append("paper 002's Table II round trips are measured by `erni experiment roundtrip`")
    res.draw = lambda fig: _draw(fig, scenario, names, blocks, ps, ts, events, res, fail_at, duration, window, mode)
    return res


Event = tuple[float, str, str, str]  # t, robot, kind, about


def _visited_in_window(ts: NDArray[np.float64], ps: NDArray[np.float64], territory: patrol.Block, cell: float,
                       window: float, alive_until: dict[int, float]) -> tuple[list[float], list[float]]:
    """The share of the territory's cells some live robot was in or next to within the last `window`
    seconds, every fifth sample: times and shares."""
    xs = np.arange(territory[0] + cell / 2, territory[2], cell)
    ys = np.arange(territory[1] + cell / 2, territory[3], cell)
    last_visit = np.full((len(ys), len(xs)), -math.inf)
    coverage_t: list[float] = []
    coverage_v: list[float] = []
    for k, t in enumerate(ts):
        for i in range(len(alive_until)):
            if t > alive_until[i]:
                continue
            cx = int((ps[k, i, 0] - territory[0]) / cell)
            cy = int((ps[k, i, 1] - territory[1]) / cell)
            for yy in range(max(0, cy - 1), min(len(ys), cy + 2)):
                for xx in range(max(0, cx - 1), min(len(xs), cx + 2)):
                    last_visit[yy, xx] = t
        if k % 5 == 0:
            coverage_t.append(float(t))
            coverage_v.append(float((last_visit >= t - window).mean()))
    return coverage_t, coverage_v


def _failure_metrics(res: Result, name: str, t_fail: float, events: list[Event]) -> None:
    """The metrics of one failed robot: when it failed, when it was found silent, who claimed its block."""
    silent = [e for e in events if e[2] == "silent" and e[3] == name]
    claims = [e for e in events if e[2] == "claim" and e[3] == name]
    yields = [e for e in events if e[2] == "yield" and e[3] == name]
    res.metrics[f"{name}: fails at"] = (t_fail, "s")
    res.metrics[f"{name}: first detection after the failure"] = (
        (min(e[0] for e in silent) - t_fail) if silent else math.nan, "s")
    res.metrics[f"{name}: takeover after the failure"] = ((claims[0][0] - t_fail) if claims else math.nan, "s")
    res.metrics[f"{name}: claims made (1 is right)"] = (float(len(claims)), "claims")
    res.metrics[f"{name}: neighbours that yielded"] = (float(len(yields)), "robots")
    res.metrics[f"{name}: block taken over by"] = (claims[0][1] if claims else "nobody", "")


def _compare(res: Result, failed: list[str], events: list[Event], *, heartbeat: float, silence: float,
             base: float, mode: str) -> None:
    """The paper's statements beside ours: settings, detection, the one claim, the neighbour that took over."""
    claims_all = [e for e in events if e[2] == "claim"]
    detect = [res.metrics[f"{name}: first detection after the failure"][0] for name in failed]
    takeover = [res.metrics[f"{name}: takeover after the failure"][0] for name in failed]
    res.compare("heartbeat period / silence before failed", "not stated", f"{heartbeat:g} / {silence:g} s", "s",
                "the scenario's setting", "input")
    res.compare("back-off of the k-th ranked neighbour", "not stated", f"{base:g} x (1 + k) s", "s",
                "the scenario's setting", "input")
    res.compare("failure detected by the neighbours", "yes", ", ".join(f"after {d:.1f} s" for d in detect
                                                                        if isinstance(d, float)) or "no", "",
                "first `silent` decision of any robot after the failed one stopped; bounded by the silence "
                "setting (an input), not a finding")
    res.compare("neighbours claiming the block", "exactly one", f"{len(claims_all)}", "claims",
                "claims made by all robots over the run" + (" (reported in their task results)"
                                                           if mode == "agents" else ""))
    res.compare("taken over by a neighbour of the failed block", "yes",
                ", ".join(str(res.metrics[f"{name}: block taken over by"][0]) for name in failed) or "-", "",
                "the robot whose claim stood, and the time from the failure: "
                + ", ".join(f"{t:.1f} s" for t in takeover if isinstance(t, float)))


def _agents(scenario: Scenario, progress: Progress, blocks: list[patrol.Block], fail_at: dict[str, float],
            duration: float) -> tuple[NDArray[np.float64], NDArray[np.float64], list[Event], dict[str, int]]:
    """Six agents given Deploy patrol; the failed one's process is killed; decisions from their results."""
    import time

    from erni.sim.experiments.agents import TeamRun

    s = scenario.strategy
    names = scenario.robot_names()
    mission = {"speed": float(s.get("speed", 0.4)), "patrol_spacing": float(s.get("spacing", 2.0)),
               "backoff_base": float(s.get("base", 1.5)), "network_aware": False}
    heartbeat, silence = float(s.get("heartbeat", 1.0)), float(s.get("silence", 5.0))
    with TeamRun(scenario, progress, mission=mission).start() as team:
        assert team.team is not None
        epoch0 = time.time() - team.now  # team clock 0 as wall-clock time
        uids = {}
        for name, b in zip(names, blocks):
            uids[name] = team.send(name, "Deploy", "patrol", xmin=b[0], ymin=b[1], xmax=b[2], ymax=b[3],
                                   heartbeat=heartbeat, silence=silence)
        pending = sorted(fail_at.items(), key=lambda kv: kv[1])
        failed_at: dict[str, float] = {}
        while team.now < duration:
            team.pump(0.5)
            progress("patrolling", round(team.now), round(duration))
            while pending and team.now >= pending[0][1]:
                name, _ = pending.pop(0)
                failed_at[name] = team.now
                team.team.fail(name)
        team.pump(1.0)
        samples = team.samples()
        events: list[Event] = []
        holds: dict[str, int] = {}
        for name, uid in uids.items():
            r = team.results.get(uid)
            if r is None:
                continue
            kinds = r.values.get("events") or []
            times = r.values.get("event_at") or []
            assert isinstance(kinds, list) and isinstance(times, list)
            for ev, at in zip(kinds, times):
                kind, _, about = str(ev).partition(" ")
                events.append((float(at) - epoch0 if isinstance(at, (int, float)) else math.nan, name, kind, about))
            held = r.values.get("holds")
            holds[name] = len(held) if isinstance(held, list) else 0
        for name, at in failed_at.items():
            fail_at[name] = at  # the moment the process was killed
            events.append((at, name, "fails", name))
    events.sort()
    ts = np.array([x.t for x in samples]) - samples[0].t + (samples[0].t - team.t0)
    ps = np.array([np.stack([x.x, x.y], axis=1) for x in samples])
    return ts, ps, events, holds


def _kinematic(scenario: Scenario, progress: Progress, blocks: list[patrol.Block], fail_at: dict[str, float],
               duration: float) -> tuple[NDArray[np.float64], NDArray[np.float64], list[Event], dict[str, int]]:
    """The takeover tables stepped in one process; heartbeats to every robot the radio connects."""
    s = scenario.strategy
    starts = scenario.starts()
    names = [st.name for st in starts]
    n = len(names)
    heartbeat = float(s.get("heartbeat", 1.0))
    silence = float(s.get("silence", 5.0))
    base = float(s.get("base", 1.5))
    speed = float(s.get("speed", 0.4))
    spacing = float(s.get("spacing", 2.0))
    dt = float(s.get("dt", 0.2))
    R = scenario.radio.comm_range
    pos = np.array([[st.x, st.y] for st in starts])
    th = np.radians([st.heading for st in starts])
    tables = [patrol.TakeoverTable(names[i], blocks[i], silence=silence, base=base) for i in range(n)]
    routes = [list(patrol.sweep_path(blocks[i], spacing)) for i in range(n)]
    waypoint = [0] * n
    alive = np.ones(n, dtype=bool)
    events: list[tuple[float, str, str, str]] = []  # t, robot, kind, about
    track = kinematic.Track()
    track.add(0.0, pos, th, np.zeros(n))
    next_beat = 0.0
    steps = int(round(duration / dt))

    def reroute(i: int) -> None:
        _reroute(routes, waypoint, i, tables[i], blocks, names, spacing)

    for k in range(steps):
        t = (k + 1) * dt
        _fail_due(t, names, alive, fail_at, events)
        if t >= next_beat:
            next_beat += heartbeat
            idx = np.flatnonzero(alive)
            for comp in kinematic.components(pos[alive], R):
                _exchange_beats(t, [int(idx[c]) for c in comp], tables, names, blocks, events, reroute)
        for i in np.flatnonzero(alive).tolist():
            for ev in tables[i].tick(t):
                events.append((t, names[i], ev.kind, ev.about))
                if ev.kind in ("claim", "yield", "return"):
                    reroute(i)
        targets = np.array([routes[i][waypoint[i]] for i in range(n)])
        pos, th, sp = kinematic.drive(pos, th, targets, dt, speed, moving=alive)
        _next_waypoints(pos, targets, alive, waypoint, routes)
        track.add(t, pos, th, sp)
        if k % 5 == 0:
            progress("patrolling", round(t), round(duration))
    ts, ps, _th, _speed = track.arrays()
    return ts, ps, events, {names[i]: len(tables[i].holds) for i in range(n)}


def _fail_due(t: float, names: list[str], alive: NDArray[np.bool_], fail_at: dict[str, float],
              events: list[Event]) -> None:
    """The robots whose failure time has come stop (logged in `events`)."""
    for i, name in enumerate(names):
        if alive[i] and name in fail_at and t >= fail_at[name]:
            alive[i] = False
            events.append((t, name, "fails", name))


def _next_waypoints(pos: NDArray[np.float64], targets: NDArray[np.float64], alive: NDArray[np.bool_],
                    waypoint: list[int], routes: list[list[NDArray[np.float64]]]) -> None:
    """A live robot at its waypoint heads for the next one of its route (round and round)."""
    for i in range(len(waypoint)):
        if alive[i] and math.hypot(*(pos[i] - targets[i])) < 0.15:
            waypoint[i] = (waypoint[i] + 1) % len(routes[i])


def _exchange_beats(t: float, members: list[int], tables: list[patrol.TakeoverTable], names: list[str],
                    blocks: list[patrol.Block], events: list[Event], reroute: Callable[[int], None]) -> None:
    """Every member of one connected group hears every other's heartbeat; a robot whose table decides
    something (logged in `events`) is rerouted."""
    for i in members:
        beat = tables[i].heartbeat()
        for j in members:
            if j != i:
                for ev in tables[j].heard(names[i], blocks[i], t, tuple(beat["holds"]), beat["claims"]):
                    events.append((t, names[j], ev.kind, ev.about))
                    reroute(j)


def _reroute(routes: list[list[NDArray[np.float64]]], waypoint: list[int], i: int, table: patrol.TakeoverTable,
             blocks: list[patrol.Block], names: list[str], spacing: float) -> None:
    """Robot i patrols its own block, then every block it holds."""
    held = [names.index(r) for r in sorted(table.holds, key=names.index)]
    route: list[NDArray[np.float64]] = []
    for b in [i] + [j for j in held if j != i]:
        route += list(patrol.sweep_path(blocks[b], spacing))
    routes[i] = route
    waypoint[i] = min(waypoint[i], len(route) - 1)


def _draw(fig: Any, scenario: Scenario, names: list[str], blocks: list[patrol.Block], ps: NDArray[np.float64],
          ts: NDArray[np.float64], events: list[tuple[float, str, str, str]], res: Result, fail_at: dict[str, float],
          duration: float, window: float, mode: str) -> None:
    from matplotlib.patches import Rectangle

    gs = fig.add_gridspec(2, 2, width_ratios=[1.25, 1])
    ax = fig.add_subplot(gs[:, 0])
    for i, b in enumerate(blocks):
        ax.add_patch(Rectangle((b[0], b[1]), b[2] - b[0], b[3] - b[1], facecolor=color(i), alpha=0.07,
                               edgecolor="#555555", lw=1.2))
        ax.text(b[0] + 0.4, b[3] - 0.5, f"block {i + 1}", va="top", fontsize=9, color="#333333")
    for i, name in enumerate(names):
        ax.plot(ps[:, i, 0], ps[:, i, 1], color=color(i), lw=1.0, alpha=0.85, label=name, zorder=10 - i)
        if name in fail_at:
            k = int(np.searchsorted(ts, fail_at[name]))
            ax.plot(*ps[min(k, len(ts) - 1), i], "X", color="black", ms=12, label=f"{name} fails")
    map_axes(ax, "Patrol paths: each robot sweeps its block")
    ax.legend(loc="upper center", bbox_to_anchor=(0.5, -0.1), ncol=4, fontsize=8)
    ax = fig.add_subplot(gs[0, 1])
    for row, name in enumerate(names):
        end = fail_at.get(name, duration)
        ax.barh(row, end, left=0, color=color(row), alpha=0.35, height=0.6)
        for t, who, kind, _about in events:
            if who != name:
                continue
            marker = {"silent": "|", "claim": "*", "yield": "x", "return": "o", "fails": "X"}[kind]
            ax.plot(t, row, marker, color="black" if kind != "claim" else "#e6a100", ms=11 if kind == "claim" else 7,
                    mec="black")
    for kind, marker, label in (("silent", "|", "detects silence"), ("claim", "*", "claims the block"),
                                ("yield", "x", "yields"), ("fails", "X", "fails")):
        ax.plot([], [], marker, color="#e6a100" if kind == "claim" else "black", mec="black", label=label)
    ax.set_yticks(range(len(names)), names)
    ax.invert_yaxis()
    time_axes(ax, "What each robot decided", "robot (bar: running)")
    ax.set_xlim(0, duration)
    ax.legend(loc="lower right", fontsize=8, ncol=2)
    ax = fig.add_subplot(gs[1, 1])
    times, visited, _ = res.series["team/territory_visited_in_window"]
    ax.plot(times, np.array(visited) * 100, color=color(0), lw=1.8)
    for name, at in fail_at.items():
        ax.axvline(at, color="black", ls="--", lw=1, label=f"{name} fails")
    claims = [e for e in events if e[2] == "claim"]
    for c in claims:
        ax.axvline(c[0], color="#e6a100", lw=1.5, label=f"{c[1]} takes over block of {c[3]}")
    time_axes(ax, f"Territory visited in the last {window:g} s", "share of the territory (%)")
    ax.set_ylim(0, 105)
    ax.legend(loc="lower right", fontsize=8)
    fig.suptitle(f"{scenario.title} ({mode} mode)", fontsize=13)
