"""`erni sim` starts a team larger than this machine is measured to hold in real time only with a
one-line warning on stderr naming the figure (robots per core, from bench/bench_team.py)."""

from __future__ import annotations

import argparse
import os

import pytest

from erni.commands import sim
from erni.commands.sim import ROBOTS_PER_CORE, capacity_warning, cores


def test_the_figure_is_the_measured_one():
    assert ROBOTS_PER_CORE == 25  # 50 robots held real time on 2 cores, 100 did not (bench_team.json)


@pytest.mark.parametrize("robots,n,warned", [(50, 2, False), (51, 2, True), (200, 2, True), (25, 1, False),
                                             (26, 1, True), (200, 8, False), (201, 8, True)])
def test_a_team_beyond_the_cores_is_warned_of(robots, n, warned):
    assert bool(capacity_warning(robots, n)) is warned


def test_the_warning_names_the_figure():
    assert capacity_warning(200, 2) == (
        "200 robots is more than this machine is measured to hold in real time (about 25 robots per core: "
        "50 on its 2 cores, bench/bench_team.py); starting anyway, expect a slow start and skipped SIPs")
    assert "50 on its 2 cores" not in capacity_warning(26, 1) and "25 on its 1 core," in capacity_warning(26, 1)


def test_cores_are_the_ones_this_process_may_use():
    assert cores() == len(os.sched_getaffinity(0))


class _Team:
    """Isolates the warning from starting 200 agents: the team is built, and its start fails at once."""

    def __init__(self, scenario, **kw):
        from erni.sim.team import TeamError

        self.error = TeamError
        self.run_dir, self.names = kw["run_dir"], scenario.robot_names()
        self.placement = None  # where the agents run does not matter to the warning

    def start(self, progress, timeout):
        raise self.error("start skipped by the test")

    def stop(self):
        pass


def parse(*argv: str) -> argparse.Namespace:
    parser = argparse.ArgumentParser()
    sim.register(parser.add_subparsers())
    return parser.parse_args(["sim", *argv])


@pytest.mark.parametrize("robots,hosts,here,warned", [(200, [], None, True), (50, [], None, False),
                                                      (100, ["127.0.0.2"], None, False),
                                                      (200, ["127.0.0.2", "127.0.0.3"], None, True),
                                                      (200, ["127.0.0.2"], 20, False), (80, ["127.0.0.2"], 60, True)])
def test_erni_sim_says_it_on_stderr_before_it_starts(robots, hosts, here, warned, monkeypatch, tmp_path, capfd):
    """Only this host's share counts: 100 robots over two hosts is 50 here."""
    import erni.sim.team

    monkeypatch.setattr(erni.sim.team, "Team", _Team)
    monkeypatch.setattr(sim, "cores", lambda: 2)
    monkeypatch.setattr(os, "umask", lambda mask: 0o022)  # run() sets the process's umask; not the test's
    placed = [arg for host in hosts for arg in ("--agent-host", host)] + (["--listen", "127.0.0.1"] if hosts else []) \
        + (["--agents-here", str(here)] if here is not None else [])
    assert sim.run(parse("--headless", "--robots", str(robots), "--run-dir", str(tmp_path), *placed)) == 1
    out, err = capfd.readouterr()
    lines = err.splitlines()
    if warned:
        share = here if here is not None else -(-robots // (1 + len(hosts)))
        assert lines[0].startswith(f"erni sim: {share} robots is more than this machine "
                                   "is measured to hold")
        assert lines[1] == "erni sim: start skipped by the test"
    else:
        assert lines == ["erni sim: start skipped by the test"]
    assert "starting..." in out
