"""The `erni` command: one sub-command per module in `erni.commands`.

Each module in `erni/commands/` defines `register(subparsers)`, which adds its parser and
sets `func` (a callable taking the parsed arguments and returning an exit code). `COMMANDS`
names each sub-command's module and one-line help, so that `erni stop` imports the stop's
module and not the simulator's: only the chosen command's module is imported, and the others
appear in `erni --help` by their line of help alone. `build_parser()` without a command
registers them all (the reference pages read every option of every command from it).
"""

from __future__ import annotations

import argparse
import gc
import importlib
import os
import sys
from typing import Any

import erni

# sub-command -> (its module in erni.commands, its one-line help: the same as its register() gives,
# which tests/core/test_cli_startup.py checks)
COMMANDS: dict[str, tuple[str, str]] = {
    "agent": ("agent", "run one agent from a TOML config until Ctrl-C"),
    "console": ("console", "type commands to the team in the speech grammar"),
    "experiment": ("experiment", "run one of the papers' experiments headless and write its figure and metrics"),
    "keys": ("keys", "make a team authority, issue and revoke agent identities"),
    "net-sim": ("net_sim", "simulate a MANET and serve each node's NHDP/OLSRv2/ERNI MIBs over SNMP"),
    "peers": ("peers", "list known agents and whether they are heard"),
    "record": ("record", "record a team's tasks, results, poses and peer events"),
    "replay": ("replay", "replay a recorded log or MCAP bag into a control node"),
    "robot-sim": ("robot_sim", "run simulated ARCOS robots (MobileSim-compatible port 8101)"),
    "router": ("router", "run a Zenoh router for a team on wire = \"zenoh\""),
    "sim": ("sim", "run a whole simulated team on this machine until Ctrl-C"),
    "stop": ("stop", "stop robots of a running team (every robot without names)"),
    "task": ("task", "send a task to an agent and print its result"),
    "tasks": ("tasks", "print the task language"),
    "watch": ("watch", "stream poses, results and peer events as lines"),
}


def register(sub: Any, name: str) -> None:
    """Add sub-command `name` to `sub` with every option its module gives it."""
    module = importlib.import_module(f"erni.commands.{COMMANDS[name][0]}")
    module.register(sub)


def build_parser(command: str | None = None) -> argparse.ArgumentParser:
    """Return the top-level parser: with every sub-command's own parser (`command` None), or with only
    `command`'s (the others listed by name and help, their modules not imported)."""
    parser = argparse.ArgumentParser(
        prog="erni",
        description="ERNI: teams of mobile robots on wireless ad-hoc networks.",
    )
    parser.add_argument("--version", action="version", version=f"erni {erni.__version__}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for name, (_, helptext) in sorted(COMMANDS.items()):
        if command is None or name == command:
            register(sub, name)
        else:
            sub.add_parser(name, help=helptext, add_help=False)
    return parser


def chosen(argv: list[str]) -> str:
    """The sub-command `argv` names ('' for none: `erni`, `erni --help`, `erni --version`, a typo)."""
    first = next((a for a in argv if not a.startswith("-")), "")
    return first if first in COMMANDS else ""


def main(argv: list[str] | None = None) -> int:
    """Run the `erni` command line; return the process exit code."""
    collecting, frozen = gc.isenabled(), gc.get_freeze_count()
    # importing builds thousands of objects that live until the process ends (the task language's
    # models, the wire's types): the collector, left on, would walk them again and again for nothing
    gc.disable()
    try:
        return _main(sys.argv[1:] if argv is None else list(argv))
    finally:  # as it was, for a caller in-process (erni task freezes what its start built)
        if not frozen:
            gc.unfreeze()
        if collecting:
            gc.enable()


def _main(argv: list[str]) -> int:
    command = chosen(argv)
    parser = build_parser(command or "")
    args = parser.parse_args(argv)
    if not getattr(args, "func", None):
        parser.print_help(sys.stderr)
        return 2
    if not getattr(args, "collect_later", False):  # a command that sends first turns the collector on itself
        gc.enable()
    from erni.blackboard.errors import ErniError
    from erni.commands._text import say

    try:
        return int(args.func(args) or 0)
    except KeyboardInterrupt:
        return 130
    except BrokenPipeError:  # `erni watch | head -1`: the reader is gone; end quietly, as Unix tools do
        quiet = os.open(os.devnull, os.O_WRONLY)
        os.dup2(quiet, sys.stdout.fileno())  # what is still buffered goes nowhere, not into a traceback
        return 141  # 128 + SIGPIPE: what a shell reports for a tool the closed pipe ended
    except ErniError as err:  # what a command did not catch itself (a network that cannot be opened ...)
        say(f"erni {args.command}: {str(err).splitlines()[0] if str(err) else type(err).__name__}", file=sys.stderr)
        return 1
