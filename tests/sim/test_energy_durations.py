"""The energy run (paper 000, 5.3) at the paper's durations on demand, the short one by default."""

from __future__ import annotations

import argparse

import numpy as np
import pytest

from erni.commands import experiment as command
from erni.sim import experiments
from erni.sim.experiments import energy
from erni.sim.scenario import ScenarioError, find_scenario, load_scenario
from erni.strategies import energy as paper


def scenario():
    return load_scenario(find_scenario("energy"))


def test_the_default_run_keeps_the_scenarios_short_durations():
    p = energy.plan(scenario().strategy)
    assert (p["standby"], p["hold"], p["battery_wh"]) == (10.0, 3.0, 0.5)


def test_paper_durations_hold_standby_600_s_and_each_speed_120_s_on_a_pack_that_lasts():
    p = energy.plan(scenario().strategy, paper_durations=True)
    assert (p["standby"], p["hold"]) == (600.0, 120.0)
    assert p["sweep"] == scenario().strategy["sweep"]
    need = paper.P0 * p["standby"] + float(paper.power(np.array(p["sweep"])).sum()) * p["hold"]
    need += float(paper.power(np.array([p["speed"]]))[0]) * p["distance"] / p["speed"]
    assert need < 0.8 * p["battery_wh"] * 3600.0  # the 0.5 Wh pack would run empty (1.8 kJ)
    # held that long in a line the sweep would leave the radio range (30 m): it drives circles
    assert p["radius"] and 2 * p["radius"] < load_scenario(find_scenario("energy")).radio.comm_range
    assert energy.plan(scenario().strategy)["radius"] is None  # the short run drives straight, as before


def parse(*argv: str) -> argparse.Namespace:
    parser = argparse.ArgumentParser()
    command.register(parser.add_subparsers())
    return parser.parse_args(["experiment", *argv])


def test_the_command_passes_paper_durations_to_energy_only(monkeypatch, capsys):
    seen: dict[str, object] = {}

    def fake(name, sc, progress=None, **options):
        seen.update(options, name=name)
        raise RuntimeError("stop here")

    monkeypatch.setattr(experiments, "run", fake)
    assert command.run(parse("energy", "--paper-durations", "--no-plot")) == 1
    assert seen == {"name": "energy", "mode": "agents", "paper_durations": True}
    seen.clear()
    assert command.run(parse("energy", "--no-plot")) == 1
    assert "paper_durations" not in seen
    assert command.run(parse("relay1", "--paper-durations", "--no-plot")) == 2
    assert "--paper-durations works with energy" in capsys.readouterr().err


def test_an_experiment_without_a_long_form_refuses_the_option():
    with pytest.raises(ScenarioError, match="paper_durations"):
        experiments.run("relay1", load_scenario(find_scenario("relay1")), mode="kinematic", paper_durations=True)


@pytest.mark.ondemand  # about 30 minutes of one agent process
def test_energy_at_the_paper_durations(tmp_path):
    result = experiments.run("energy", scenario(), paper_durations=True)
    row = next(r for r in result.rows if r.quantity.startswith("standby; each sweep"))
    assert row.ours == "600 s; 120 s" and row.kind == "input"
    for level in scenario().strategy["sweep"]:
        got = result.metrics[f"asked {level:g} m/s: mean odometry speed while moving"][0]
        assert abs(got - level) < 0.1 * level + 0.02, result.report()
    odo = result.metrics["whole experiment: energy from odometry (model)"][0]
    batt = result.metrics["whole experiment: energy from the battery readings"][0]
    assert odo > 25_000 and abs(odo - batt) < 2 * result.metrics["battery reading step (0.1 V)"][0]
