"""A creep round as the tests run it, and what every trial must show."""

from __future__ import annotations

from collections.abc import Sequence

from erni.sim import creep
from erni.sim.team import Team


def one_round(team: Team, speeds: Sequence[float], number: int = 1, rest: float = 3.0) -> list[creep.Trial]:
    creep.reset(team, lambda: creep.peers_up(team), rest=rest)
    return creep.run_round(team, number, speeds, observe=8.0)


def assert_held(trials: list[creep.Trial]) -> None:
    """No partition; every end robot stood inside the range and did not creep on. A robot whose
    only link already shows loss may be held before it moves at all (the guard does not start a
    motion away from a lossy critical link): then it never stood after moving, and it must not
    have left its start."""
    rows = [t.row() for t in trials]
    assert not any(t.partitioned for t in trials), rows
    for t in trials:
        assert t.closest > 0.0, t.row()
        if t.stop_after_crossing is None:
            start, far = t.track[0][1], max(d for _, d in t.track)
            assert far - start < 0.1, ("moved and never stood", t.row())
        assert t.crept_on < 0.3, t.row()
