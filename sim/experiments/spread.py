"""Paper 001: potential-field self-deployment of 120 robots, open field and corridor, at t = 30 s.

Kinematic mode: the mission's `potential.spread_step` (equations 15 and 16) moves every
robot each dt = 0.2 s, for each variant the paper shows (holonomic or nonholonomic robots,
physical or Delaunay neighbourhood). Metrics per variant: mean nearest-neighbour distance,
spread (bounding box), area covered by sensing discs, share of robots in the largest radio
component over time, convergence time (all speeds below a threshold) and energy per robot
from paper 000's model applied to each track.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
from numpy.typing import NDArray

from erni.sim import kinematic
from erni.sim.experiments import Experiment, Progress, Result
from erni.sim.experiments.plots import color, draw_world, headings, map_axes, time_axes
from erni.sim.scenario import Scenario, ScenarioError
from erni.strategies import energy as energy_model
from erni.strategies.potential import SpreadConfig, mean_nn_distance, spread_step

VARIANTS = ["holonomic/physical", "holonomic/delaunay", "nonholonomic/physical", "nonholonomic/delaunay"]


def _config(scenario: Scenario, variant: str) -> SpreadConfig:
    s = scenario.strategy
    model, _, neighbourhood = variant.partition("/")
    return SpreadConfig(distance=float(s.get("distance", 5.0)), gain=float(s.get("gain", 2.0)),
                        dt=float(s.get("dt", 0.2)), range=float(s.get("range", 6.0)),
                        obstacle_distance=float(s.get("obstacle_distance", 2.0)),
                        wall_distance=float(s.get("wall_distance", 2.5)),
                        neighbourhood=neighbourhood, model=model)


def _obstacles(scenario: Scenario) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    walls = np.array([[a[0], a[1], b[0], b[1]] for a, b in scenario.world.segments()], dtype=float).reshape(-1, 4)
    circles = np.array([[c.center[0], c.center[1], c.radius] for c in scenario.world.circle],
                       dtype=float).reshape(-1, 3)
    return circles, walls


def run(scenario: Scenario, progress: Progress, *, experiment: Experiment, variants: list[str] | None = None,
        **_: Any) -> Result:
    """Run every variant for the scenario's duration (default 30 s); return figure and metrics."""
    variants = variants or list(scenario.strategy.get("variants", VARIANTS))
    for v in variants:
        if v not in VARIANTS:
            raise ScenarioError(f"strategy.variants: unknown variant {v!r}; expected some of {', '.join(VARIANTS)}")
    duration = scenario.duration or 30.0
    starts = scenario.starts()
    pos0 = np.array([[s.x, s.y] for s in starts])
    th0 = np.radians([s.heading for s in starts])
    circles, walls = _obstacles(scenario)
    sensing = float(scenario.strategy.get("sensing", 2.5))
    R = scenario.radio.comm_range
    threshold = float(scenario.strategy.get("still_speed", 0.05))
    res = Result(experiment.name, experiment.title, "kinematic")
    tracks: dict[str, kinematic.Track] = {}
    converged: dict[str, bool] = {}  # variant -> every robot came to rest
    total = 0
    cfgs = {v: _config(scenario, v) for v in variants}
    steps = {v: int(round(duration / cfgs[v].dt)) for v in variants}
    all_steps = sum(steps.values())
    for v in variants:
        cfg = cfgs[v]
        pos, th = pos0.copy(), th0.copy()
        vel, om = np.zeros_like(pos), np.zeros(len(pos))
        track = kinematic.Track()
        track.add(0.0, pos, th, np.zeros(len(pos)))
        for k in range(steps[v]):
            new, th, vel, om = spread_step(pos, th, vel, om, cfg, circles, walls)
            stop = kinematic.blocked_by_walls(pos, new, walls)  # walls are solid: a robot stops at them
            pos = np.where(stop[:, None], pos, new)
            vel[stop] = 0.0
            track.add((k + 1) * cfg.dt, pos, th, np.hypot(vel[:, 0], vel[:, 1]))
            total += 1
            if total % 5 == 0 or total == all_steps:
                progress(v, total, all_steps)
        tracks[v] = track
        t, p, _th, sp = track.arrays()
        share = [kinematic.largest_share(p[i], R) for i in range(0, len(t), 5)]
        res.series[f"{v}/largest_component"] = (list(t[::5]), share, "share")
        res.series[f"{v}/mean_nn_distance"] = (list(t[::5]), [mean_nn_distance(p[i]) for i in range(0, len(t), 5)], "m")
        final = p[-1]
        energies = [energy_model.track_energy(t, p[:, i, 0], p[:, i, 1])[0] for i in range(p.shape[1])]
        conv = kinematic.convergence_time(t, sp, threshold)
        converged[v] = conv is not None
        res.metrics[f"{v}: mean NN distance at t={duration:g}"] = (mean_nn_distance(final), "m")
        res.metrics[f"{v}: spread x * y"] = (float(np.ptp(final[:, 0])) * float(np.ptp(final[:, 1])), "m^2")
        res.metrics[f"{v}: area covered (r={sensing:g} m)"] = (kinematic.coverage(final, sensing), "m^2")
        res.metrics[f"{v}: largest component (R={R:g} m)"] = (share[-1], "share")
        res.metrics[f"{v}: convergence (v<{threshold:g} m/s)"] = (conv if conv is not None else math.nan, "s")
        res.metrics[f"{v}: energy per robot, mean"] = (float(np.mean(energies)), "J")
        res.metrics[f"{v}: energy per robot, max"] = (float(np.max(energies)), "J")
        for i, e in enumerate(energies):
            res.robots.setdefault(starts[i].name, {})[f"{v} energy_j"] = round(e, 2)
    res.paper.append(("desired distance d", cfgs[variants[0]].distance, 5.0, "m"))
    if not all(converged.values()):
        res.notes.append(f"convergence NaN: some robot still moved faster than {threshold:g} m/s at the end")
    res.notes.append(f"kinematic mode: {len(pos0)} robots stepped in-process by the mission's spread_step "
                     f"(neighbourhood range {cfgs[variants[0]].range:g} m)")
    res.draw = lambda fig: _draw(fig, scenario, tracks, res, duration, pos0)
    return res


def _draw(fig: Any, scenario: Scenario, tracks: dict[str, kinematic.Track], res: Result, duration: float,
          pos0: NDArray[np.float64]) -> None:
    gs = fig.add_gridspec(2, 3, width_ratios=[1, 1, 0.9])
    extent = max(float(np.abs(tr.pos[-1]).max()) for tr in tracks.values()) + 3
    for k, (v, track) in enumerate(tracks.items()):
        ax = fig.add_subplot(gs[k // 2, k % 2])
        draw_world(ax, scenario.world)
        final = track.pos[-1]
        ax.scatter(pos0[:, 0], pos0[:, 1], s=6, color="#bbbbbb", label="start (t = 0)", zorder=3)
        ax.scatter(final[:, 0], final[:, 1], s=14, color=color(k), label=f"t = {duration:g} s", zorder=4)
        headings(ax, final, track.th[-1], 1.8, color=color(k), zorder=4)
        ax.set_xlim(-extent, extent)
        ax.set_ylim(-extent, extent)
        map_axes(ax, f"{v.replace('/', ', ')} neighbourhood")
        ax.legend(loc="upper right", fontsize=8, framealpha=0.9)
    ax = fig.add_subplot(gs[0, 2])
    for k, v in enumerate(tracks):
        t, vals, _ = res.series[f"{v}/mean_nn_distance"]
        ax.plot(t, vals, color=color(k), label=v.replace("/", ", "))
    d = scenario.strategy.get("distance", 5.0)
    ax.axhline(d, color="#555555", ls=":", lw=1, label=f"desired d = {d:g} m")
    time_axes(ax, "Mean distance to the nearest robot", "distance (m)")
    ax.set_ylim(0, d * 1.15)
    ax.legend(fontsize=8, loc="lower right")
    ax = fig.add_subplot(gs[1, 2])
    for k, v in enumerate(tracks):
        t, vals, _ = res.series[f"{v}/largest_component"]
        ax.plot(t, np.array(vals) * 100, color=color(k), label=v.replace("/", ", "))
    time_axes(ax, f"Connectivity (radio range R = {scenario.radio.comm_range:g} m)",
              "robots in the largest component (%)")
    ax.set_ylim(0, 105)
    ax.legend(fontsize=8, loc="lower left")
    fig.suptitle(f"{scenario.title}: the team at t = {duration:g} s (start: grey square)", fontsize=13)
