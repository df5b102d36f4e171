"""Paper 000, section 5.3: standby power, the 5 m run (speed and power over time), power by speed.

Agents mode: one robot agent process drives its simulated ARCOS robot, tasked through the
control node exactly as a user would (`BotMotion forward`, `BotMotion velocity`). The
simulator samples the robot's commanded and actual speed and the energy its battery model
draws (paper 000's model), so the experiment measures what the whole stack makes the
robot do: acceleration ramps, the controller's braking, standstill between tasks.
"""

from __future__ import annotations

import time
from typing import Any

import numpy as np
from numpy.typing import NDArray

from erni.sim.experiments import Experiment, Progress, Result
from erni.sim.experiments.plots import color, time_axes
from erni.sim.scenario import Scenario
from erni.sim.team import Sample, Team, TeamError
from erni.strategies import energy as paper


def _window(samples: list[Sample], t0: float, t1: float) -> list[Sample]:
    return [s for s in samples if t0 <= s.t <= t1]


def _mean_power(samples: list[Sample]) -> float:
    if len(samples) < 2:
        raise TeamError("too few samples to measure power")
    return (samples[-1].energy[0] - samples[0].energy[0]) / (samples[-1].t - samples[0].t)


def _steady_power(samples: list[Sample], v: float, tol: float = 0.005) -> tuple[float, int]:
    """Mean power over consecutive sample pairs both at speed `v` (transients between them excluded)."""
    energy = duration = 0.0
    pairs = 0
    for a, b in zip(samples, samples[1:]):
        if abs(a.v[0] - v) < tol and abs(b.v[0] - v) < tol and b.t > a.t:
            energy += b.energy[0] - a.energy[0]
            duration += b.t - a.t
            pairs += 1
    return (energy / duration if pairs >= 2 else float("nan")), pairs


def run(scenario: Scenario, progress: Progress, *, experiment: Experiment, **_: Any) -> Result:
    """Run standby, the 5 m run and the speed sweep on a real agent; return figure and metrics."""
    s = scenario.strategy
    standby = float(s.get("standby", 10.0))
    distance = float(s.get("distance", 5.0))
    speed = float(s.get("speed", 0.5))
    sweep = [float(v) for v in s.get("sweep", [0.1, 0.3, 0.5, 0.7, 0.9])]
    hold = float(s.get("hold", 3.0))
    robot = scenario.robot_names()[0]
    total = 3 + standby + distance / speed + 2 + len(sweep) * (hold + 1.0)
    team = Team(scenario.with_robots(1), headless=True, control_port=0, record=True, feed_hz=20.0,
                mission=False, ui=False)
    t_start = time.monotonic()

    def tick(label: str) -> None:
        progress(label, min(total, round(time.monotonic() - t_start, 1)), round(total))

    try:
        team.start(lambda label, done, n: tick(label), timeout=90)
        time.sleep(1.0)  # let the start-up settle: motors enabled, first poses
        t0 = team.elapsed()
        while team.elapsed() < t0 + standby:
            tick("standby (P0)")
            time.sleep(0.2)
        stand = _window(team.samples, t0, t0 + standby)
        run_t0 = team.elapsed()
        task = team.send_task(robot, "BotMotion", "forward", distance=distance, speed=speed)
        deadline = time.monotonic() + distance / speed * 3 + 10
        while task.uid not in team.results and time.monotonic() < deadline:
            tick(f"{distance:g} m run at {speed:g} m/s")
            try:
                team.wait_result(task.uid, 0.2)
            except TeamError:
                pass
        result = team.wait_result(task.uid, 1.0)
        if result.state.value != "succeeded":
            raise TeamError(f"the {distance:g} m run failed: {result.message}")
        time.sleep(1.0)  # the robot at rest after the run
        run_t1 = team.elapsed()
        levels: list[tuple[float, float, int]] = []  # speed, mean power, samples
        for level in sweep:
            tv0 = team.elapsed()
            task = team.send_task(robot, "BotMotion", "velocity", v=level, w=0.0, duration=hold)
            while task.uid not in team.results:
                tick(f"holding {level:g} m/s")
                try:
                    team.wait_result(task.uid, 0.2)
                except TeamError:
                    if team.elapsed() > tv0 + hold * 4 + 5:
                        raise TeamError(f"velocity {level:g} m/s: no result within {hold * 4 + 5:g} s") from None
            window = _window(team.samples, tv0, team.elapsed())
            power, n = _steady_power(window, level)
            levels.append((level, power, n))
        progress("done", round(total), round(total))
    finally:
        team.stop()
    samples = team.samples
    run_s = _window(samples, run_t0, run_t1)
    p0 = _mean_power(stand)
    ok = [(v, p) for v, p, n in levels if np.isfinite(p)]
    slope, intercept = np.polyfit([v for v, _ in ok], [p for _, p in ok], 1) if len(ok) >= 2 else (np.nan, np.nan)
    t = np.array([x.t for x in run_s]) - run_t0
    v = np.array([x.v[0] for x in run_s])
    tv = np.array([x.target_v[0] for x in run_s])
    e = np.array([x.energy[0] for x in run_s])
    pw = np.gradient(e, t) if len(t) > 2 else np.zeros_like(t)
    x0, y0 = run_s[0].x[0], run_s[0].y[0]
    travelled = float(np.hypot(run_s[-1].x[0] - x0, run_s[-1].y[0] - y0))
    moving = t[np.abs(v) > 1e-3]
    e_run = float(e[-1] - e[0])
    model_run = float(paper.energy(v, float(np.median(np.diff(t)))) if len(t) > 1 else 0.0)
    res = Result(experiment.name, experiment.title, "agents")
    res.metrics["standby power P0"] = (p0, "W")
    res.metrics[f"distance travelled (asked {distance:g} m)"] = (travelled, "m")
    res.metrics["time moving"] = (float(moving[-1] - moving[0]) if len(moving) else 0.0, "s")
    res.metrics["peak speed"] = (float(v.max()) if len(v) else 0.0, "m/s")
    res.metrics["energy of the run window"] = (e_run, "J")
    res.metrics["paper's model on our speed trace"] = (model_run, "J")
    for vv, p, n in levels:
        res.metrics[f"mean power at {vv:g} m/s ({n} samples)"] = (p, "W")
    res.paper += [("standby power P0", p0, paper.P0, "W"),
                  ("Pmov slope (W per m/s)", float(slope), paper.PMOV_SLOPE, "W s/m"),
                  ("Pmov intercept", float(intercept), paper.PMOV_BASE, "W")]
    res.series["robot1/speed"] = (list(t), list(v), "m/s")
    res.series["robot1/commanded_speed"] = (list(t), list(tv), "m/s")
    res.series["robot1/power"] = (list(t), list(pw), "W")
    res.notes.append("our robot's battery follows paper 000's model, so the fit checks that the whole "
                     "stack (tasks, behaviours, ARCOS, physics) drives at the asked speeds")
    res.draw = lambda fig: _draw(fig, t, v, tv, pw, p0, levels, float(slope), float(intercept), speed, distance)
    return res


def _draw(fig: Any, t: NDArray[np.float64], v: NDArray[np.float64], tv: NDArray[np.float64],
          pw: NDArray[np.float64], p0: float, levels: list[tuple[float, float, int]], slope: float,
          intercept: float, speed: float, distance: float) -> None:
    gs = fig.add_gridspec(2, 2, width_ratios=[1.3, 1])
    ax = fig.add_subplot(gs[0, 0])
    ax.plot(t, tv, color=color(1), ls="--", lw=1.5, label="desired (commanded) speed")
    ax.plot(t, v, color=color(0), lw=2, label="actual speed")
    time_axes(ax, f"Speed during the {distance:g} m movement", "speed (m/s)")
    ax.set_ylim(-0.05, max(speed * 1.3, float(v.max()) * 1.15 if len(v) else 1))
    ax.legend(loc="upper right")
    ax = fig.add_subplot(gs[1, 0], sharex=ax)
    ax.plot(t, pw, color=color(2), lw=0.8, alpha=0.35, label="power drawn (each 50 ms sample)")
    if len(t) > 10:
        k = max(1, int(round(0.5 / float(np.median(np.diff(t))))))
        smooth = np.convolve(pw, np.ones(k) / k, mode="same")
        ax.plot(t[k:-k], smooth[k:-k], color=color(2), lw=2, label="power drawn (0.5 s mean)")
    ax.axhline(paper.P0, color="#777777", ls=":", lw=1, label=f"paper P0 = {paper.P0} W")
    pm = paper.PMOV_SLOPE * speed + paper.PMOV_BASE
    ax.axhline(pm, color="#444444", ls="--", lw=1, label=f"paper Pmov({speed:g} m/s) = {pm:.2f} W")
    time_axes(ax, f"Power during the {distance:g} m movement", "power (W)")
    ax.set_ylim(0, pm * 1.35)
    ax.legend(loc="lower center", fontsize=9)
    ax = fig.add_subplot(gs[:, 1])
    vs = np.array([x for x, _, _ in levels])
    ps = np.array([p for _, p, _ in levels])
    grid = np.linspace(0, max(1.0, float(vs.max()) if len(vs) else 1.0), 50)
    ax.plot(grid, paper.PMOV_SLOPE * grid + paper.PMOV_BASE, color="#444444", ls="--",
            label=f"paper: {paper.PMOV_SLOPE} v + {paper.PMOV_BASE} W")
    if np.isfinite(slope):
        ax.plot(grid, slope * grid + intercept, color=color(0), lw=1,
                label=f"ours (fit): {slope:.2f} v + {intercept:.3f} W")
    ax.scatter(vs, ps, color=color(0), zorder=3, label="ours: mean power while holding a speed")
    ax.scatter([0], [p0], color=color(1), marker="s", zorder=3, label=f"ours: standby P0 = {p0:.3f} W")
    ax.scatter([0], [paper.P0], facecolor="none", edgecolor="#444444", marker="o", s=80, zorder=3,
               label=f"paper: P0 = {paper.P0} W")
    ax.set_xlabel("speed (m/s)")
    ax.set_ylabel("average power (W)")
    ax.set_title("Average power by speed")
    ax.grid(True, color="#e0e0e0", lw=0.6)
    ax.set_ylim(0, None)
    ax.legend(loc="lower right", fontsize=9)
    fig.suptitle("Paper 000, energy: speed and power of a robot agent driving its simulated robot", fontsize=13)
