"""The world model: TOML loading with clear errors, rays, clearance and line of sight."""

from __future__ import annotations

import math
from pathlib import Path

import pytest

from erni.sim.world import World, WorldError
from tests.motion.conftest import sim_only_because

pytestmark = sim_only_because("tests ERNI's simulated world itself")

EXAMPLES = Path(__file__).resolve().parents[2] / "examples"


def test_example_worlds_load():
    corridor = World.load(EXAMPLES / "world-corridor.toml")
    assert corridor.name == "corridor" and len(corridor.wall) == 1 and len(corridor.robot) == 2
    assert corridor.start_pose(1).name == "robot2"
    assert corridor.start_pose(0, "robot2").y == -1.0
    assert World.load(EXAMPLES / "world-empty.toml").bounds == (-10.0, -10.0, 10.0, 10.0)


def test_bad_world_files_name_the_file_and_the_field(tmp_path):
    bad = tmp_path / "bad.toml"
    bad.write_text("[[circle]]\ncenter = [0, 0]\nradius = -1\n")
    with pytest.raises(WorldError, match=r"bad.toml: circle\[0\]\.radius: .*greater than 0"):
        World.load(bad)
    bad.write_text("[[wal]]\na = [0, 0]\n")
    with pytest.raises(WorldError, match=r"unknown key 'wal'"):
        World.load(bad)
    bad.write_text("bounds = [1, 1, 0, 0]\n")
    with pytest.raises(WorldError, match="xmin < xmax"):
        World.load(bad)
    bad.write_text("name = \n")
    with pytest.raises(WorldError, match="not valid TOML"):
        World.load(bad)
    with pytest.raises(WorldError, match="no such world file"):
        World.load(tmp_path / "missing.toml")


def test_rays_hit_walls_circles_and_polygons_at_the_right_distance():
    w = World(wall=[{"a": (3, -1), "b": (3, 1)}], circle=[{"center": (0, 5), "radius": 1}],
              polygon=[{"points": [(-4, -1), (-2, -1), (-2, 1), (-4, 1)]}])
    assert w.ray(0, 0, 0.0, 10) == pytest.approx(3.0)
    assert w.ray(0, 0, math.pi / 2, 10) == pytest.approx(4.0)
    assert w.ray(0, 0, math.pi, 10) == pytest.approx(2.0)
    assert w.ray(0, 0, -math.pi / 2, 10) == 10  # nothing below: capped at max range
    assert w.ray(0, 0, math.atan2(1, 3), 10) == pytest.approx(math.hypot(3, 1))  # the wall's end
    assert w.ray(0, 0, 0.0, 10, extra=[((1.5, 0.0), 0.5)]) == pytest.approx(1.0)


def test_clearance_and_bounds():
    w = World(bounds=(-1, -1, 1, 1), circle=[{"center": (0.5, 0.5), "radius": 0.1}])
    assert w.clearance(0, 0) == pytest.approx(min(1.0, math.hypot(0.5, 0.5) - 0.1))
    assert w.clearance(0.9, 0) == pytest.approx(0.1)
    inside = World(polygon=[{"points": [(0, 0), (1, 0), (1, 1), (0, 1)]}])
    assert inside.clearance(0.5, 0.5) == 0.0
    assert inside.clearance(2, 0.5) == pytest.approx(1.0)


def test_crossings_count_what_a_radio_link_passes_through():
    w = World(wall=[{"a": (1, -1), "b": (1, 1)}, {"a": (2, -1), "b": (2, 1)}],
              circle=[{"center": (0, 3), "radius": 0.5}])
    assert w.crossings((0, 0), (3, 0)) == 2
    assert w.crossings((0, 0), (0.5, 0)) == 0
    assert w.line_of_sight((0, 0), (0, 2))
    assert not w.line_of_sight((0, 2), (0, 4))
