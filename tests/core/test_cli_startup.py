"""What `import erni` and the `erni` command line import before they act: none of the heavy parts.

A stop from the command line is only as quick as the command starts, so `import erni`, building
the parser of `erni stop` or `erni task` and `erni --help` import neither the agent, pydantic,
numpy nor aiohttp (each checked in a fresh interpreter's `sys.modules`). How quick it is, is
measured by bench/bench_cli.py, never timed here. The names `erni`, `erni.blackboard` and
`erni.transport` offer are imported when first used, and each still resolves.
"""

from __future__ import annotations

import argparse
import importlib
import json
import pkgutil
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
HEAVY = ["erni.blackboard.agent", "erni.transport.endpoint", "erni.transport.plugin", "erni.sim", "erni.plugins",
         "pydantic", "numpy", "aiohttp"]


def imported_after(code: str) -> list[str]:
    """The modules of `HEAVY` that a fresh interpreter has imported after running `code`."""
    probe = f"{code}\nimport json, sys\nprint(json.dumps([m for m in {HEAVY!r} if m in sys.modules]))"
    out = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True, timeout=60, cwd=ROOT)
    assert out.returncode == 0, out.stderr
    return list(json.loads(out.stdout.splitlines()[-1]))


@pytest.mark.parametrize("code", [
    "import erni",
    "import erni; erni.__version__",
    "import erni.blackboard, erni.transport",
    "import erni.cli; erni.cli.build_parser('stop')",
    "import erni.cli; erni.cli.build_parser('task')",
    "import erni.cli; erni.cli.build_parser('')",
    "import erni.cli; erni.cli.build_parser('stop').parse_args(['stop', '--via', '127.0.0.1:1', 'robot1'])",
])
def test_importing_erni_and_building_a_parser_pull_in_nothing_heavy(code):
    assert imported_after(code) == []


@pytest.mark.parametrize("argv", [["--help"], ["stop", "--help"], ["task", "--help"], ["--version"]])
def test_the_help_of_the_command_line_pulls_in_nothing_heavy(argv):
    code = f"import erni.cli\ntry:\n    erni.cli.main({argv!r})\nexcept SystemExit:\n    pass"
    assert imported_after(code) == []


def test_the_language_is_imported_without_the_agent():
    """`from erni import Task` (what a command sending a task needs) does not bring the agent."""
    assert imported_after("from erni import Task, GotoParams") == ["pydantic"]


@pytest.mark.parametrize("package", ["erni", "erni.blackboard", "erni.transport"])
def test_every_public_name_still_resolves(package):
    module = importlib.import_module(package)
    for name in module.__all__:
        assert getattr(module, name) is not None, name
    assert set(module.__all__) <= set(dir(module))
    namespace: dict[str, object] = {}
    exec(f"from {package} import *", namespace)  # noqa: S102
    assert set(module.__all__) <= set(namespace)
    with pytest.raises(AttributeError):
        module.no_such_name  # noqa: B018


def test_a_sub_package_is_reached_from_the_package():
    code = "import erni\nprint(erni.blackboard.agent.Agent.__name__, erni.transport.wire.Message.__name__)"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60, cwd=ROOT)
    assert out.stdout.split() == ["Agent", "Message"], out.stderr


def test_the_command_table_names_every_command_module_with_its_own_help():
    from erni.cli import COMMANDS, build_parser

    modules = {m.name for m in pkgutil.iter_modules(importlib.import_module("erni.commands").__path__)
               if not m.name.startswith("_")}
    assert sorted(module for module, _ in COMMANDS.values()) == sorted(modules)
    full = build_parser()
    (sub,) = [a for a in full._actions if isinstance(a, argparse._SubParsersAction)]
    assert sorted(sub.choices) == sorted(COMMANDS)
    helps = {a.dest: a.help for a in sub._choices_actions}
    assert helps == {name: text for name, (_, text) in COMMANDS.items()}


def test_erni_help_lists_every_command_as_the_full_parser_does():
    from erni.cli import build_parser

    assert build_parser("").format_help() == build_parser().format_help()


def test_a_stop_is_the_one_the_console_sends_in_each_tier():
    from erni.commands.stop import STOP, stops
    from erni.plugins.ui.dialogue import tasks_for

    for verb in STOP:
        (mine,) = stops(verb, ["robot1"], "cli")
        (console,) = tasks_for("stop", {}, ["robot1"], verb=verb, source="cli")
        assert (mine.verb, mine.preposition, mine.params) == (console.verb, console.preposition, console.params)
