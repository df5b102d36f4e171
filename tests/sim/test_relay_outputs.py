"""The relay experiments (paper 000, 5.2): one settle rule, a consistent lower bound, a complete CSV."""

from __future__ import annotations

import csv

import pytest

from erni.sim import experiments, netns
from erni.sim.experiments import relay
from erni.sim.scenario import find_scenario, load_scenario


def test_relay1_and_relay2_judge_settling_by_one_rule():
    for name in ("relay1", "relay2"):
        sc = load_scenario(find_scenario(name))
        assert "settle" not in sc.strategy, f"{name} sets its own settle distance"
        result = experiments.run(name, sc, mode="kinematic")
        row = next(r for r in result.rows if r.quantity.startswith(("decisions until", "relays settle")))
        assert f"within {relay.SETTLE:g} m" in row.how


def test_the_stated_lower_bound_never_exceeds_the_decisions_measured():
    for name in ("relay1", "relay2"):
        result = experiments.run(name, load_scenario(find_scenario(name)), mode="kinematic")
        row = next(r for r in result.rows if r.quantity.startswith("start: farthest relay"))
        bound = int(row.how.rsplit("(", 1)[1].rstrip(")"))
        settled = result.metrics["decisions until every relay stays at its slot"][0]
        assert bound <= settled, (name, bound, settled)
    assert relay.fewest_decisions(3.0, 1.5, 1.0) == 2  # relay1: 3 m off, 1 m moves
    assert relay.fewest_decisions(6.0, 1.5, 1.0) == 5  # relay2
    assert relay.fewest_decisions(1.0, 1.5, 1.0) == 0


def test_the_csv_holds_the_link_qualities_the_figure_draws(tmp_path):
    result = experiments.run("relay2", load_scenario(find_scenario("relay2")), mode="kinematic")
    path = tmp_path / "relay2.csv"
    result.write_csv(path)
    rows = [r for r in csv.DictReader(path.open()) if r["section"] == "series"]
    quantities = {(r["robot"], r["quantity"]) for r in rows}
    assert quantities >= {("robot1", "link_quality_to_S"), ("robot1", "link_quality_to_robot2"),
                          ("robot2", "link_quality_to_robot1"), ("robot2", "link_quality_to_D")}
    decisions = len(result.series["robot1/position_along"][0]) - 1
    for robot, quantity in quantities - {("robot1", "position_along"), ("robot2", "position_along")}:
        values = [float(r["value"]) for r in rows if (r["robot"], r["quantity"]) == (robot, quantity)]
        assert len(values) == decisions and all(0.0 <= v <= 1.0 for v in values)


def test_a_real_mesh_relay_run_refuses_a_start_whose_links_cannot_carry_a_handshake():
    """On the real-mesh tier a relay learns its neighbours' positions from their Poses over transport sessions:
    relay1's start (robot1 11 m from D at comm_range 12 m, a delivery ratio of 0.11) is refused at once, in one
    line naming the link, its quality and a start that works, where the run used to wait 480 s with the relay
    "waiting for the position of destination"; the mesh variants of relay1 and relay2 start."""
    from erni.sim.scenario import ScenarioError
    from erni.sim.world import RobotStart

    def chain(name: str) -> tuple[object, list[RobotStart]]:
        sc = load_scenario(find_scenario(name))
        ends = [RobotStart(name=p.name, x=p.x, y=p.y, heading=0.0) for p in sc.poi[:2]]
        return sc, [ends[0], *sc.starts(), ends[1]]

    with pytest.raises(ScenarioError) as err:
        relay._check_mesh_start(*chain("relay1"))
    assert "robot1 and destination start 11.0 m apart, link quality 0.11" in str(err.value)
    assert "\n" not in str(err.value) and "scenario-relay1-mesh.toml" in str(err.value)
    for name in ("relay1-mesh", "relay2-mesh"):
        relay._check_mesh_start(*chain(name))  # every link at 0.38 or better


@pytest.mark.netns
@pytest.mark.skipif(bool(netns.unavailable_reason()), reason="real-mesh tier unavailable")
@pytest.mark.xfail(strict=False, reason="known load-dependent failure: under the whole suite the relay stayed at or "
                   "near its start in 2 of 3 runs (passes alone); reported as xfailed, not passed, until it is fixed")
def test_on_the_real_mesh_the_relay_moves_toward_its_weaker_link_as_babeld_reads_it(tmp_path):
    """relay1 on the mesh variant (16 m radio), six decisions of 8 s on the real-mesh tier: S, D and the relay in
    namespaces with babeld, the relay's link qualities from MobiNet reading babeld. It starts 6 m from S and 10 m
    from D (the model's 0.77 and 0.46: nearer D than the scenario's start, so that its handshake with D completes
    within the test), so it moves toward D along S-D; its links are babeld's readings (between 0 and 1, not the
    model's values), and the notes say the qualities are measured."""
    sc = load_scenario(find_scenario("relay1-mesh"))
    start = sc.robot[0].model_copy(update={"x": -2.0})
    sc = sc.model_copy(update={"duration": 48.0, "robot": [start], "strategy": {**sc.strategy, "period": 8.0}})
    result = experiments.run("relay1", sc, mode="agents", netns=True)
    assert "babeld" in result.mode_note
    _, along, _ = result.series["robot1/position_along"]
    assert along[-1] > along[0] + 0.5, along  # toward D, the weaker link
    _, q_s, _ = result.series["robot1/link_quality_to_S"]
    _, q_d, _ = result.series["robot1/link_quality_to_D"]
    read = [(s, d) for s, d in zip(q_s, q_d) if s > 0 and d > 0]  # 0 until the relay has both neighbours' Poses
    assert len(read) >= 2 and all(s <= 1.0 and d <= 1.0 for s, d in read), (q_s, q_d)
    assert (q_s[-1], q_d[-1]) != (pytest.approx(0.77, abs=1e-3), pytest.approx(0.46, abs=1e-3))
    assert any("link qualities (measured): babeld's reading" in n for n in result.notes), result.notes
