"""Which links keep changing at the end of a spread run: each change told apart (a flip of a
quadrilateral's diagonal, an edge of the team, at the radio reach, near a wall, about d or shorter)."""

from __future__ import annotations

import numpy as np

from erni.sim.experiments import spread
from erni.sim.scenario import find_scenario, load_scenario

WALLS = np.array([[-50.0, 15.0, 50.0, 15.0], [-50.0, -15.0, 50.0, -15.0]])


def test_a_flip_is_told_from_a_lone_link_at_the_reach_and_from_one_near_a_wall():
    # a quadrilateral whose diagonal 0-2 gives way to 1-3, and a lone link 4-5 made at 7 m near the wall
    pos = np.array([[-2.0, 0.0], [0.0, -2.5], [2.0, 0.0], [0.0, 2.5], [-3.5, 13.0], [3.5, 13.0]])
    after = np.array([[0, 1, 3], [1, 2, 3]], dtype=np.intp)
    before = np.array([[0, 1, 2], [0, 2, 3]], dtype=np.intp)
    got, _ = spread._change_kinds(10.0, {(1, 3), (4, 5)}, {(0, 2)}, pos, after, 5.0, 7.5, WALLS, 2.5, before)
    kinds = {(c.i, c.j): c for c in got}
    assert kinds[(1, 3)].on and kinds[(1, 3)].flip and not kinds[(1, 3)].edge and kinds[(1, 3)].short
    assert not kinds[(0, 2)].on and kinds[(0, 2)].flip and not kinds[(0, 2)].edge  # inside the triangulation before
    lone = kinds[(4, 5)]
    assert not lone.flip and lone.edge and lone.reach and lone.wall and not lone.short
    assert abs(lone.length - 7.0) < 1e-9
    assert not kinds[(1, 3)].wall and not kinds[(1, 3)].reach
    summary = spread.change_summary(got, 100.0)
    assert summary["count"] == 3 and abs(summary["flip"] - 2 / 3) < 1e-9 and summary["links"] == 3
    assert summary["top"][1] == 1


def test_a_run_keeps_the_link_changes_of_its_last_window_and_reports_them(monkeypatch):
    monkeypatch.setattr(spread, "CHANGES_WINDOW", 40.0)
    sc = load_scenario(find_scenario("spread-corridor")).with_robots(30)
    sc = sc.model_copy(update={"duration": 130.0})
    run = spread._kinematic(sc, lambda *a: None, "holonomic/delaunay", "")
    assert run.changes and run.t[-1] > 40.0
    assert min(c.t for c in run.changes) >= run.t[-1] - 40.0 - 1e-9
    got = spread.change_summary(run.changes, float(run.t[-1]))
    assert got["per_s"] == len(run.changes) / 40.0


def test_a_physical_link_inside_the_team_is_not_on_its_edge_and_one_between_rim_robots_is():
    # corners 0-3 far out, four robots inside: 4-5 (6 m) is no Delaunay edge (6-7 lie between them)
    pos = np.array([[-20.0, -20.0], [20.0, -20.0], [20.0, 20.0], [-20.0, 20.0],
                    [-3.0, 0.0], [3.0, 0.0], [0.0, 0.5], [0.0, -0.5]])
    got, tri = spread._change_kinds(5.0, {(4, 5), (0, 1)}, set(), pos, None, 5.0, 7.5, np.zeros((0, 4)), 2.5)
    assert tri is not None and not {(4, 5)} <= {tuple(sorted(e)) for t in tri.tolist() for e in
                                                  ((t[0], t[1]), (t[1], t[2]), (t[0], t[2]))}
    kinds = {(c.i, c.j): c for c in got}
    assert not kinds[(4, 5)].edge and not kinds[(4, 5)].flip and not kinds[(4, 5)].wall
    assert kinds[(0, 1)].edge  # a side of the hull
