"""The papers' experiments: each runs a scenario headless and returns its figure and metrics.

`EXPERIMENTS` maps an experiment name to its runner; `run(name, ...)` returns a `Result`
with scalar metrics, per-robot totals, time series, and a table of the paper's numbers
beside ours, each row saying how ours was obtained and whether it is a measurement or an
input of the simulation. `Result.plot(path)` draws the paper's figure with that table under
it (matplotlib, Agg) and `Result.write_csv(path)` writes every number in tidy form
(`section, t, robot, quantity, value, unit`).
"""

from __future__ import annotations

import csv
import importlib
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

from erni.sim.scenario import ScenarioError

if TYPE_CHECKING:
    from erni.sim.scenario import Scenario

Progress = Callable[[str, float, float], None]


AGENT_ROBOTS = 12  # the largest team this 2-core machine runs as one agent process per robot


@dataclass(frozen=True)
class Experiment:
    """One experiment: its scenario (`examples/scenario-NAME.toml`), paper, modes and runner.

    `modes` lists what it can run on: "agents" (real agent processes: the control node tasks
    them through the transport, robots through ARCOS, the network through MobiNet) and/or
    "kinematic" (the strategies' pure functions stepped in one process, for teams too large
    for one process per robot). The default is "agents" whenever the experiment offers it and
    the team has at most `AGENT_ROBOTS` robots.
    """

    name: str
    scenario: str
    paper: str
    title: str
    modes: tuple[str, ...]
    module: str
    seeds: bool = False  # repeats itself over several seeds (`seeds` option)
    netns: bool = False  # runs its teams on the real-mesh tier too (`netns` option)
    paper_durations: bool = False  # can run at the paper's (long) durations (`paper_durations` option)

    def default_mode(self, scenario: Scenario | None = None) -> str:
        """"agents" where offered and the team is small enough, else the other mode."""
        small = scenario is None or scenario.count <= AGENT_ROBOTS
        if "agents" in self.modes and (small or len(self.modes) == 1):
            return "agents"
        return next(m for m in self.modes if m != "agents")

    def runner(self) -> Callable[..., Result]:
        """The module's `run(scenario, progress, *, experiment, mode, **options) -> Result`."""
        runner: Callable[..., Result] = importlib.import_module(f"erni.sim.experiments.{self.module}").run
        return runner


EXPERIMENTS: dict[str, Experiment] = {e.name: e for e in [
    Experiment("energy", "energy", "000", "5 m run: speed and power; standby and moving power",
               ("agents",), "energy", paper_durations=True),
    Experiment("poi", "poi", "000", "PoI coverage by three robots around an obstacle (WiDep)",
               ("agents", "kinematic"), "poi", seeds=True),
    Experiment("relay1", "relay1", "000", "one robot relaying between a source and a destination",
               ("agents", "kinematic"), "relay", netns=True),
    Experiment("relay2", "relay2", "000", "two robots relaying between a source and a destination",
               ("agents", "kinematic"), "relay", netns=True),
    Experiment("relay-video", "relay-video", "000", "video through one relay: loss and delay against its position "
               "(Figure 6)", ("transport",), "relayvideo", netns=True),
    Experiment("spread-open", "spread-open", "001", "robots spreading in an open field until they settle",
               ("agents", "kinematic"), "spread", seeds=True),
    Experiment("spread-corridor", "spread-corridor", "001",
               "robots spreading in a corridor (walls at y = +-15 m) until they settle", ("agents", "kinematic"),
               "spread", seeds=True),
    Experiment("spread-paths", "spread-paths", "001", "paths of 12 robots, holonomic and nonholonomic (Figs 6-7)",
               ("agents", "kinematic"), "spread", seeds=True),
    Experiment("territory", "territory", "002", "six territories; one robot fails and is taken over",
               ("agents", "kinematic"), "territory"),
    Experiment("roundtrip", "roundtrip", "002", "sensor data and images from one robot to 1-5 consumers: round "
               "trip (Table II)", ("agents",), "roundtrip", netns=True),
    Experiment("response", "response", "003", "motor command to odometry: raw, poll, notify (Table I)",
               ("agents",), "response"),
    Experiment("memory", "memory", "004", "resident memory of a robot agent and a robot's processes (Table 1)",
               ("agents",), "memory"),
    Experiment("netaware", "netaware", "004", "the mission's network guard on against off: the same team, "
               "tasks and seeds", ("agents",), "netaware", seeds=True, netns=True),
]}


@dataclass(frozen=True)
class Compare:
    """One row of an experiment's table: what the paper states beside what we measured, and how.

    `kind` is "measured" (a result of this run), "input" (a setting of the simulation or of the
    strategy: shown for reference, never a finding) or "none" (the paper states no number).
    """

    quantity: str
    paper: float | str
    ours: float | str
    unit: str = ""
    how: str = ""
    kind: str = "measured"


@dataclass
class Result:
    """What an experiment measured, and how to draw it."""

    name: str
    title: str
    mode: str
    metrics: dict[str, tuple[float | str, str]] = field(default_factory=dict)  # name -> (value or robot, unit)
    robots: dict[str, dict[str, float | str]] = field(default_factory=dict)  # robot -> quantity -> value
    series: dict[str, tuple[list[float], list[float], str]] = field(default_factory=dict)  # t, v, unit
    rows: list[Compare] = field(default_factory=list)  # the paper beside ours
    notes: list[str] = field(default_factory=list)
    mode_note: str = ""  # how the robots ran (shown in the figure)
    draw: Callable[[Any], None] | None = None  # draws the figure on a matplotlib Figure
    figure_height: float = 7.5  # inches the drawing takes (the table comes under it)

    def compare(self, quantity: str, paper: float | str, ours: float | str, unit: str = "", how: str = "",
                kind: str = "measured") -> None:
        """Add a row to the paper-vs-ours table."""
        self.rows.append(Compare(quantity, paper, ours, unit, how, kind))

    def report(self) -> str:
        """The metrics as text, then the paper's numbers beside ours with how ours were obtained."""
        lines = [f"{self.name}: {self.title} ({self.mode} mode)"]
        if self.mode_note:
            lines.append(f"  {self.mode_note}")
        for key, (value, unit) in self.metrics.items():
            lines.append(f"  {key:<52} {_fmt(value):>12} {unit}")
        if len(self.robots) > 12:
            lines.append(f"  per-robot values of {len(self.robots)} robots: see the CSV (--csv)")
        elif self.robots:
            quantities = list(dict.fromkeys(q for values in self.robots.values() for q in values))
            width = max(12, *(len(q) + 2 for q in quantities))
            lines.append("  " + f"{'robot':<10}" + "".join(f"{q:>{width}}" for q in quantities))
            for robot, values in self.robots.items():
                cells = [values.get(q, "") for q in quantities]
                lines.append("  " + f"{robot:<10}" + "".join(f"  {v}" if isinstance(v, str) else f"{_fmt(v):>{width}}"
                                                           for v in cells))
        if self.rows:
            lines.append(f"  {'quantity':<46} {'paper':>20} {'ours':>20}  unit   how ours was obtained")
            for r in self.rows:
                tag = " (input)" if r.kind == "input" else ""
                lines.append(f"  {r.quantity + tag:<46} {_fmt(r.paper):>20} {_fmt(r.ours):>20}  {r.unit:<6} {r.how}")
        lines += [f"  note: {n}" for n in self.notes]
        return "\n".join(lines)

    def plot(self, path: str | Path) -> None:
        """Draw the figure, with the paper-vs-ours table under it, into `path` (PNG, SVG or PDF)."""
        import matplotlib

        matplotlib.use("Agg")
        from matplotlib.figure import Figure

        from erni.sim.experiments.plots import draw_table, table_lines

        if self.draw is None:
            raise ScenarioError(f"{self.name}: this experiment draws no figure")
        table = 0.6 + 0.2 * table_lines(self.rows) if self.rows else 0.0
        fig = Figure(figsize=(13, self.figure_height + table), dpi=110, layout="constrained")
        note = f"{self.mode} mode: {self.mode_note}" if self.mode_note else f"{self.mode} mode"
        if self.rows:
            subs: Any = fig.subfigures(2, 1, height_ratios=[self.figure_height, table])
            top, bottom = subs[0], subs[1]
            self.draw(top)
            draw_table(bottom, self.rows, note)
        else:
            self.draw(fig)
            fig.text(0.002, 0.002, note, fontsize=8, color="#444444", ha="left", va="bottom")
        fig.savefig(path)

    def write_csv(self, path: str | Path) -> None:
        """Write every number: section, t, robot, quantity, value, unit."""
        with open(path, "w", newline="", encoding="utf-8") as f:
            w = csv.writer(f)
            w.writerow(["section", "t", "robot", "quantity", "value", "unit"])
            for key, (value, unit) in self.metrics.items():
                w.writerow(["metric", "", "", key, value, unit])
            for robot, values in self.robots.items():
                for q, value in values.items():
                    w.writerow(["robot", "", robot, q, value, ""])
            for key, (ts, vs, unit) in self.series.items():
                robot, _, quantity = key.rpartition("/")
                for t, v in zip(ts, vs):
                    w.writerow(["series", round(t, 3), robot, quantity, v, unit])
            for r in self.rows:
                w.writerow(["paper", "", "", r.quantity, r.paper, r.unit])
                w.writerow(["input" if r.kind == "input" else "ours", "", "", r.quantity, r.ours, r.unit])


def _fmt(v: float | str) -> str:
    if isinstance(v, float):
        return f"{v:.4g}" if abs(v) < 1e5 else f"{v:.0f}"
    return str(v)


def run(name: str, scenario: Scenario, progress: Progress | None = None, **options: Any) -> Result:
    """Run experiment `name` on `scenario`; `progress(label, done, total)` hears how far it got.

    `mode` (an option) picks the mode; without it the experiment's default for this team.
    """
    exp = EXPERIMENTS[name]
    mode = options.pop("mode", None) or exp.default_mode(scenario)
    if mode not in exp.modes:
        raise ScenarioError(f"{name} runs in {' or '.join(exp.modes)} mode, not {mode!r}")
    if "seeds" in options and not exp.seeds:
        raise ScenarioError(f"{name} runs one seed at a time; it has no seeds option")
    if options.get("netns") and not exp.netns:
        raise ScenarioError(f"{name} runs on the loopback tier only; it has no netns option")
    if options.get("paper_durations") and not exp.paper_durations:
        raise ScenarioError(f"{name} has no paper_durations option: it runs at the paper's durations already")
    if not options.get("paper_durations"):
        options.pop("paper_durations", None)
    if not options.get("netns"):
        options.pop("netns", None)  # the loopback tier is every experiment's default
    return exp.runner()(scenario, progress or (lambda *a: None), experiment=exp, mode=mode, **options)
