"""Run one agent from its TOML config until SIGINT or SIGTERM: what `erni agent` does, and what a
launcher that runs the same agent behind something of its own (the simulator's radio,
`erni.sim.radio`) calls, without reaching up into the command line.

`add_arguments` gives a parser the agent's arguments, `run` builds, starts and stops the agent.
What it prints goes out one line per event with its control characters escaped, as the
commands print (`erni.blackboard.text.printable`).
"""

from __future__ import annotations

import argparse
import os
import signal
import sys
import threading
from collections.abc import Callable
from typing import IO, Any

from erni.blackboard import heap
from erni.blackboard.agent import Agent
from erni.blackboard.config import build_agent, read_config
from erni.blackboard.errors import ConfigError, ErniError
from erni.blackboard.text import printable
from erni.logs import setup_logging

__all__ = ["add_arguments", "run"]


def add_arguments(p: argparse.ArgumentParser) -> None:
    """The arguments of `erni agent` (shared with launchers that run the same agent)."""
    p.add_argument("config", help="agent config file (TOML)")
    p.add_argument("--log-level", choices=["DEBUG", "INFO", "WARNING", "ERROR"],
                   help="override the config's [agent] log_level")
    p.add_argument("--check", action="store_true", help="validate the config and exit")
    p.add_argument("--stop-grace", type=float, default=5.0, metavar="SECONDS",
                   help="after SIGINT or SIGTERM, exit at once if a clean stop has not finished "
                        "within this many seconds (default 5), naming the threads still busy")
    p.add_argument("--reset-journal", action="store_true",
                   help="if the journal cannot be read, move it aside (NAME.bad-N) and start empty")


def run(args: argparse.Namespace, prepare: Callable[[Agent], None] | None = None) -> int:
    """Load the config, start the agent, wait for a signal, stop cleanly.

    `prepare(agent)` runs after the agent is built and before it starts (a launcher's hook).
    """
    try:
        config = read_config(args.config)
        agent = build_agent(config, args.config)
    except ConfigError as err:
        _say_lines(str(err), file=sys.stderr)  # one line per problem of the file
        return 2
    agent.reset_journal = args.reset_journal
    if prepare is not None:
        prepare(agent)
    if args.check:
        _say(f"{args.config}: ok (agent {config.agent.name}, "
              f"{len(agent.plugins)} plugin(s): {', '.join(p.name for p in agent.plugins)})")
        return 0
    setup_logging(args.log_level or config.agent.log_level)
    heap.cap_arenas()   # before the agent's threads start: one malloc arena for all of them
    stop = threading.Event()
    running = threading.Event()

    fired: list[int] = []

    def on_signal(signum: int, frame: Any) -> None:
        # A second signal may come while this handler is inside stop.set(), holding the event's
        # lock (a killed launcher's death signal comes once per thread of it that exits): the
        # plain flag, set before the lock is taken, keeps that nested call off the lock.
        if fired:
            return
        fired.append(signum)
        stop.set()
        watchdog = threading.Timer(args.stop_grace, _exit_hard, (config.agent.name, args.stop_grace))
        watchdog.daemon = True
        watchdog.start()
        if not running.is_set():
            raise KeyboardInterrupt   # a start still setting up (or waiting on a peer) is abandoned

    previous = {s: signal.signal(s, on_signal) for s in (signal.SIGINT, signal.SIGTERM)}
    try:
        try:
            agent.start()
            heap.freeze()   # what start-up made lives as long as the process: no full collection rescans it
            heap.trim()     # and what it made and dropped goes back to the system
            running.set()
        except KeyboardInterrupt:   # from on_signal: the stop came during the start
            return 0
        except (ErniError, OSError) as err:
            _say(f"{args.config}: cannot start agent {config.agent.name}: {str(err).splitlines()[0]}",
                  file=sys.stderr)
            return 2
        stop.wait()   # the signal handler sets it (a blocked wait in the main thread runs handlers)
    finally:
        agent.stop()
        for s, handler in previous.items():
            signal.signal(s, handler)
    return 0


def _exit_hard(name: str, grace: float) -> None:
    """The stop watchdog: a stop that outlives its grace ends the process, naming what was busy."""
    busy = sorted(t.name for t in threading.enumerate() if t is not threading.current_thread()
                  and t is not threading.main_thread())
    _say(f"agent {name}: did not stop within {grace:g} s of the signal; exiting now "
          f"(threads still running: {', '.join(busy) or 'main only'})", file=sys.stderr, flush=True)
    os._exit(3)


def _say(text: str, *, file: IO[str] | None = None, flush: bool = False) -> None:
    print(printable(text), file=file or sys.stdout, flush=flush)


def _say_lines(text: str, *, file: IO[str] | None = None) -> None:
    for line in text.split("\n"):
        _say(line, file=file)
