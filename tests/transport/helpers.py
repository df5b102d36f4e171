"""Agents with a transport on loopback, for the transport tests."""

from __future__ import annotations

import socket
from typing import Any

from erni.blackboard import Agent

KEY = "test-team-key"


def free_port(kind: int = socket.SOCK_DGRAM) -> int:
    with socket.socket(socket.AF_INET, kind) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def make_agent(name: str, discovery_port: int, *, echo: bool = True, start: bool = True,
               **settings: Any) -> Agent:
    """An agent with the transport (fast timings) and, optionally, the echo performer."""
    agent = Agent(name, workers=2)
    base: dict[str, Any] = {"key": KEY, "discovery_port": discovery_port, "beacon_period": 0.1,
                            "peer_timeout": 0.6, "ack_timeout": 0.3, "connect_timeout": 0.3,
                            "task_ttl": 5.0}
    base.update(settings)
    agent.add_plugin("transport", settings=base, name="transport")
    if echo:
        agent.add_plugin("echo", settings={"verbs": ["BotMotion"], "delay": 0.05}, name="motion")
    return agent.start() if start else agent
