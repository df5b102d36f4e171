"""SnmpSource's per-part cache hands back what was walked, whichever parts a later read asks for."""

from __future__ import annotations

import asyncio

from erni.plugins.mobinet.resource import NEIGHBORS, POSITIONS
from erni.plugins.mobinet.snmp import SnmpSource


def test_a_cached_part_is_reused_by_a_read_of_other_parts(served):
    async def go():
        src = SnmpSource(*served["robot3"], timeout=10.0)  # the simulated agent answers from this process
        try:
            first = await src.read(frozenset({NEIGHBORS}))
            # same topology version: the neighbour walk comes from the cache, the positions are walked
            second = await src.read(frozenset({NEIGHBORS, POSITIONS}))
            return first, second
        finally:
            await src.aclose()

    first, second = asyncio.run(go())
    assert {n.name for n in first.neighbors} == {"robot2", "robot4"}
    assert {n.name for n in second.neighbors} == {"robot2", "robot4"}
    assert set(second.positions) == {"robot1", "robot2", "robot3", "robot4", "robot5"}
