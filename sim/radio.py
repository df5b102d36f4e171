"""The simulated radio as each agent of `erni sim` hears it: an inbound filter of its transport.

The launcher knows from the radio model which agents can reach each other (directly or over
several hops) and pushes, for every agent, the names it can hear through a pipe the agent
inherits, one JSON list per line, whenever that changes. The agent process is started as
`python -m erni.sim.radio CONFIG` — the same agent as `erni agent CONFIG` — with its transport
given `RadioFilter.allows` as its inbound filter. Frames from agents the radio cannot carry
are dropped on arrival and counted (`dropped.unreachable`); command-line clients (role `cli`)
are not on the simulated radio and always pass. The real-mesh tier drops packets in the
kernel instead and needs none of this.
"""

from __future__ import annotations

import argparse
import json
import logging
import os
import sys
import threading

from erni.blackboard.agent import Agent
from erni.transport.plugin import TransportPlugin

FD_ENV = "ERNI_SIM_RADIO_FD"
"""Environment variable naming the inherited pipe the launcher writes reachability to."""

log = logging.getLogger("erni.sim.radio")


class RadioFilter:
    """Which senders this agent hears now; updated by a thread reading the launcher's pipe."""

    def __init__(self, fd: int | None = None) -> None:
        self._allowed: frozenset[str] | None = None  # None: not restricted (yet)
        self.updates = 0
        self._thread: threading.Thread | None = None
        if fd is not None:
            self._thread = threading.Thread(target=self._read, args=(fd,), name="sim-radio", daemon=True)
            self._thread.start()

    def allows(self, sender: str, role: str) -> bool:
        """True when a frame from `sender` (of `role`) reaches this agent through the simulated radio."""
        allowed = self._allowed
        return allowed is None or role == "cli" or sender in allowed

    def set(self, names: list[str] | None) -> None:
        """Hear exactly `names` from now on (None: everyone)."""
        self._allowed = None if names is None else frozenset(names)
        self.updates += 1

    def _read(self, fd: int) -> None:
        with os.fdopen(fd, "r", encoding="utf-8") as pipe:
            for line in pipe:  # blocks until the launcher writes: nothing polls
                try:
                    names = json.loads(line)
                except ValueError:
                    log.warning("sim radio: ignored a reachability line that is not JSON: %.60r", line)
                    continue
                if names is None or (isinstance(names, list) and all(isinstance(n, str) for n in names)):
                    self.set(names)
                else:
                    log.warning("sim radio: ignored a reachability line that is not a list of names: %.60r", line)


def install(agent: Agent, radio: RadioFilter) -> None:
    """Give every transport of `agent` the radio as its inbound filter (before the agent starts)."""
    for plugin in agent.plugins:
        if isinstance(plugin, TransportPlugin):
            plugin.inbound_filter = radio.allows


def main(argv: list[str] | None = None) -> int:
    """`python -m erni.sim.radio CONFIG [--log-level L]`: `erni agent` behind the simulated radio."""
    from erni import launch

    parser = argparse.ArgumentParser(prog="python -m erni.sim.radio",
                                     description="Run an agent of `erni sim` behind the simulated radio.")
    launch.add_arguments(parser)
    args = parser.parse_args(argv)
    fd = os.environ.get(FD_ENV)
    radio = RadioFilter(int(fd) if fd else None)
    return launch.run(args, prepare=lambda agent: install(agent, radio))


if __name__ == "__main__":
    sys.exit(main())
