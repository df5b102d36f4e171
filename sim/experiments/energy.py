"""Paper 000, section 5.3: standby, the 5 m run (speed and power over time), power by speed.

One robot agent process drives its simulated ARCOS robot, tasked through the control node
exactly as a user would (`BotMotion forward`, `BotMotion velocity`). Everything measured is
what the agent itself sees through its driver: the experiment leases a watch from the robot's
agent and keeps the Poses it publishes (odometry: position and wheel speed; the battery
voltage of each SIP). Energy comes from that stream in two independent ways:

- odometry: paper 000's model (P0 standing, Pmov = 11.55 v + 14.838 W moving) applied to the
  speeds the agent measured, sample by sample;
- battery: the fall of the voltage the robot reports (0.1 V steps, the ARCOS field's
  resolution), times the pack's joules per volt.

What this can validate: that the whole stack (tasks, behaviours, ARCOS, the robot's speed
controller) drives at the asked speeds and distances, how the controller's ramps and braking
shape the run (Figure 9), and that the agent's two energy readings agree. What it cannot:
the power constants themselves. The simulated robot's battery is drained by paper 000's own
model, so P0 and Pmov are inputs of this simulation and any fit of them returns them; they are
shown as inputs. The simulated pack is small (`battery_wh`, an input) so its 0.1 V readings
resolve the run at all: a real 100 Wh pack moves 0.1 V per 18 kJ.

Durations: the scenario's are short (standby 10 s, each sweep speed held 3 s: about a minute
in all). `paper_durations` (`erni experiment energy --paper-durations`, on demand: about 30
minutes) holds them as paper 000 does, standby 600 s and each sweep speed 120 s, on a pack of
`PAPER_BATTERY_WH` (the scenario's 0.5 Wh would run empty: the run then takes about 28 kJ). Held
that long in a straight line the sweep would drive 540 m, far out of the control node's radio
range (30 m), so at the paper's durations the robot holds each speed on a circle of
`PAPER_RADIUS` m (turning at v / r); the paper's model, and the simulated battery, count the
speed only.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from erni.sim.experiments import Experiment, Progress, Result
from erni.sim.experiments.agents import PoseSample, TeamRun
from erni.sim.experiments.plots import color, time_axes
from erni.sim.scenario import Scenario, ScenarioError
from erni.strategies import energy as paper


def _odometry_energy(poses: list[PoseSample]) -> float:
    """Paper 000's model over the agent's own speed samples (J), each held until the next."""
    if len(poses) < 2:
        return 0.0
    st = np.array([p.stamp for p in poses])
    v = np.array([p.v for p in poses])
    return float((paper.power(v[:-1]) * np.diff(st)).sum())


PAPER_STANDBY = 600.0  # s standing still (paper 000, 5.3)
PAPER_HOLD = 120.0  # s each sweep speed is held (paper 000, 5.3)
PAPER_BATTERY_WH = 10.0  # the simulated pack at the paper's durations: 15 readings of 0.1 V over the run
PAPER_RADIUS = 4.0  # m: the circle each speed is held on at the paper's durations (in radio range)


def plan(strategy: dict[str, Any], paper_durations: bool = False) -> dict[str, Any]:
    """Standby, run, sweep and pack of the experiment: the scenario's, or the paper's durations."""
    p: dict[str, Any] = {"standby": float(strategy.get("standby", 10.0)), "distance": float(strategy.get("distance", 5.0)),
         "speed": float(strategy.get("speed", 0.5)),
         "sweep": [float(v) for v in strategy.get("sweep", [0.1, 0.3, 0.5, 0.7, 0.9])],
         "hold": float(strategy.get("hold", 3.0)), "battery_wh": float(strategy.get("battery_wh", 0.5)),
         "radius": None}
    if paper_durations:
        p.update(standby=PAPER_STANDBY, hold=PAPER_HOLD, battery_wh=max(p["battery_wh"], PAPER_BATTERY_WH),
                 radius=PAPER_RADIUS)
    return p


def _window(poses: list[PoseSample], t0: float, t1: float) -> list[PoseSample]:
    return [p for p in poses if t0 <= p.t <= t1]


@dataclass
class _Drive:
    """What one agent did in the experiment: every Pose it published, when each phase began (team clock)
    and each sweep speed's hold (asked, start, end)."""

    poses: list[PoseSample]
    t_stand: float
    t_run: float
    t_run_end: float
    levels: list[tuple[float, float, float]]


def run(scenario: Scenario, progress: Progress, *, experiment: Experiment, mode: str,
        paper_durations: bool = False, **_: Any) -> Result:
    """Run standby, the 5 m run and the speed sweep on a real agent; return figure and metrics."""
    p = plan(scenario.strategy, paper_durations)
    standby, distance, speed, hold, battery_wh = p["standby"], p["distance"], p["speed"], p["hold"], p["battery_wh"]
    radius: float | None = p["radius"]
    drive = _drive(scenario, progress, p)
    poses, t_run, levels = drive.poses, drive.t_run, drive.levels
    stand = _window(poses, drive.t_stand, t_run)
    run_p = _window(poses, t_run, drive.t_run_end)
    if len(stand) < 3 or len(run_p) < 5:
        raise ScenarioError(f"too few Poses from the agent ({len(stand)} standing, {len(run_p)} in the run)")
    res = Result(experiment.name, experiment.title, mode)
    res.mode_note = ("one robot agent process tasked through the control node; every number below comes from the "
                     "Poses its agent published (odometry and battery), leased through a watch")
    t = np.array([p.t for p in run_p]) - t_run
    v = np.array([p.v for p in run_p])
    moving = t[np.abs(v) > 1e-3]
    travelled = float(np.hypot(run_p[-1].x - run_p[0].x, run_p[-1].y - run_p[0].y))
    rise = next((float(tt) for tt, vv in zip(t, v) if vv >= 0.9 * speed), math.nan)
    first_move = float(moving[0]) if len(moving) else math.nan
    e_run = _odometry_energy(run_p)
    e_ideal = paper.PMOV_SLOPE * distance + paper.PMOV_BASE * distance / speed  # an instant step to `speed`
    res.metrics[f"distance travelled by odometry (asked {distance:g} m)"] = (travelled, "m")
    res.metrics["time moving"] = (float(moving[-1] - moving[0]) if len(moving) else 0.0, "s")
    res.metrics[f"rise time to 90 % of {speed:g} m/s (from the task being sent)"] = (rise, "s")
    res.metrics["peak speed"] = (float(v.max()), "m/s")
    res.metrics["run energy: paper's model on the agent's odometry"] = (e_run, "J")
    res.metrics["run energy: paper's model on an instant step to the asked speed"] = (e_ideal, "J")
    sweep_rows = _sweep_metrics(res, poses, levels)
    batt = [(p.t, float(p.battery)) for p in poses if p.battery is not None]
    whole = _odometry_energy(poses)
    per_volt = battery_wh * 3600.0 / 2.0  # the simulated pack: 13.0 V full, 11.0 V empty (inputs)
    e_batt = (batt[0][1] - batt[-1][1]) * per_volt if len(batt) > 1 else math.nan
    res.metrics["whole experiment: energy from odometry (model)"] = (whole, "J")
    res.metrics["whole experiment: energy from the battery readings"] = (e_batt, "J")
    res.metrics["battery reading step (0.1 V)"] = (0.1 * per_volt, "J")
    res.series["robot1/speed"] = (list(t), list(v), "m/s")
    res.series["robot1/power_model_on_odometry"] = (list(t), list(paper.power(v)), "W")
    res.series["robot1/battery"] = ([b[0] for b in batt], [float(b[1]) for b in batt], "V")
    _input_rows(res, standby, hold, battery_wh, radius if paper_durations else None)
    res.compare(f"{distance:g} m run at {speed:g} m/s: distance", f"{distance:g}", round(travelled, 3), "m",
                "odometry of the agent's Poses, start to rest")
    res.compare("speed follows the desired speed", "with the controller's lag (Fig. 9)",
                f"90 % after {rise:.2f} s", "s", f"first odometry speed >= {0.9 * speed:g} m/s after the task "
                f"was sent (wheels first turned after {first_move:.2f} s)")
    res.compare("run energy", "not stated (Fig. 9: power)", round(e_run, 1), "J",
                f"model on the agent's odometry speeds; an instant step would give {e_ideal:.1f} J")
    res.compare("energy: odometry and battery agree", "yes (\"highly correlated\", Fig. 11)",
                f"{whole:.0f} J vs {e_batt:.0f} J", "J",
                f"whole experiment; the battery reads in steps of {0.1 * per_volt:.0f} J")
    res.notes.append("what this validates: the stack drives at the asked speeds and distances, and the "
                     "agent's two energy readings agree; it cannot validate P0 and Pmov, which are inputs")
    whole_t = np.array([p.t for p in poses]) - t_run
    whole_v = np.array([p.v for p in poses])
    asked = [(0.0, speed, float(moving[-1]) if len(moving) else float(t[-1]))]
    asked += [(a - t_run, level, b - t_run) for level, a, b in levels]
    res.draw = lambda fig: _draw(fig, t, v, speed, distance, sweep_rows, batt, t_run, whole_t, whole_v, asked)
    return res


def _drive(scenario: Scenario, progress: Progress, p: dict[str, Any]) -> _Drive:
    """One robot agent through standby, the run and the speed sweep, its Poses watched throughout."""
    distance, speed, hold = p["distance"], p["speed"], p["hold"]
    radius: float | None = p["radius"]
    robot = scenario.robot_names()[0]
    team = TeamRun(scenario.with_robots(1), progress, use_mission=False, feed_hz=20.0,
                   robot={"battery_wh": p["battery_wh"]})
    levels: list[tuple[float, float, float]] = []  # asked, start, end (team clock)
    with team.start():
        team.watch(robot)
        team.wait("first poses", 10.0, lambda: len(team.poses) > 5)
        if not team.poses:
            raise ScenarioError(f"{robot}: its agent published no Pose within 10 s")
        t_stand = team.now
        team.wait("standby (P0)", p["standby"])
        t_run = team.now
        uid = team.send(robot, "BotMotion", "forward", distance=distance, speed=speed)
        team.wait(f"{distance:g} m at {speed:g} m/s", distance / speed * 3 + 10, lambda: team.final(uid) is not None)
        r = team.final(uid)
        if r is None or r.state.value != "succeeded":
            raise ScenarioError(f"the {distance:g} m run did not succeed: {r.message if r else 'no result'}")
        team.wait("at rest after the run", 1.5)
        t_run_end = team.now
        for level in p["sweep"]:
            t0 = team.now
            turn = math.degrees(level / radius) if radius else 0.0  # deg/s: on a circle at the paper's durations
            held = team.send(robot, "BotMotion", "velocity", v=level, w=turn, duration=hold)
            team.wait(f"holding {level:g} m/s", hold * 4 + 5, lambda: team.final(held) is not None)  # noqa: B023
            levels.append((level, t0, team.now))
        team.wait("at rest", 1.0)
        poses = list(team.poses)
    return _Drive(poses, t_stand, t_run, t_run_end, levels)


def _sweep_metrics(res: Result, poses: list[PoseSample], levels: list[tuple[float, float, float]]
                   ) -> list[tuple[float, float, float, int]]:
    """Each sweep speed's mean odometry speed (a metric) and the model's power while steady at it:
    rows of (asked, mean speed, mean power, steady samples)."""
    sweep_rows = []
    for level, a, b in levels:
        win = _window(poses, a, b)
        steady = [p.v for p in win if abs(p.v - level) < 0.05 * max(level, 0.1)]
        mean_v = float(np.mean([p.v for p in win if p.v > 0.5 * level])) if win else math.nan
        p_mean = float(np.mean(paper.power(np.array(steady)))) if steady else math.nan
        sweep_rows.append((level, mean_v, p_mean, len(steady)))
        res.metrics[f"asked {level:g} m/s: mean odometry speed while moving"] = (mean_v, "m/s")
    return sweep_rows


def _input_rows(res: Result, standby: float, hold: float, battery_wh: float, radius: float | None) -> None:
    """The comparison's rows of inputs: the power model, the durations (on a circle of `radius` m at the
    paper's), the pack."""
    res.compare("standby power P0", paper.P0, paper.P0, "W", "the simulated battery is drained by paper 000's "
                "model: an input, not a finding", "input")
    res.compare("moving power Pmov", f"{paper.PMOV_SLOPE} v + {paper.PMOV_BASE}",
                f"{paper.PMOV_SLOPE} v + {paper.PMOV_BASE}", "W", "the same model drains the simulated battery",
                "input")
    res.compare("standby; each sweep speed held", "600 s; 120 s", f"{standby:g} s; {hold:g} s", "",
                f"the paper's durations (--paper-durations), each speed on a circle of {radius:g} m"
                if radius else
                "the scenario's, short (--paper-durations: the paper's)", "input")
    res.compare("battery pack / reading resolution", "Wifibot pack, power from the motor driver",
                f"{battery_wh:g} Wh / 0.1 V", "", "chosen so 0.1 V steps resolve the run", "input")


def _draw(fig: Any, t: NDArray[np.float64], v: NDArray[np.float64], speed: float, distance: float,
          sweep: list[tuple[float, float, float, int]], batt: list[tuple[float, float]], t_run: float,
          whole_t: NDArray[np.float64] | None = None, whole_v: NDArray[np.float64] | None = None,
          asked: list[tuple[float, float, float]] | None = None) -> None:
    """Left: the whole experiment on one time axis (0 = the 5 m task sent; standby before it, the
    sweep after): speed, the model's power on it, the battery readings. Right: the 5 m run close
    up (the lag of paper 000's Fig. 9), and the sweep's asked against measured speed."""
    wt = t if whole_t is None else whole_t
    wv = v if whole_v is None else whole_v
    gs = fig.add_gridspec(3, 2, width_ratios=[1.35, 1])
    top = fig.add_subplot(gs[0, 0])
    for k, (a, level, b) in enumerate(asked or []):
        top.plot([a, a, b, b], [0, level, level, 0], color=color(1), ls="--", lw=1.2,
                 label="desired speed (the tasks')" if k == 0 else None)
    top.plot(wt, wv, color=color(0), lw=1.2, label="actual speed (the agent's odometry)")
    time_axes(top, "Speed: standby, the 5 m run, the sweep", "speed (m/s)")
    top.legend(loc="upper left", fontsize=8)
    mid = fig.add_subplot(gs[1, 0], sharex=top)
    mid.plot(wt, paper.power(wv), color=color(2), lw=1.2, label="paper 000's model on the odometry speed")
    mid.axhline(paper.P0, color="#777777", ls=":", lw=1, label=f"P0 = {paper.P0} W (input)")
    time_axes(mid, "Power (the model on the measured speed)", "power (W)")
    mid.set_ylim(0, float(paper.power(np.array([max(float(wv.max()), speed)]))[0]) * 1.25)
    mid.legend(loc="upper left", fontsize=8)
    low = fig.add_subplot(gs[2, 0], sharex=top)
    low.step([b[0] - t_run for b in batt], [b[1] for b in batt], where="post", color=color(3), lw=1.5)
    time_axes(low, "Battery voltage the agent read (0.1 V steps)", "battery (V)")
    low.set_xlabel("time from the 5 m task (s)")
    for ax in (top, mid):
        ax.set_xlabel("")
        ax.tick_params(labelbottom=False)
    ax = fig.add_subplot(gs[0:2, 1])
    moving = t[np.abs(v) > 1e-3]
    end = float(moving[-1]) if len(moving) else float(t[-1])
    ax.step([0, 0, end, end, t[-1]], [0, speed, speed, 0, 0], where="post", color=color(1), ls="--", lw=1.5,
            label="desired speed (the task's)")
    ax.plot(t, v, color=color(0), lw=2, label="actual speed (odometry)")
    time_axes(ax, f"The {distance:g} m run close up", "speed (m/s)")
    ax.set_xlabel("time from the 5 m task (s)")
    ax.set_ylim(-0.05, max(speed * 1.3, float(v.max()) * 1.15 if len(v) else 1))
    ax.legend(loc="lower center", fontsize=8)
    ax = fig.add_subplot(gs[2, 1])
    asked_v = np.array([row[0] for row in sweep])
    got = np.array([row[1] for row in sweep])
    ax.plot([0, asked_v.max() * 1.05], [0, asked_v.max() * 1.05], color="#999999", ls=":", lw=1, label="asked = got")
    ax.plot(asked_v, got, "o-", color=color(0), label="mean speed while moving")
    ax.set_xlabel("asked speed (m/s)")
    ax.set_ylabel("measured (m/s)")
    ax.set_title("Speed sweep: asked against measured")
    ax.grid(True, color="#e0e0e0", lw=0.6)
    ax.legend(fontsize=8, loc="upper left")
    for a in fig.axes:
        a.title.set_size(10)
    fig.suptitle("Paper 000, energy: speed and power of a robot agent driving its simulated robot (agents mode)",
                 fontsize=12)
