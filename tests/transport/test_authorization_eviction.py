"""Idle strangers before authentication never lock out a client that authenticates at once."""

from __future__ import annotations

import socket

from erni.blackboard.testing import wait_until
from tests.transport.helpers import free_port, make_agent, make_client


def counters(agent) -> dict[str, int]:
    return agent.plugin("transport").endpoint.counters


def addr_of(agent) -> tuple[str, int]:
    return agent.plugin("transport").address


def test_idle_strangers_from_the_clients_own_address_do_not_lock_it_out():
    """500 idle connections from 127.0.0.1 held the cap of that address: the command-line client,
    connecting from the same address, was refused. The oldest stranger of the host now makes room."""
    control = make_agent("control", free_port(), echo=False, frame_timeout=30.0)
    flood = []
    try:
        for _ in range(500):  # each connection made before the next (a full listen backlog waits)
            try:
                flood.append(socket.create_connection(addr_of(control), timeout=5))
            except OSError:
                pass
        handled = ("closed.evicted", "refused.connections")
        per_host = control.plugin("transport").endpoint.limits.max_connections_per_host
        assert len(flood) > 400
        # every stranger beyond the host's cap is evicted or refused once the agent accepted it
        wait_until(lambda: sum(counters(control).get(c, 0) for c in handled) >= len(flood) - per_host, timeout=40)
        client = make_client(addr_of(control))
        try:
            client.send(addr_of(control), "peers.request", None)
            wait_until(lambda: (m := client.receive(0.1)) is not None and m.kind == "peers.reply", timeout=15)
        finally:
            client.endpoint.stop()
    finally:
        for s in flood:
            s.close()
        control.stop()
