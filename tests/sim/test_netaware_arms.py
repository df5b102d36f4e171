"""`erni experiment netaware` is an A/B test: the arms of a guard comparison differ in `network_aware` alone.

The short runs (one seed, seconds instead of a minute) check it on what the agents really got:
the mission settings in every robot's agent config and the tasks the control node sent.
"""

from __future__ import annotations

import csv
import subprocess
import sys
import tomllib
from pathlib import Path
from typing import Any

import pytest

from erni.sim import experiments, netns
from erni.sim.experiments import agents, netaware
from erni.sim.scenario import ScenarioError, find_scenario, load_scenario


def scenario(**strategy: Any):
    sc = load_scenario(find_scenario("netaware"))
    return sc.model_copy(update={"strategy": {**sc.strategy, **strategy}})


def test_the_arms_of_a_guard_comparison_share_tasks_and_settings_but_network_aware():
    sc = scenario()
    for name in ("goto", "randomwalk"):
        c = netaware.COMPARISONS[name]
        assert c.kind == "guard"
        on, off = c.arms
        assert (on.network_aware, off.network_aware) == (True, False) and on.algorithm == off.algorithm
        a, b = netaware.arm_settings(sc, on), netaware.arm_settings(sc, off)
        assert {k for k in a.keys() | b.keys() if a.get(k) != b.get(k)} == {"network_aware"}
        assert netaware.arm_tasks(sc, on) == netaware.arm_tasks(sc, off)
        assert len(netaware.arm_tasks(sc, on)) == sc.count
    # the seed draws the tasks: another seed, other targets and walks
    other = sc.model_copy(update={"seed": sc.seed + 1})
    arm = netaware.COMPARISONS["goto"].arms[0]
    assert netaware.arm_tasks(other, arm) != netaware.arm_tasks(sc, arm)


def test_widep_is_no_arm_pair_of_the_guard_and_its_comparison_is_labelled_two_algorithms():
    with pytest.raises(ScenarioError, match="the guard holds remote motion jobs only"):
        netaware.run(scenario(missions=["widep"]), lambda *a: None,
                     experiment=experiments.EXPERIMENTS["netaware"], mode="agents", seeds=1)
    c = netaware.COMPARISONS["widep-vs-goto"]
    assert c.kind == "algorithm" and "algorithm" in c.differs
    assert [a.algorithm for a in c.arms] == ["widep", "poi-goto"]
    assert [a.network_aware for a in c.arms] == [False, False]  # only the algorithm differs


def test_netns_is_an_option_of_netaware_alone():
    with pytest.raises(ScenarioError, match="loopback tier only"):
        experiments.run("memory", scenario(), netns=True)
    out = subprocess.run([sys.executable, "-m", "erni", "experiment", "territory", "--netns"],
                         capture_output=True, text=True, timeout=60)
    assert out.returncode == 2 and "--netns: territory runs on the loopback tier only" in out.stderr


def recording(monkeypatch: pytest.MonkeyPatch) -> list[dict[str, Any]]:
    """Record, per team, every robot's mission settings from its agent config and the tasks sent."""
    runs: list[dict[str, Any]] = []
    start, send = agents.TeamRun.start, agents.TeamRun.send

    def started(self: agents.TeamRun, timeout: float = 120.0) -> agents.TeamRun:
        start(self, timeout)
        assert self.team is not None
        mission = {}
        for name in self.team.names:
            config = tomllib.loads((self.team.run_dir / "agents" / f"{name}.toml").read_text())
            (settings,) = [p["settings"] for p in config["plugin"] if p["class"] == "mission"]
            mission[name] = settings
        runs.append({"mission": mission, "sent": [], "netns": self.team.mesh is not None})
        return self

    def sent(self: agents.TeamRun, robot: str, verb: str, preposition: str, **params: Any) -> str:
        runs[-1]["sent"].append((robot, verb, preposition, params))
        return send(self, robot, verb, preposition, **params)

    monkeypatch.setattr(agents.TeamRun, "start", started)
    monkeypatch.setattr(agents.TeamRun, "send", sent)
    return runs


def check_pairs(runs: list[dict[str, Any]], missions: list[str]) -> None:
    """Consecutive teams are the two arms of one mission: the same tasks, settings differing in
    network_aware alone (on in the first, off in the second)."""
    assert len(runs) == 2 * len(missions)
    for on, off in zip(runs[::2], runs[1::2]):
        assert on["sent"] == off["sent"] and len(on["sent"]) == len(on["mission"])
        for robot in on["mission"]:
            a, b = on["mission"][robot], off["mission"][robot]
            assert {k for k in a.keys() | b.keys() if a.get(k) != b.get(k)} == {"network_aware"}, (a, b)
            assert a["network_aware"] is True and b["network_aware"] is False


def check_outputs(result: experiments.Result, missions: list[str], tmp_path: Path) -> None:
    png, table = tmp_path / "netaware.png", tmp_path / "netaware.csv"
    result.plot(png)
    result.write_csv(table)
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and png.stat().st_size > 30_000
    rows = list(csv.DictReader(table.open()))
    for mission in missions:
        for arm in ("guard on", "guard off"):
            value = result.metrics[f"{mission}, {arm}: connectivity kept (share of time)"][0]
            assert 0.0 <= float(str(value).split()[0]) <= 1.0
            done = str(result.metrics[f"{mission}, {arm}: tasks completed"][0])
            assert done.split(" = ")[0].endswith("/4")
            (run,) = [v for k, v in result.robots.items() if k.startswith(f"{mission}/{arm}/")]
            assert (run["time_s"] == "-") == (str(run["completed"]).startswith("0/")), run
            assert any(r["quantity"] == f"{mission}, {arm}: time to complete" for r in rows)
        differs = next(r for r in result.rows if r.quantity == f"{mission}: what differs between the arms")
        assert differs.ours == "guard" and "network_aware setting alone" in differs.how
        assert any(r.quantity == f"{mission}: connectivity kept, guard on / guard off" for r in result.rows)
    assert any("guard holds remote motion jobs only" in n for n in result.notes)


QUICK = {"goto_time": 12.0, "walk": 4.0, "goto_near": 3.0, "goto_far": 4.0}


@pytest.mark.slow
def test_a_quick_run_on_the_loopback_tier_differs_between_its_arms_in_the_guard_alone(monkeypatch, tmp_path):
    runs = recording(monkeypatch)
    missions = ["goto", "randomwalk"]
    result = experiments.run("netaware", scenario(missions=missions, **QUICK), seeds=1)
    check_pairs(runs, missions)
    assert not any(r["netns"] for r in runs)
    check_outputs(result, missions, tmp_path)
    # a walk of 4 s ends in time whatever the guard does; its success is timed from the sending
    for arm in ("guard on", "guard off"):
        assert result.metrics[f"randomwalk, {arm}: tasks completed"][0].startswith("4/4"), result.report()
        assert 4.0 <= float(str(result.metrics[f"randomwalk, {arm}: time to complete"][0]).split()[0]) < 15.0


@pytest.mark.slow
@pytest.mark.netns
@pytest.mark.skipif(bool(netns.unavailable_reason()), reason="real-mesh tier unavailable")
def test_a_quick_run_on_the_real_mesh_differs_between_its_arms_in_the_guard_alone(monkeypatch, tmp_path):
    runs = recording(monkeypatch)
    missions = ["goto"]
    result = experiments.run("netaware", scenario(missions=missions, **QUICK), seeds=1, netns=True)
    check_pairs(runs, missions)
    assert all(r["netns"] for r in runs)
    assert "babeld" in result.mode_note
    check_outputs(result, missions, tmp_path)
