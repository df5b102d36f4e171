"""The architecture's rules, checked on the import graph and on the source.

The contracts live in `.importlinter` at the repository's root (import-linter reads it; `lint-imports` runs
them by hand): the layers (command line over simulator over plugins over transport over blackboard), runtime
code importing neither the simulator nor the command line, the shared libraries importing no plugin, and the
plugins independent of each other. Here each contract is checked on ERNI's graph, and each is shown to fail
when a break of it is put back (an import added to a copy of the graph): a contract that cannot fail checks
nothing. What import-linter cannot see, a plugin reaching into another plugin's attributes through the
agent's list of plugins, is read off the source.
"""

from __future__ import annotations

import ast
import copy
import pathlib
from typing import Any

import grimp
import pytest
from importlinter import api
from importlinter.contracts.forbidden import ForbiddenContract
from importlinter.contracts.independence import IndependenceContract
from importlinter.contracts.layers import LayersContract

ROOT = pathlib.Path(__file__).resolve().parents[1]
CONFIG = ROOT / ".importlinter"
KINDS: dict[str, type[Any]] = {"layers": LayersContract, "forbidden": ForbiddenContract,
                               "independence": IndependenceContract}


@pytest.fixture(scope="module")
def options() -> dict[str, Any]:
    return api.read_configuration(str(CONFIG))


@pytest.fixture(scope="module")
def graph(options: dict[str, Any]) -> grimp.ImportGraph:
    return grimp.build_graph(*options["session_options"]["root_packages"], include_external_packages=False,
                             cache_dir=None)


def _contract(options: dict[str, Any], key: str) -> Any:
    found = next(c for c in options["contracts_options"] if c["id"] == key)
    return KINDS[found["type"]](name=found["name"], session_options=options["session_options"],
                                contract_options=found)


def _check(options: dict[str, Any], key: str, graph: grimp.ImportGraph) -> Any:
    return _contract(options, key).check(copy.deepcopy(graph), verbose=False)


def test_the_contracts_are_the_ones_documented(options: dict[str, Any]) -> None:
    assert sorted(c["id"] for c in options["contracts_options"]) == ["layers", "libraries", "plugins", "runtime"]


@pytest.mark.parametrize("key", ["layers", "runtime", "libraries", "plugins"])
def test_erni_keeps_each_contract(options: dict[str, Any], graph: grimp.ImportGraph, key: str) -> None:
    check = _check(options, key, graph)
    assert check.kept, check.metadata


def test_every_part_of_erni_is_under_a_contract(options: dict[str, Any], graph: grimp.ImportGraph) -> None:
    """A new top-level module or package of `erni` is placed in the layers or named as runtime code."""
    named: set[str] = set()
    for contract in options["contracts_options"]:
        for field in ("layers", "source_modules", "modules"):
            named.update(m.strip("() ") for line in contract.get(field, []) for m in line.replace(":", "|").split("|"))
    tops = {".".join(m.split(".")[:2]) for m in graph.modules} - {"erni"}
    assert sorted(tops - named) == []


# Each break: (contract, importer, imported) — an import the architecture refuses, put back on a copy of the graph.
BREAKS = [
    ("layers", "erni.sim.radio", "erni.commands.agent"),             # the simulator's radio on the command line
    ("layers", "erni.transport.plugin", "erni.plugins.motion"),      # the transport on a plugin
    ("layers", "erni.blackboard.agent", "erni.transport.plugin"),    # the blackboard on the transport
    ("runtime", "erni.plugins.ui.plugin", "erni.sim.team"),          # a plugin on the simulator
    ("runtime", "erni.replay", "erni.commands.replay"),              # a library on the command line
    ("libraries", "erni.replay", "erni.plugins.ros2.bags"),          # replay on a plugin's module
    ("libraries", "erni.ros2_rmw", "erni.plugins.ros2.plugin"),
    ("plugins", "erni.plugins.ros2.plugin", "erni.transport.plugin"),  # allowed: a plugin over the transport
    ("plugins", "erni.plugins.ui.dialogue", "erni.plugins.mission"),   # one plugin on another
    ("plugins", "erni.plugins.mission.plugin", "erni.plugins.mobinet.snmp"),
]


@pytest.mark.parametrize(("key", "importer", "imported"), BREAKS)
def test_each_contract_fails_when_a_break_is_put_back(options: dict[str, Any], graph: grimp.ImportGraph, key: str,
                                                       importer: str, imported: str) -> None:
    broken = copy.deepcopy(graph)
    broken.add_import(importer=importer, imported=imported, line_number=1, line_contents=f"import {imported}")
    check = _check(options, key, broken)
    if (key, imported) == ("plugins", "erni.transport.plugin"):
        assert check.kept  # the control: an import the contracts allow keeps them kept
    else:
        assert not check.kept, f"{key} kept with {importer} -> {imported}"


# --- what the import graph does not show ----------------------------------------------------------

PLUGIN_DIRS = ("plugins", "transport")


def reaches_into_plugins(source: str) -> list[int]:
    """Lines of `source` that read the agent's list of plugins (`agent.plugins`, `self._require_agent().plugins`):
    the way to another plugin's attributes. What one plugin offers another goes on the blackboard or through
    `Agent.provide` / `Plugin.provided`."""
    return sorted(node.lineno for node in ast.walk(ast.parse(source))
                  if isinstance(node, ast.Attribute) and node.attr == "plugins" and isinstance(node.ctx, ast.Load))


def test_the_reach_check_sees_a_plugin_reading_another_ones_attributes() -> None:
    assert reaches_into_plugins("for p in self._require_agent().plugins:\n    s = p.endpoint.session\n") == [1]
    assert reaches_into_plugins("x = agent.plugins[0].resource\n") == [1]
    assert reaches_into_plugins("import erni.plugins\nfrom erni.plugins import motion\ns = self.provided('x')\n") == []




def test_no_plugin_reaches_into_another_plugins_attributes() -> None:
    found: dict[str, int] = {}
    for folder in PLUGIN_DIRS:
        for path in sorted((ROOT / folder).rglob("*.py")):
            lines = reaches_into_plugins(path.read_text(encoding="utf-8"))
            if lines:
                found[str(path.relative_to(ROOT))] = len(lines)
    assert found == {}
