"""Paper 002, section II.C: six robots patrol six territories; one fails and a neighbour takes over.

Kinematic mode: each robot drives its block's sweep path (`patrol.sweep_path`) and sends a
heartbeat every `heartbeat` seconds to every robot the radio connects it to (directly or
over several hops). Each robot keeps a `patrol.TakeoverTable`: when a neighbour falls silent
its neighbours back off by rank, the first claims the block and patrols it after its own,
the others yield on hearing the claim. The scenario's `[[failure]]` says who fails when.
Metrics: detection and takeover delays, claims made (exactly one is right), who took over,
the share of the territory visited within a sliding window over time, energy per robot.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
from numpy.typing import NDArray

from erni.sim import kinematic
from erni.sim.experiments import Experiment, Progress, Result
from erni.sim.experiments.plots import color, map_axes, time_axes
from erni.sim.scenario import Scenario, ScenarioError
from erni.strategies import energy as paper_energy
from erni.strategies import patrol


def run(scenario: Scenario, progress: Progress, *, experiment: Experiment, **_: Any) -> Result:
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
    speed = float(s.get("speed", 0.4))
    spacing = float(s.get("spacing", 2.0))
    window = float(s.get("window", 60.0))
    cell = float(s.get("cell", 1.0))
    dt = float(s.get("dt", 0.2))
    duration = scenario.duration or 180.0
    R = scenario.radio.comm_range
    fail_at = {f.robot: f.at for f in scenario.failure}
    pos = np.array([[st.x, st.y] for st in starts])
    th = np.radians([st.heading for st in starts])
    tables = [patrol.TakeoverTable(names[i], blocks[i], silence=silence, base=base) for i in range(n)]
    routes = [list(patrol.sweep_path(blocks[i], spacing)) for i in range(n)]
    waypoint = [0] * n
    alive = np.ones(n, dtype=bool)
    events: list[tuple[float, str, str, str]] = []  # t, robot, kind, about
    holdings: list[tuple[float, str, tuple[str, ...]]] = []
    xs = np.arange(territory[0] + cell / 2, territory[2], cell)
    ys = np.arange(territory[1] + cell / 2, territory[3], cell)
    last_visit = np.full((len(ys), len(xs)), -math.inf)
    coverage_t: list[float] = []
    coverage_v: list[float] = []
    track = kinematic.Track()
    track.add(0.0, pos, th, np.zeros(n))
    next_beat = 0.0
    steps = int(round(duration / dt))
    for k in range(steps):
        t = (k + 1) * dt
        for i, name in enumerate(names):
            if alive[i] and name in fail_at and t >= fail_at[name]:
                alive[i] = False
                events.append((t, name, "fails", name))
        if t >= next_beat:
            next_beat += heartbeat
            comps = kinematic.components(pos[alive], R)
            idx = np.flatnonzero(alive)
            for comp in comps:
                members = [int(idx[c]) for c in comp]
                for i in members:
                    beat = tables[i].heartbeat()
                    for j in members:
                        if j != i:
                            for ev in tables[j].heard(names[i], blocks[i], t, tuple(beat["holds"]), beat["claims"]):
                                events.append((t, names[j], ev.kind, ev.about))
                                _reroute(routes, waypoint, j, tables[j], blocks, names, spacing)
        for i in np.flatnonzero(alive).tolist():
            for ev in tables[i].tick(t):
                events.append((t, names[i], ev.kind, ev.about))
                if ev.kind in ("claim", "yield", "return"):
                    _reroute(routes, waypoint, i, tables[i], blocks, names, spacing)
        targets = np.array([routes[i][waypoint[i]] for i in range(n)])
        pos, th, sp = kinematic.drive(pos, th, targets, dt, speed, moving=alive)
        for i in range(n):
            if alive[i] and math.hypot(*(pos[i] - targets[i])) < 0.15:
                waypoint[i] = (waypoint[i] + 1) % len(routes[i])
            if alive[i]:
                cx = int((pos[i, 0] - territory[0]) / cell)
                cy = int((pos[i, 1] - territory[1]) / cell)
                for yy in range(max(0, cy - 1), min(len(ys), cy + 2)):
                    for xx in range(max(0, cx - 1), min(len(xs), cx + 2)):
                        last_visit[yy, xx] = t
        track.add(t, pos, th, sp)
        if k % 5 == 0:
            coverage_t.append(t)
            coverage_v.append(float((last_visit >= t - window).mean()))
            holdings.append((t, "", tuple(",".join(sorted(tb.holds)) for tb in tables)))
            progress("patrolling", round(t), round(duration))
    ts, ps, _th, _speed = track.arrays()
    res = Result(experiment.name, experiment.title, "kinematic")
    res.series["team/territory_visited_in_window"] = (coverage_t, coverage_v, "share")
    failed = [name for name in names if name in fail_at]
    for name in failed:
        t_fail = fail_at[name]
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
    before = [v for t, v in zip(coverage_t, coverage_v) if t <= min(fail_at.values(), default=duration)]
    res.metrics["territory visited within the window, before failure"] = (max(before) if before else math.nan, "share")
    res.metrics["territory visited within the window, at the end"] = (coverage_v[-1], "share")
    res.metrics["territory visited within the window, lowest after failure"] = (
        min((v for t, v in zip(coverage_t, coverage_v) if t > min(fail_at.values(), default=duration)),
            default=math.nan), "share")
    for i, name in enumerate(names):
        e, dist = paper_energy.track_energy(ts, ps[:, i, 0], ps[:, i, 1])
        res.robots[name] = {"block": i + 1, "distance_m": round(dist, 1), "energy_j": round(e, 1),
                            "holds": len(tables[i].holds)}
    res.notes.append(f"window for 'visited': the last {window:g} s; heartbeats every {heartbeat:g} s; "
                     f"back-off base {base:g} s by rank (nearest touching block first)")
    res.notes.append("paper 002 gives no takeover times; its Table II round trips (about 90 ms) are not "
                     "modelled here")
    res.draw = lambda fig: _draw(fig, scenario, names, blocks, ps, ts, events, res, fail_at, duration, window)
    return res


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
          duration: float, window: float) -> None:
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
    fig.suptitle(scenario.title, fontsize=13)
