"""The `erni` command: one sub-command per module in `erni.commands`.

Each module in `erni/commands/` defines `register(subparsers)`, which adds its parser and
sets `func` (a callable taking the parsed arguments and returning an exit code).
"""

from __future__ import annotations

import argparse
import importlib
import os
import pkgutil
import sys

import erni
import erni.commands
from erni.blackboard.errors import ErniError
from erni.commands._text import say


def build_parser() -> argparse.ArgumentParser:
    """Return the top-level parser with every sub-command found in `erni.commands`."""
    parser = argparse.ArgumentParser(
        prog="erni",
        description="ERNI: teams of mobile robots on wireless ad-hoc networks.",
    )
    parser.add_argument("--version", action="version", version=f"erni {erni.__version__}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for info in sorted(pkgutil.iter_modules(erni.commands.__path__), key=lambda m: m.name):
        if info.name.startswith("_"):
            continue
        module = importlib.import_module(f"erni.commands.{info.name}")
        module.register(sub)
    return parser


def main(argv: list[str] | None = None) -> int:
    """Run the `erni` command line; return the process exit code."""
    parser = build_parser()
    args = parser.parse_args(argv)
    if not getattr(args, "func", None):
        parser.print_help(sys.stderr)
        return 2
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
