"""The papers' experiments produce the behaviour the papers describe, a figure and every number."""

from __future__ import annotations

import csv
import math
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from erni.sim import experiments, kinematic
from erni.sim.experiments import netaware
from erni.sim.scenario import find_scenario, load_scenario
from erni.strategies import energy as paper

ROOT = Path(__file__).resolve().parents[2]


def scenario(name: str, **strategy):
    sc = load_scenario(find_scenario(name))
    if strategy:
        sc = sc.model_copy(update={"strategy": {**sc.strategy, **strategy}})
    return sc


def check_outputs(result, tmp_path):
    png, table = tmp_path / "fig.png", tmp_path / "numbers.csv"
    result.plot(png)
    result.write_csv(table)
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and png.stat().st_size > 30_000
    rows = list(csv.DictReader(table.open()))
    assert {r["section"] for r in rows} >= {"metric", "series"}
    assert all(r["quantity"] for r in rows)
    text = result.report()
    assert result.name in text.splitlines()[0]
    return rows


def test_poi_coverage_reaches_the_poi_without_losing_the_base(tmp_path):
    result = experiments.run("poi", scenario("poi"), mode="kinematic")
    covered = result.metrics["PoI covered at"][0]
    assert math.isfinite(covered) and covered > 10
    assert result.metrics["lowest share connected to the base"][0] == 1.0
    assert result.metrics["closest approach to the obstacle surface"][0] > 0.0
    t, d, _ = result.series["seed1/distance_to_poi"]
    assert d[0] > 9 and d[-1] <= 0.5
    energies = {r: v["energy_j"] for r, v in result.robots.items()}
    far = max(result.robots, key=lambda r: result.robots[r]["from_base_m"])
    assert energies[far] == max(energies.values())  # the robot that went farthest spent the most
    assert min(energies.values()) > paper.P0 * covered
    check_outputs(result, tmp_path)


def test_one_relay_settles_near_the_middle_and_two_split_the_line(tmp_path):
    one = experiments.run("relay1", scenario("relay1"), mode="kinematic")
    final = one.robots["robot1"]["final_m"]
    assert abs(final - 8.0) < 1.5
    assert one.metrics["decisions until every relay stays at its slot"][0] < 20
    two = experiments.run("relay2", scenario("relay2"), mode="kinematic")
    r1, r2 = two.robots["robot1"]["final_m"], two.robots["robot2"]["final_m"]
    assert 0 < r1 < r2 < 24
    assert abs(r1 - 8.0) < 2.0 and abs(r2 - 16.0) < 2.0
    check_outputs(two, tmp_path)


def test_territory_failure_is_taken_over_once_by_a_neighbour(tmp_path):
    sc = scenario("territory").model_copy(update={"duration": 180.0})
    result = experiments.run("territory", sc, mode="kinematic")
    assert result.metrics["robot2: claims made (1 is right)"][0] == 1
    assert result.metrics["robot2: block taken over by"][0] in ("robot1", "robot3", "robot5")
    detect = result.metrics["robot2: first detection after the failure"][0]
    silence = sc.strategy["silence"]
    assert silence - sc.strategy["heartbeat"] - 0.3 <= detect <= silence + 0.5
    assert result.metrics["robot2: takeover after the failure"][0] > detect
    taker = result.metrics["robot2: block taken over by"][0]
    assert result.robots[taker]["holds"] == 2 and result.robots["robot2"]["distance_m"] < result.robots[taker]["distance_m"]
    check_outputs(result, tmp_path)


def test_spread_in_a_corridor_settles_apart_and_no_robot_ends_pinned_to_a_wall(tmp_path):
    sc = scenario("spread-corridor", variants=["holonomic/delaunay", "nonholonomic/physical"], hold=3.0)
    sc = sc.with_robots(30).model_copy(update={"duration": 60.0})
    ticks = []
    result = experiments.run("spread-corridor", sc, lambda label, done, total: ticks.append((done, total)),
                             mode="kinematic")
    assert ticks and result.mode == "kinematic"
    for v in ("holonomic/delaunay", "nonholonomic/physical"):
        t, nn, _ = result.series[f"{v}/mean_nn_distance"]
        assert nn[0] < 0.6 and nn[-1] > 2.0
        assert result.metrics[f"{v}: robots within 0.5 m of a wall at the end"][0] == 0
        assert result.metrics[f"{v}: largest radio component at the end (R = 7.5 m)"][0] == 1.0
        assert result.metrics[f"{v}: converged at (all slower than 0.05 m/s for 3 s)"][0] < 60.0
        assert result.metrics[f"{v}: neighbourhood links made or broken per s in the last 3 s"][0] == 0.0
    # a settled nonholonomic robot may still feel a force, but only across its heading (the wheels hold it)
    force = result.metrics["nonholonomic/physical: largest unbalanced force at the end"][0]
    assert force > 0.5 and force - result.metrics["nonholonomic/physical: ... of it across the heading"][0] < 0.05
    rows = {r.quantity: r for r in result.rows}
    assert rows["robots / desired distance d / damping k / dt"].kind == "input"  # d is an input, never "ours"
    assert rows["wall sensed within (sensing range)"].kind == "input" and rows["wall sensed within (sensing range)"].ours == "2.5"
    assert "(input)" in result.report()
    check_outputs(result, tmp_path)


def test_a_team_jittering_in_place_settles_in_place_but_not_by_speed():
    from erni.sim.experiments.spread import _in_place, _still

    t = np.arange(0.0, 40.0, 0.5)
    pos = np.zeros((len(t), 3, 2))
    pos[:, 0, 0] = np.minimum(t, 12.0) * 0.3           # robot 1 drives 3.6 m, then stops at t = 12 s
    pos[:, 1, 1] = 0.02 * (np.arange(len(t)) % 2)      # robot 2 jumps 2 cm back and forth every sample
    step = np.diff(pos, axis=0, prepend=pos[:1])
    speed = np.hypot(step[:, :, 0], step[:, :, 1]) / 0.5
    assert math.isnan(_still(t, speed, 0.03, 10.0))    # 0.04 m/s of jitter: never "slower than 0.03"
    assert _in_place(t, pos, 0.1, 10.0) == 12.0        # ... yet every robot stays put from 12 s
    assert math.isnan(_in_place(t, pos, 0.01, 10.0))   # the jitter is wider than 1 cm
    assert math.isnan(_in_place(t[:30], pos[:30], 0.1, 10.0))  # no 10 s after the stop: not settled


def test_the_paper_table_keeps_inputs_apart_from_results(tmp_path):
    res = experiments.Result("x", "t", "kinematic", mode_note="how it ran")
    res.compare("d", 5.0, 5.0, "m", "the paper's setting", "input")
    res.compare("nearest neighbour", "5", 3.8, "m", "measured at the end")
    res.draw = lambda fig: fig.add_subplot(1, 1, 1).plot([0, 1], [0, 1])
    text = res.report()
    assert "d (input)" in text and "nearest neighbour (input)" not in text and "how it ran" in text
    res.write_csv(tmp_path / "n.csv")
    rows = list(csv.DictReader((tmp_path / "n.csv").open()))
    assert [(r["section"], r["quantity"]) for r in rows] == [("paper", "d"), ("input", "d"), ("paper",
                                                              "nearest neighbour"), ("ours", "nearest neighbour")]


def test_agents_mode_is_the_default_wherever_the_team_is_small():
    for e in experiments.EXPERIMENTS.values():
        sc = load_scenario(find_scenario(e.scenario))
        mode = e.default_mode(sc)
        assert mode in e.modes
        if "agents" in e.modes:
            assert (mode == "agents") == (sc.count <= experiments.AGENT_ROBOTS), e.name
    assert experiments.EXPERIMENTS["spread-open"].default_mode(load_scenario(find_scenario("spread-open"))) == \
        "kinematic"


def test_walls_stop_kinematic_robots():
    old = np.array([[0.0, 14.9], [0.0, 0.0]])
    new = np.array([[0.0, 15.1], [0.0, 1.0]])
    walls = np.array([[-50.0, 15.0, 50.0, 15.0]])
    assert kinematic.blocked_by_walls(old, new, walls).tolist() == [True, False]
    assert kinematic.coverage(np.array([[0.0, 0.0]]), 1.0) == pytest.approx(math.pi, rel=0.03)


@pytest.mark.slow
def test_energy_from_what_a_real_agent_sees_through_its_driver(tmp_path):
    sc = scenario("energy", standby=3.0, distance=1.0, speed=0.5, sweep=[0.3, 0.8], hold=2.0, battery_wh=0.1)
    result = experiments.run("energy", sc)
    assert result.mode == "agents"
    rows = {r.quantity: r for r in result.rows}
    assert rows["standby power P0"].kind == "input" and rows["moving power Pmov"].kind == "input"
    assert abs(result.metrics["distance travelled by odometry (asked 1 m)"][0] - 1.0) < 0.1
    assert result.metrics["peak speed"][0] == pytest.approx(0.5, abs=0.05)
    assert result.metrics["asked 0.8 m/s: mean odometry speed while moving"][0] == pytest.approx(0.8, abs=0.1)
    # two readings of the agent: the model over its odometry, and its battery's fall (18 J steps here)
    odo = result.metrics["whole experiment: energy from odometry (model)"][0]
    batt = result.metrics["whole experiment: energy from the battery readings"][0]
    step = result.metrics["battery reading step (0.1 V)"][0]
    assert odo > paper.P0 * 5 and abs(odo - batt) <= 2 * step + 0.05 * odo
    check_outputs(result, tmp_path)


def test_experiment_command_writes_figure_and_csv_and_refuses_bad_input(tmp_path):
    png, table = tmp_path / "poi.png", tmp_path / "poi.csv"
    out = subprocess.run([sys.executable, "-m", "erni", "experiment", "poi", "--mode", "kinematic", "--plot", str(png),
                          "--csv", str(table)], cwd=tmp_path, capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    assert "PoI covered at" in out.stdout and png.stat().st_size > 30_000 and table.stat().st_size > 1000
    assert f"figure: {png}" in out.stdout and "how ours was obtained" in out.stdout
    out = subprocess.run([sys.executable, "-m", "erni", "experiment", "nope"], cwd=tmp_path, capture_output=True,
                         text=True, timeout=60)
    assert out.returncode == 2 and "unknown experiment 'nope'; expected one of energy, poi" in out.stderr
    out = subprocess.run([sys.executable, "-m", "erni", "experiment", "poi", "--plot", "/no/such/dir/x.png"],
                         cwd=tmp_path, capture_output=True, text=True, timeout=60)
    assert out.returncode == 2 and "--plot /no/such/dir/x.png" in out.stderr
    out = subprocess.run([sys.executable, "-m", "erni", "experiment", "relay1", "--seeds", "3"],
                         cwd=tmp_path, capture_output=True, text=True, timeout=60)
    assert out.returncode == 2 and "--seeds: relay1 runs one seed at a time" in out.stderr
    out = subprocess.run([sys.executable, "-m", "erni", "experiment", "--list"], cwd=tmp_path, capture_output=True,
                         text=True, timeout=60)
    assert out.returncode == 0
    listed = {line.split()[0]: line for line in out.stdout.splitlines()[1:]}
    assert set(listed) == set(experiments.EXPERIMENTS)
    assert "agents" in listed["netaware"] and listed["spread-open"].split()[2] == "kinematic"
    assert listed["poi"].split()[2] == "agents"


# --- agents mode: short versions of the paper runs (the full ones: `pytest -m ondemand`) ---------


@pytest.mark.slow
def test_roundtrip_to_several_consumers_through_real_agents(tmp_path):
    sc = scenario("roundtrip", consumers=[1, 2], count=15, warmup=3, gap=0.02)
    result = experiments.run("roundtrip", sc)
    assert result.mode == "agents"
    for n in (1, 2):
        for kind in ("sensor", "image"):
            xs = result.series[f"{n}/{kind}_rtt_ms"][1]
            assert len(xs) == 15 and all(0.1 < x < 1000 for x in xs)
    ours = {r.quantity: r for r in result.rows}
    assert ours["1 consumer(s): other sensory data (pose, sonar, battery)"].paper == "not measured"
    check_outputs(result, tmp_path)


@pytest.mark.slow
def test_response_test_through_the_device_layer_the_blackboard_and_the_transport(tmp_path):
    sc = scenario("response", iterations=4, runs=1, rest=0.1)
    result = experiments.run("response", sc)
    for path in ("raw", "poll", "notify", "remote"):
        xs = result.series[f"{path}/run1_ms"][1]
        assert len(xs) == 4 and all(0.0 < x < 2000 for x in xs)
    raw = np.mean(result.series["raw/run1_ms"][1])
    assert raw < 60  # odometry every 10 ms: the device layer answers within a few cycles
    check_outputs(result, tmp_path)


@pytest.mark.slow
def test_memory_of_robot_agents_is_read_from_proc(tmp_path):
    sc = scenario("memory", settle=3.0, window=2.0).with_robots(2)
    result = experiments.run("memory", sc)
    agent = result.metrics["robot agent (transport, motion, MobiNet, mission): VmRSS, largest"][0]
    floor = result.metrics["bare Python interpreter: VmRSS (floor)"][0]
    assert 5 < floor < agent < 500
    assert {r.quantity for r in result.rows} >= {"robot agent process", "whole robot"}
    check_outputs(result, tmp_path)


@pytest.mark.ondemand  # minutes of three agent processes in lockstep rounds, ten times
def test_poi_coverage_by_real_agents_in_ten_of_ten_seeds(tmp_path):
    result = experiments.run("poi", scenario("poi"), mode="agents", seeds=10)
    assert result.metrics["runs that covered the PoI, always connected to the base"][0] == "10 of 10", \
        result.report()
    check_outputs(result, tmp_path)


@pytest.mark.ondemand
def test_relays_on_agents_settle(tmp_path):
    for name in ("relay1", "relay2"):
        result = experiments.run(name, scenario(name), mode="agents")
        assert math.isfinite(result.metrics["decisions until every relay stays at its slot"][0]), result.report()
    check_outputs(result, tmp_path)


@pytest.mark.ondemand
def test_patrol_on_agents_detects_the_failure_and_one_neighbour_takes_over(tmp_path):
    result = experiments.run("territory", scenario("territory"), mode="agents")
    assert result.metrics["robot2: claims made (1 is right)"][0] == 1, result.report()
    assert result.metrics["robot2: block taken over by"][0] in ("robot1", "robot3", "robot5")
    check_outputs(result, tmp_path)


@pytest.mark.slow
def test_widep_keeps_the_team_in_reach_of_the_control_node_and_it_hears_the_success():
    # WiDep steps with R = the longest link of quality 0.3 (6.8 m here, not the 8 m where
    # delivery is 0): the team stays one component with the control node, so the success reaches it
    sc = scenario("netaware", missions=["widep-vs-goto"], poi_distance=10.0)
    assert netaware.widep_range(sc) == pytest.approx(6.8)
    widep = netaware.COMPARISONS["widep-vs-goto"].arms[0]
    assert widep.algorithm == "widep" and not widep.network_aware
    out = netaware._one(sc, "widep-vs-goto", widep, lambda *a: None)
    assert out.completed == 1, out
    assert out.connected > 0.99, out
    assert out.reported == 1, out


@pytest.mark.ondemand
def test_network_aware_team_keeps_connectivity_better_than_a_blind_one(tmp_path):
    result = experiments.run("netaware", scenario("netaware"), seeds=10)
    rows = {r.quantity: r for r in result.rows}
    aware, blind = (float(x) for x in str(rows["goto: connectivity kept, guard on / guard off"].ours).split(" / "))
    assert aware > blind, result.report()
    check_outputs(result, tmp_path)


def test_a_share_of_times_interval_stays_within_0_and_1():
    from erni.sim.experiments.stats import mean_ci

    shares = [1.0] * 9 + [0.55]  # one run of ten lost its connectivity half the time
    m, lo, hi = mean_ci(shares)
    assert hi > 1.0  # the Student-t interval alone runs past 1
    m2, lo2, hi2 = mean_ci(shares, bounds=(0.0, 1.0))
    assert (m2, lo2, hi2) == (m, lo, 1.0) and 0.8 < lo2 < m2


def test_spread_repeats_over_the_seeds_given_on_the_command_line(tmp_path):
    out = subprocess.run([sys.executable, "-m", "erni", "experiment", "spread-open", "--mode", "kinematic",
                          "--seeds", "2", "--duration", "3", "--robots", "5", "--no-plot"],
                         cwd=tmp_path, capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    assert "5 robot(s), 2 seeds" in out.stdout
    assert "seed 2 (2/2)" in out.stdout + out.stderr
    assert "over 2 seeds: converged" in out.stdout
