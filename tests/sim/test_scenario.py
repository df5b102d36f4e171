"""Scenario files: every example loads, layouts place robots as asked, bad input is one clear line."""

from __future__ import annotations

import math
from pathlib import Path

import pytest

from erni.sim.experiments import EXPERIMENTS
from erni.sim.scenario import Scenario, ScenarioError, find_scenario, load_scenario, parse_scenario

EXAMPLES = Path(__file__).resolve().parents[2] / "examples"


@pytest.mark.parametrize("path", sorted(EXAMPLES.glob("scenario-*.toml")), ids=lambda p: p.stem)
def test_every_example_scenario_loads(path):
    scenario = load_scenario(path)
    names = scenario.robot_names()
    assert len(names) == scenario.count == len(set(names))
    assert path.stem == f"scenario-{scenario.name}"


def test_every_experiment_has_its_scenario():
    for exp in EXPERIMENTS.values():
        assert find_scenario(exp.scenario).is_file(), exp.name


def test_the_default_scenario_file_is_the_built_in_default():
    from_file = load_scenario(EXAMPLES / "scenario-default.toml")
    built_in = Scenario()
    assert from_file.with_robots(from_file.count) == built_in.with_robots(built_in.count)
    assert from_file.starts() == built_in.starts()


def test_the_paper_scenarios_carry_the_papers_numbers():
    poi = load_scenario(EXAMPLES / "scenario-poi.toml")
    assert (poi.count, poi.radio.comm_range, (poi.poi[0].x, poi.poi[0].y)) == (3, 4.5, (0.0, 11.0))
    assert len(poi.world.circle) == 1
    corridor = load_scenario(EXAMPLES / "scenario-spread-corridor.toml")
    assert corridor.count == 120
    assert sorted({a[1] for a, b in corridor.world.segments()}) == [-15.0, 15.0]
    assert (corridor.strategy["distance"], corridor.strategy["gain"], corridor.strategy["dt"]) == (5.0, 2.0, 0.2)
    starts = corridor.starts()
    assert all(-1 <= s.x <= 1 and -1 <= s.y <= 1 for s in starts)
    assert len({round(s.heading, 3) for s in starts}) > 100  # random headings
    territory = load_scenario(EXAMPLES / "scenario-territory.toml")
    assert territory.count == 6 and [f.robot for f in territory.failure] == ["robot2"]


@pytest.mark.parametrize("layout", ["line", "grid", "circle", "random"])
def test_layouts_keep_robots_apart_and_around_the_origin(layout):
    scenario = Scenario(robots={"count": 9, "layout": layout, "origin": [3.0, -2.0], "spacing": 2.0, "area": 6.0})
    pts = [(s.x, s.y) for s in scenario.starts()]
    assert len(pts) == 9
    cx = sum(p[0] for p in pts) / 9
    cy = sum(p[1] for p in pts) / 9
    assert abs(cx - 3.0) < 3.0 and abs(cy + 2.0) < 3.0
    if layout != "random":
        closest = min(math.dist(a, b) for i, a in enumerate(pts) for b in pts[i + 1:])
        assert closest >= 1.99


def test_listed_robots_win_over_the_layout_and_with_robots_trims():
    scenario = Scenario(robot=[{"name": "alpha", "x": 5.0, "y": 5.0}], robots={"count": 3})
    assert scenario.robot_names() == ["alpha", "robot2", "robot3"]
    assert scenario.starts()[0].x == 5.0
    fewer = scenario.with_robots(1)
    assert fewer.robot_names() == ["alpha"]
    more = Scenario().with_robots(7)
    assert more.count == 7 and more.robot_names()[-1] == "robot7"


def test_tasks_and_failures_are_checked_against_the_language_and_the_robots():
    with pytest.raises(ScenarioError) as err:
        parse_scenario({"task": [{"verb": "BotMotion", "preposition": "goto", "params": {"x": 1}}]}, "s.toml")
    assert str(err.value) == "s.toml: task[0]: goto: missing 'y'"
    with pytest.raises(ScenarioError, match=r"^s.toml: failure\[0\].robot: unknown robot 'robot9'"):
        parse_scenario({"failure": [{"at": 1, "robot": "robot9"}]}, "s.toml")
    with pytest.raises(ScenarioError, match=r"^s.toml: task\[0\].to: unknown robot 'bob'"):
        parse_scenario({"task": [{"to": "bob", "verb": "BotMotion", "preposition": "stop"}]}, "s.toml")


@pytest.mark.parametrize("text, expected", [
    ("[radio]\ncomm_range = 3.0\nlossless_range = 5.0\n",
     "radio: lossless_range (5.0 m) must not exceed comm_range (3.0 m)"),
    ("[robots]\ncount = 0\n", "robots.count: Input should be greater than or equal to 1 (got 0)"),
    ("[robots]\nlayout = \"spiral\"\n", "robots.layout: Input should be 'line', 'grid', 'random' or 'circle'"),
    ("colour = 1\n", "unknown key 'colour'"),
    ("world = \"no-such-world.toml\"\n", "world: "),
    ("[[robot]]\nname = \"control\"\n", "control"),
    ("duration = -1\n", "duration: Input should be greater than 0 (got -1)"),
])
def test_bad_scenarios_name_the_file_and_the_field(tmp_path, text, expected):
    path = tmp_path / "bad.toml"
    path.write_text(text)
    with pytest.raises(ScenarioError) as err:
        load_scenario(path)
    assert str(err.value).startswith(f"{path}: ")
    assert expected in str(err.value)
    assert "\n" not in str(err.value)


def test_unreadable_files_are_named(tmp_path):
    with pytest.raises(ScenarioError, match="no such scenario file"):
        load_scenario(tmp_path / "missing.toml")
    broken = tmp_path / "broken.toml"
    broken.write_text("name = [\n")
    with pytest.raises(ScenarioError, match="not valid TOML"):
        load_scenario(broken)
    with pytest.raises(ScenarioError, match="no such scenario; expected a TOML file or one of: .*poi"):
        find_scenario("nonexistent")


def test_a_world_file_is_read_relative_to_the_scenario(tmp_path):
    (tmp_path / "w.toml").write_text("name = \"w\"\nbounds = [0.0, 0.0, 4.0, 4.0]\n")
    (tmp_path / "s.toml").write_text("world = \"w.toml\"\n")
    assert load_scenario(tmp_path / "s.toml").world.bounds == (0.0, 0.0, 4.0, 4.0)
