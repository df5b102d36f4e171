"""Creeping out of radio range on the real mesh: babeld's late, noisy qualities, and the guard.

The same bed as tests/sim/test_creep.py, in network namespaces: MobiNet reads babeld (Hellos
every 0.5 s), the radio is nftables' loss between the nodes' ports. One round clean, one with
30 % of every frame on every link dropped (babeld's qualities, the transport and the Hellos all
suffer) in the same team.
"""

from __future__ import annotations

import pytest

from erni.sim import creep
from erni.sim.scenario import find_scenario, load_scenario
from erni.sim.team import Team
from tests.netns.creep_helpers import assert_held, one_round

pytestmark = [pytest.mark.netns, pytest.mark.slow]


def test_creeping_robots_stand_inside_range_on_babelds_readings_clean_and_at_thirty_percent_loss(tmp_path):
    team = Team(load_scenario(find_scenario("creep")), run_dir=tmp_path, headless=True,
                transport={"beacon_period": 0.3, "peer_timeout": 1.5, "task_ttl": 60.0}, netns=True, mission=True)
    try:
        team.start(timeout=120)
        assert_held(one_round(team, creep.SPEEDS, rest=8.0))
        assert team.mesh is not None
        team.mesh.set_extra_loss(0.3)
        assert_held(one_round(team, creep.SPEEDS, number=2, rest=8.0))
    finally:
        team.stop()
    assert team.mesh is not None and team.mesh.leftovers() == []
