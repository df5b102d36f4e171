"""The papers' experiments: each runs a scenario headless and returns its figure and metrics.

`EXPERIMENTS` maps an experiment name to its runner; `run(name, ...)` returns a `Result`
with scalar metrics, per-robot totals, time series, and the paper's numbers beside ours
where the paper gives them. `Result.plot(path)` draws the paper's figure (matplotlib, Agg)
and `Result.write_csv(path)` writes every number in tidy form
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


@dataclass(frozen=True)
class Experiment:
    """One experiment: its scenario (`examples/scenario-NAME.toml`), paper, mode and runner."""

    name: str
    scenario: str
    paper: str
    title: str
    mode: str  # "agents": real agent processes; "kinematic": strategies run in-process
    module: str
    modes: tuple[str, ...] = ()  # the modes it can run in (default: just `mode`)

    def runner(self) -> Callable[..., Result]:
        """The module's `run(scenario, progress, **options) -> Result`."""
        runner: Callable[..., Result] = importlib.import_module(f"erni.sim.experiments.{self.module}").run
        return runner


EXPERIMENTS: dict[str, Experiment] = {e.name: e for e in [
    Experiment("energy", "energy", "000", "5 m run: speed and power; standby and moving power",
               "agents", "energy"),
    Experiment("poi", "poi", "000", "PoI coverage by three robots around an obstacle (WiDep)",
               "kinematic", "poi", ("kinematic", "agents")),
    Experiment("relay1", "relay1", "000", "one robot relaying between a source and a destination",
               "kinematic", "relay"),
    Experiment("relay2", "relay2", "000", "two robots relaying between a source and a destination",
               "kinematic", "relay"),
    Experiment("spread-open", "spread-open", "001", "120 robots spreading in an open field",
               "kinematic", "spread"),
    Experiment("spread-corridor", "spread-corridor", "001",
               "120 robots spreading in a corridor (walls at y = +-15 m)", "kinematic", "spread"),
    Experiment("territory", "territory", "002", "six territories; one robot fails and is taken over",
               "kinematic", "territory"),
]}


@dataclass
class Result:
    """What an experiment measured, and how to draw it."""

    name: str
    title: str
    mode: str
    metrics: dict[str, tuple[float | str, str]] = field(default_factory=dict)  # name -> (value or robot, unit)
    robots: dict[str, dict[str, float]] = field(default_factory=dict)  # robot -> quantity -> value
    series: dict[str, tuple[list[float], list[float], str]] = field(default_factory=dict)  # t, v, unit
    paper: list[tuple[str, float, float, str]] = field(default_factory=list)  # quantity, ours, theirs, unit
    notes: list[str] = field(default_factory=list)
    draw: Callable[[Any], None] | None = None  # draws the figure on a matplotlib Figure

    def report(self) -> str:
        """The metrics as text, with the paper's numbers beside ours."""
        lines = [f"{self.name}: {self.title} ({self.mode} mode)"]
        for key, (value, unit) in self.metrics.items():
            lines.append(f"  {key:<48} {_fmt(value):>12} {unit}")
        if len(self.robots) > 12:
            lines.append(f"  per-robot values of {len(self.robots)} robots: see the CSV (--csv)")
        elif self.robots:
            quantities = list(next(iter(self.robots.values())))
            lines.append("  " + f"{'robot':<10}" + "".join(f"{q:>14}" for q in quantities))
            for robot, values in self.robots.items():
                lines.append("  " + f"{robot:<10}" + "".join(f"{_fmt(values[q]):>14}" for q in quantities))
        if self.paper:
            lines.append(f"  {'quantity':<48} {'ours':>12} {'paper':>12}")
            for quantity, ours, theirs, unit in self.paper:
                lines.append(f"  {quantity:<48} {_fmt(ours):>12} {_fmt(theirs):>12} {unit}")
        lines += [f"  note: {n}" for n in self.notes]
        return "\n".join(lines)

    def plot(self, path: str | Path) -> None:
        """Draw the figure into `path` (PNG, SVG or PDF by suffix)."""
        import matplotlib

        matplotlib.use("Agg")
        from matplotlib.figure import Figure

        fig = Figure(figsize=(12, 7.5), dpi=110, layout="constrained")
        if self.draw is None:
            raise ScenarioError(f"{self.name}: this experiment draws no figure")
        self.draw(fig)
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
            for quantity, ours, theirs, unit in self.paper:
                w.writerow(["ours", "", "", quantity, ours, unit])
                w.writerow(["paper", "", "", quantity, theirs, unit])


def _fmt(v: float | str) -> str:
    if isinstance(v, float):
        return f"{v:.4g}" if abs(v) < 1e5 else f"{v:.0f}"
    return str(v)


def run(name: str, scenario: Scenario, progress: Progress | None = None, **options: Any) -> Result:
    """Run experiment `name` on `scenario`; `progress(label, done, total)` hears how far it got."""
    exp = EXPERIMENTS[name]
    mode = options.get("mode")
    if mode is not None and mode not in (exp.modes or (exp.mode,)):
        raise ScenarioError(f"{name} runs in {' or '.join(exp.modes or (exp.mode,))} mode, not {mode!r}")
    return exp.runner()(scenario, progress or (lambda *a: None), experiment=exp, **options)
