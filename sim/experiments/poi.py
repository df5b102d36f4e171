"""Paper 000, section 5.1: three robots cover a point of interest past an obstacle (WiDep, Figure 5).

Kinematic mode: every `period` seconds all robots take one WiDep decision from the same
snapshot (`widep.widep_round`: step toward the PoI, or an auxiliary PoI beside the obstacle,
at most (R - d+(u)) / 2 so RNG neighbours stay connected), then drive there as unicycles.
The base station (the control node) is part of the network and does not move. Metrics:
time to cover the PoI, connectivity to the base over time, distance travelled and energy
per robot (paper 000's model) by the robot's final position (Figure 11).
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
from numpy.typing import NDArray

from erni.sim import kinematic
from erni.sim.experiments import Experiment, Progress, Result
from erni.sim.experiments.plots import color, draw_world, map_axes, range_circle, time_axes
from erni.sim.scenario import Scenario, ScenarioError
from erni.strategies import energy as paper_energy
from erni.strategies import widep


def run(scenario: Scenario, progress: Progress, *, experiment: Experiment, mode: str | None = None,
        **_: Any) -> Result:
    """Cover the PoI (kinematic WiDep rounds, or real agents given `Deploy widep`); return figure and metrics."""
    if not scenario.poi:
        raise ScenarioError(f"{scenario.name}: the PoI experiment needs a [[poi]] in the scenario")
    s = scenario.strategy
    poi = np.array([scenario.poi[0].x, scenario.poi[0].y])
    R = float(s.get("range", scenario.radio.comm_range))
    tolerance = float(s.get("tolerance", 0.5))
    duration = scenario.duration or 300.0
    names = scenario.robot_names()
    base = np.array([[scenario.control.x, scenario.control.y]])
    obstacles = np.array([[c.center[0], c.center[1], c.radius] for c in scenario.world.circle]).reshape(-1, 3)
    n = len(names)
    battery: list[float] = []  # agents mode: energy each simulated robot's battery gave (J)
    if (mode or experiment.mode) == "agents":
        ts, ps, covered_at, rounds = _agents(scenario, progress, poi, tolerance, duration, battery)
    else:
        ts, ps, covered_at, rounds = _kinematic(scenario, progress, poi, R, tolerance, duration, base, obstacles)
    decisions: list[tuple[float, NDArray[np.float64]]] = []
    res = Result(experiment.name, experiment.title, mode or experiment.mode)
    connected_share = []
    for k in range(len(ts)):
        everyone = np.vstack([ps[k], base])
        connected_share.append(len(kinematic.reach_of(everyone, R, n)) / n)
    res.series["team/connected_to_base"] = (list(ts), connected_share, "share")
    res.series["team/distance_to_poi"] = (list(ts), list(np.min(np.hypot(*(ps - poi).transpose(2, 0, 1)), axis=1)), "m")
    res.metrics["PoI covered at"] = (covered_at if covered_at is not None else math.nan, "s")
    if rounds is not None:
        res.metrics["WiDep rounds"] = (float(rounds), "rounds")
    res.metrics["connected to the base the whole run"] = (float(min(connected_share) == 1.0), "yes=1")
    res.metrics["lowest share connected to the base"] = (min(connected_share), "share")
    res.metrics["closest approach to the obstacle surface"] = (_clearance(ps, obstacles), "m")
    energies = []
    for i, name in enumerate(names):
        e, dist = paper_energy.track_energy(ts, ps[:, i, 0], ps[:, i, 1])
        final_from_base = float(np.hypot(*(ps[-1, i] - base[0])))
        energies.append(e)
        res.robots[name] = {"distance_m": round(dist, 2), "energy_j": round(e, 1),
                            "from_base_m": round(final_from_base, 2)}
        if battery:
            res.robots[name]["battery_j"] = round(battery[i], 1)
    res.metrics["energy, whole team"] = (float(sum(energies)), "J")
    res.notes.append("paper 000 gives no numbers for this run (its Figure 5 shows the trajectories); "
                     f"R = {R:g} m and the PoI ({poi[0]:g}, {poi[1]:g}) are the paper's")
    if covered_at is None:
        res.notes.append(f"the PoI was not covered within {duration:g} s")
    res.draw = lambda fig: _draw(fig, scenario, names, ts, ps, base[0], poi, R, res, decisions, covered_at)
    if (mode or experiment.mode) == "agents":
        res.notes.append("agents mode: each robot's mission plugin ran Deploy widep on what its agent knows")
    return res


def _kinematic(scenario: Scenario, progress: Progress, poi: NDArray[np.float64], R: float, tolerance: float,
               duration: float, base: NDArray[np.float64], obstacles: NDArray[np.float64]
               ) -> tuple[NDArray[np.float64], NDArray[np.float64], float | None, int]:
    """WiDep rounds from one snapshot each `period` s, robots driven as unicycles in between."""
    s = scenario.strategy
    period = float(s.get("period", 4.0))
    speed = float(s.get("speed", 0.3))
    dt = float(s.get("dt", 0.1))
    separation = float(s.get("separation", 0.8))
    starts = scenario.starts()
    pos = np.array([[st.x, st.y] for st in starts])
    th = np.radians([st.heading for st in starts])
    n = len(pos)
    movable = np.r_[np.ones(n, dtype=bool), False]
    track = kinematic.Track()
    track.add(0.0, pos, th, np.zeros(n))
    t = 0.0
    covered_at: float | None = None
    rounds = 0
    while t < duration:
        if widep.covered(pos, poi, tolerance):
            covered_at = t
            break
        everyone = np.vstack([pos, base])
        targets, _ = widep.widep_round(everyone, poi, R, tolerance=tolerance, obstacles=obstacles,
                                       separation=separation, movable=movable)
        rounds += 1
        round_end = t + period
        while t < round_end - 1e-9:
            pos, th, sp = kinematic.drive(pos, th, targets[:n], dt, speed)
            t += dt
            track.add(t, pos, th, sp)
        progress("WiDep rounds", round(t, 1), duration)
    for _ in range(int(5.0 / dt)):  # the team holds its place a little after covering the PoI
        t += dt
        track.add(t, pos, th, np.zeros(n))
    progress("WiDep rounds", duration, duration)
    ts, ps, _, _ = track.arrays()
    return ts, ps, covered_at, rounds


def _agents(scenario: Scenario, progress: Progress, poi: NDArray[np.float64], tolerance: float, duration: float,
            battery: list[float]) -> tuple[NDArray[np.float64], NDArray[np.float64], float | None, None]:
    """Real agents: the scenario's tasks (Deploy widep) through the control node; the simulator records."""
    from erni.sim.team import Team, plugin_available

    if not plugin_available("erni.plugins.mission", "MissionControl"):
        raise ScenarioError("agents mode needs the mission plugin (erni.plugins.mission.MissionControl)")
    if not scenario.task:
        raise ScenarioError(f"{scenario.name}: agents mode sends the scenario's [[task]]s; it has none")
    team = Team(scenario, headless=True, control_port=0, record=True, ui=False, mission=True)
    covered_at: float | None = None
    try:
        team.start(lambda label, done, total: progress(label, done, total), timeout=90)
        t0 = team.elapsed()
        for spec in scenario.task:
            for name in (team.names if spec.to == "all" else [spec.to]):
                team.send_task(name, spec.verb, spec.preposition, **spec.params)
        import time

        while team.elapsed() - t0 < duration:
            time.sleep(0.5)
            progress("robots deploying", round(team.elapsed() - t0), round(duration))
            pos = np.array([[r.x, r.y] for r in team.robots])
            if covered_at is None and widep.covered(pos, poi, tolerance):
                covered_at = team.elapsed() - t0
            if covered_at is not None and team.elapsed() - t0 > covered_at + 5.0:
                break
    finally:
        team.stop()
    samples = [x for x in team.samples if x.t >= t0]
    ts = np.array([x.t - t0 for x in samples])
    ps = np.array([np.stack([x.x, x.y], axis=1) for x in samples])
    battery.extend(b - a for a, b in zip(samples[0].energy, samples[-1].energy))
    return ts, ps, covered_at, None


def _clearance(ps: NDArray[np.float64], obstacles: NDArray[np.float64]) -> float:
    if len(obstacles) == 0:
        return math.nan
    best = math.inf
    for cx, cy, r in obstacles:
        best = min(best, float(np.min(np.hypot(ps[..., 0] - cx, ps[..., 1] - cy) - r)))
    return best


def _draw(fig: Any, scenario: Scenario, names: list[str], ts: NDArray[np.float64], ps: NDArray[np.float64],
          base: NDArray[np.float64], poi: NDArray[np.float64], R: float, res: Result,
          decisions: list[tuple[float, NDArray[np.float64]]], covered_at: float | None) -> None:
    gs = fig.add_gridspec(2, 2, width_ratios=[1.0, 1.1])
    ax = fig.add_subplot(gs[:, 0])
    draw_world(ax, scenario.world)
    for i, name in enumerate(names):
        ax.plot(ps[:, i, 0], ps[:, i, 1], color=color(i), lw=1.8, label=f"{name} trajectory")
        ax.plot(*ps[0, i], "o", color=color(i), mfc="white", ms=7)
        ax.plot(*ps[-1, i], "o", color=color(i), ms=8)
        range_circle(ax, ps[-1, i, 0], ps[-1, i, 1], R, color=color(i), alpha=0.5)
    final = np.vstack([ps[-1], base])
    adj = widep.comm_adjacency(final, R)
    for a in range(len(final)):
        for b in range(a + 1, len(final)):
            if adj[a, b]:
                ax.plot(*zip(final[a], final[b]), color="#555555", lw=0.8, ls="-", alpha=0.6, zorder=1)
    ax.plot(*base, "s", color="black", ms=10, label="base station (control node)")
    ax.plot(*poi, "*", color="#e6a100", ms=18, mec="black", label=f"PoI ({poi[0]:g}, {poi[1]:g})")
    ax.plot([], [], "o", color="grey", mfc="white", label="start")
    ax.plot([], [], "o", color="grey", label="end")
    ax.plot([], [], ls="--", color="grey", label=f"range R = {R:g} m")
    ax.plot([], [], color="#555555", lw=0.8, label="radio link at the end")
    bounds = scenario.world.bounds
    if bounds is not None:
        ax.set_xlim(bounds[0] - 0.5, bounds[2] + 0.5)
        ax.set_ylim(bounds[1] - 0.5, bounds[3] + 0.5)
    map_axes(ax, "Trajectories (WiDep, one obstacle)")
    ax.legend(loc="upper left", fontsize=7.5, framealpha=0.92)
    ax = fig.add_subplot(gs[0, 1])
    t, d, _ = res.series["team/distance_to_poi"]
    ax.plot(t, d, color=color(0), label="closest robot to the PoI")
    t, share, _ = res.series["team/connected_to_base"]
    ax2 = ax.twinx()
    ax2.plot(t, np.array(share) * 100, color=color(2), ls="--", label="robots connected to the base")
    ax2.set_ylabel("robots connected to the base (%)")
    ax2.set_ylim(0, 110)
    if covered_at is not None:
        ax.axvline(covered_at, color="#e6a100", lw=1, label=f"PoI covered at {covered_at:.0f} s")
    time_axes(ax, "Coverage and connectivity over time", "distance to the PoI (m)")
    lines = ax.get_legend_handles_labels()
    more = ax2.get_legend_handles_labels()
    ax.legend(lines[0] + more[0], lines[1] + more[1], loc="center right", fontsize=8)
    ax = fig.add_subplot(gs[1, 1])
    order = sorted(range(len(names)), key=lambda i: res.robots[names[i]]["from_base_m"])
    xs = np.arange(len(order))
    vals = [res.robots[names[i]]["energy_j"] for i in order]
    ax.bar(xs, vals, color=[color(i) for i in order])
    for x, v in zip(xs, vals):
        ax.text(x, v, f"{v:.0f} J", ha="center", va="bottom", fontsize=9)
    ax.set_xticks(xs, [f"{names[i]}\n{res.robots[names[i]]['from_base_m']:.1f} m" for i in order])
    ax.set_xlabel("robot, and its final distance from the base station")
    ax.set_ylabel("energy consumed (J)")
    ax.set_title("Energy by robot position (paper 000's model)")
    ax.grid(True, axis="y", color="#e0e0e0", lw=0.6)
    ax.set_ylim(0, max(vals) * 1.18)
    fig.suptitle(scenario.title, fontsize=13)
