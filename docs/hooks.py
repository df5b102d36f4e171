"""MkDocs hook: the reference pages' tables, generated from the code at build time.

A page of the site asks for a generated part with a marker on a line of its own,
`<!-- erni-reference: NAME -->`; `on_page_markdown` replaces it with `render(NAME)`. Nothing
generated is committed: the parsers, the settings models, the task registry, the role policy,
the frame kinds, the MIB module and the benchmark results are read as the site is built, so a
reference page cannot say what the code does not do. tests/test_site.py reads `render` too.
"""

from __future__ import annotations

import argparse
import enum
import json
import re
import types
import typing
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]
MARKER = re.compile(r"^<!-- erni-reference: ([a-z-]+) -->$", re.M)
RESULTS = ROOT / "bench" / "results"

# -- shared helpers ------------------------------------------------------------------------


def cell(text: object) -> str:
    """Text that stays in one cell of a Markdown table."""
    return " ".join(str(text).split()).replace("|", "\\|")


def code(text: object) -> str:
    """Inline code of any text (backticks inside are doubled around)."""
    text = cell(text)
    return f"`` {text} ``" if "`" in text else f"`{text}`"


# -- the command line ------------------------------------------------------------------------


def _subcommands(parser: argparse.ArgumentParser) -> list[tuple[str, str, argparse.ArgumentParser]]:
    """(name, help, parser) of each sub-command of `parser`, in the order they were added."""
    found = []
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            helps = {a.dest: a.help or "" for a in action._choices_actions}
            for name, sub in action.choices.items():
                found.append((name, helps.get(name, ""), sub))
    return found


def _option_row(parser: argparse.ArgumentParser, action: argparse.Action) -> str:
    formatter = parser._get_formatter()
    if action.option_strings:
        metavar = "" if action.nargs == 0 else " " + formatter._format_args(action, action.dest.upper())
        names = ", ".join(f"{code(o + metavar)}" for o in action.option_strings)
    else:
        names = code(formatter._format_args(action, action.dest))
    text = formatter._expand_help(action) if action.help else ""
    default = action.default
    shown = "" if default in (None, False, argparse.SUPPRESS) or action.nargs == 0 or not action.option_strings \
        else code(default if not isinstance(default, list) else " ".join(map(str, default)))
    return f"| {names} | {shown} | {cell(text)} |"


def commands() -> list[tuple[str, argparse.ArgumentParser, str]]:
    """Every `erni` command, sub-commands included: (its words, its parser, its one-line help)."""
    from erni.cli import build_parser

    out: list[tuple[str, argparse.ArgumentParser, str]] = []

    def walk(prefix: str, parser: argparse.ArgumentParser) -> None:
        for name, helptext, sub in _subcommands(parser):
            out.append((f"{prefix} {name}", sub, helptext))
            walk(f"{prefix} {name}", sub)

    walk("erni", build_parser())
    return out


def render_cli() -> str:
    lines = ["| command | what it does |", "|---|---|"]
    every = commands()
    for words, _, helptext in every:
        lines.append(f"| [{code(words)}](#{_anchor(words)}) | {cell(helptext)} |")
    for words, parser, helptext in every:
        lines += ["", f"## {words} {{#{_anchor(words)}}}", ""]
        if parser.description and issubclass(parser.formatter_class, argparse.RawDescriptionHelpFormatter):
            lines += ["```text", parser.description.strip("\n"), "```", ""]  # laid out by its author
        elif parser.description and parser.description.strip() != helptext.strip():
            lines += [_paragraphs(parser.description), ""]
        elif helptext:
            lines += [cell(helptext), ""]
        usage = parser.format_usage().removeprefix("usage: ").strip()
        lines += ["```text", usage, "```", ""]
        rows = [a for a in parser._actions if not isinstance(a, (argparse._HelpAction, argparse._SubParsersAction))]
        if rows:
            lines += ["| option | default | meaning |", "|---|---|---|"]
            lines += [_option_row(parser, a) for a in rows]
        if parser.epilog:
            lines += ["", _paragraphs(parser.epilog)]
    return "\n".join(lines)


def _paragraphs(text: str) -> str:
    """A parser's description as Markdown: its paragraphs kept, a table in it kept as a table."""
    out = []
    for para in re.split(r"\n\s*\n", text.strip()):
        lines = [line.strip() for line in para.splitlines()]
        out.append("\n".join(lines) if lines and lines[0].startswith("|") else " ".join(lines))
    return "\n\n".join(out)


def _anchor(words: str) -> str:
    return words.replace(" ", "-")


# -- settings models ------------------------------------------------------------------------

UNITS = ("s", "m", "Hz", "m/s", "m/s^2", "deg", "deg/s", "V", "bytes", "hops", "mm", "ms", "dBFS")
UNIT_WORDS = {"seconds": "s", "volts": "V", "metres": "m", "a second": "Hz", "per second": "Hz"}
_UNIT = re.compile(r"\((" + "|".join(re.escape(u) for u in UNITS) + r")(?:[;,)]| =| \()")


def unit_of(description: str | None) -> str:
    """The unit a setting's description names: `(s)`, `(m)`, `(Hz)` ... or a unit word; '' if none."""
    if not description:
        return ""
    found = _UNIT.search(description + ")")
    if found:
        return found.group(1)
    for word, unit in UNIT_WORDS.items():
        if re.search(rf"\b{word}\b", description):
            return unit
    return ""


def type_name(annotation: Any) -> str:
    """A field's type as a reader of a TOML file sees it."""
    origin = typing.get_origin(annotation)
    args = typing.get_args(annotation)
    if origin is typing.Literal:
        return " or ".join(json.dumps(a) for a in args)
    if origin in (typing.Union, types.UnionType):
        parts = [type_name(a) for a in args if a is not type(None)]
        return " or ".join(parts) + (" (optional)" if type(None) in args else "")
    if origin is typing.Annotated:
        return type_name(args[0])
    if origin in (list, tuple, dict):
        inner = ", ".join(type_name(a) for a in args if a is not Ellipsis)
        return f"{'table' if origin is dict else 'list'} of {inner}" if inner else origin.__name__
    names = {str: "string", int: "integer", float: "number", bool: "boolean"}
    if annotation in names:
        return names[annotation]
    if isinstance(annotation, type) and issubclass(annotation, enum.Enum):
        return " or ".join(json.dumps(m.value) for m in annotation)
    name = getattr(annotation, "__name__", str(annotation))
    return {"SecretStr": "string (secret)", "Any": "any"}.get(name, name)


def _default(field: Any) -> str:
    if field.is_required():
        return "required"
    value = field.get_default(call_default_factory=True)
    if value is None:
        return "unset"
    if hasattr(value, "model_dump"):
        return "see below"
    if isinstance(value, enum.Enum):
        value = value.value
    return code(json.dumps(value) if isinstance(value, (str, list, dict, tuple, bool)) else value)


def _bounds(field: Any) -> str:
    marks = {"ge": "≥", "gt": ">", "le": "≤", "lt": "<"}
    out = []
    for meta in field.metadata:
        for attr, sign in marks.items():
            value = getattr(meta, attr, None)
            if value is not None:
                out.append(f"{sign} {value:g}" if isinstance(value, float) else f"{sign} {value}")
        pattern = getattr(meta, "pattern", None)
        if pattern:
            out.append(f"matches {code(pattern)}")
        max_length = getattr(meta, "max_length", None)
        if max_length is not None:
            out.append(f"at most {max_length} characters")
    return ", ".join(out)


def settings_rows(model: Any, prefix: str = "") -> Iterator[tuple[str, Any, Any]]:
    """(dotted name, field, model) of every setting of `model`, nested tables expanded."""
    for name, field in model.model_fields.items():
        shown = field.alias or name
        yield prefix + shown, field, model
        annotation = field.annotation
        if isinstance(annotation, type) and hasattr(annotation, "model_fields"):
            yield from settings_rows(annotation, f"{prefix}{shown}.")


def settings_table(model: Any) -> str:
    lines = ["| setting | type | default | unit | range | meaning |", "|---|---|---|---|---|---|"]
    for name, field, _ in settings_rows(model):
        lines.append(f"| {code(name)} | {cell(type_name(field.annotation))} | {_default(field)} | "
                     f"{unit_of(field.description)} | {_bounds(field)} | {cell(field.description or '')} |")
    return "\n".join(lines)


def plugins() -> list[tuple[str, type, Any]]:
    """(entry point name, plugin class, its settings model) of every plugin ERNI installs."""
    from importlib.metadata import entry_points

    from erni.blackboard.agent import ENTRY_POINT_GROUP, resolve_plugin
    from erni.blackboard.plugin import NoSettings

    found = []
    for ep in sorted(entry_points(group=ENTRY_POINT_GROUP), key=lambda e: e.name):
        if not ep.value.startswith("erni."):
            continue  # another distribution's plugin
        cls = resolve_plugin(ep.name)
        found.append((ep.name, cls, getattr(cls, "Settings", NoSettings) or NoSettings))
    return found


def render_settings() -> str:
    out = []
    for name, cls, model in plugins():
        doc = (cls.__doc__ or "").strip().splitlines()[0] if cls.__doc__ else ""
        out += [f"## `{name}` {{#{name}}}", "",
                f"`class = \"{name}\"`: {code(cls.__module__ + ':' + cls.__qualname__)}. {doc}", "",
                settings_table(model), ""]
    return "\n".join(out)


def render_agent() -> str:
    from erni.blackboard.config import AgentSection, PluginSection

    return "\n".join(["## `[agent]`", "", settings_table(AgentSection), "",
                      "## `[[plugin]]`", "", settings_table(PluginSection)])


# -- the task language -------------------------------------------------------------------------


def render_tasks() -> str:
    from erni.blackboard.tasks import VERBS, language_table

    lines = ["| verb | scope | handled by | meaning |", "|---|---|---|---|"]
    lines += [f"| `{v.name}` | {v.scope} | {v.handled_by} | {cell(v.doc)} |" for v in VERBS.values()]
    return "\n".join(lines + ["", language_table()])


# -- the role policy and the wire ---------------------------------------------------------------


def _docstring_table(doc: str) -> str:
    return "\n".join(line for line in doc.splitlines() if line.startswith("|"))


def render_policy() -> str:
    from erni.transport import policy

    status = ["| shared type | roles that publish it | field naming its owner | uid |", "|---|---|---|---|"]
    for type_name_, rule in policy.STATUS.items():
        roles = ", ".join(sorted("any role but cli" if r == policy.ANY else r for r in rule.roles))
        status.append(f"| `{type_name_}` | {roles} | `{rule.owner}` | {code(rule.uid) if rule.uid else ''} |")
    relays = ["| relay's role | may relay for |", "|---|---|"]
    relays += [f"| {r} | {', '.join(sorted(f))} |" for r, f in policy.RELAYS.items()]
    return "\n".join([
        "## Message kinds", "", _docstring_table(policy.__doc__ or ""), "",
        "## Tasks, by sender's and receiver's role", "", policy.table(), "",
        f"Roles that operate the team (task any agent, cancel any task, watch): "
        f"{', '.join(f'`{r}`' for r in sorted(policy.OPERATORS))}. "
        f"Roles that may watch and list peers: {', '.join(f'`{r}`' for r in sorted(policy.WATCHERS))}.", "",
        "## Relays", "", "\n".join(relays), "",
        "## Shared objects (status)", "", "\n".join(status), "",
        f"A registered type not listed travels as status only as an agent's own object naming it in "
        f"a field `{policy.DEFAULT_OWNER}`.",
    ])


def render_wire() -> str:
    from erni.transport import wire

    doc = (wire.__doc__ or "").strip().split("\n\n")
    grammar = "\n".join(line.removeprefix("    ") for line in doc[1].splitlines())
    kinds = ["| byte | kind |", "|---|---|"]
    kinds += [f"| `{chr(byte)}` (`{byte:#04x}`) | {name} |" for byte, name in wire.KINDS.items()]
    return "\n".join([
        cell(doc[0]), "", "```text", grammar, "```", "", "\n\n".join(cell(p) for p in doc[2:]), "",
        "## Frame kinds", "", "\n".join(kinds), "",
        f"Version {wire.VERSION}; the largest frame by default {wire.DEFAULT_MAX_FRAME} bytes "
        f"({wire.UDP_MAX_FRAME} in one datagram); JSON nested at most {wire.MAX_JSON_DEPTH} deep.", "",
        "## Envelope head", "", cell(wire.EnvelopeHead.__doc__ or ""), "", settings_table(wire.EnvelopeHead), "",
        "## Envelope item", "", cell(wire.EnvelopeItem.__doc__ or ""), "", settings_table(wire.EnvelopeItem),
    ])


# -- the MIB -----------------------------------------------------------------------------------

MIB = ROOT / "plugins" / "mobinet" / "mibs" / "ERNI-MOBINET-MIB.txt"
_DEF = re.compile(r"^(\w+)[ \t]+(OBJECT-TYPE|OBJECT IDENTIFIER|OBJECT-IDENTITY|MODULE-IDENTITY|OBJECT-GROUP|"
                  r"MODULE-COMPLIANCE)\b(.*?)::=\s*\{\s*([\w-]+)\s+([\d\s]+)\}", re.S | re.M)


def mib_objects(text: str | None = None) -> list[dict[str, str]]:
    """The module's definitions in order: name, kind, OID, and for objects SYNTAX, UNITS, access, text."""
    text = text if text is not None else MIB.read_text(encoding="utf-8")
    text = re.sub(r"--[^\n]*", "", text)
    oids: dict[str, str] = {"enterprises": "1.3.6.1.4.1"}
    out = []
    for m in _DEF.finditer(text):
        name, kind, body, parent, numbers = m.groups()
        oid = ".".join([oids.get(parent, parent), *numbers.split()])
        oids[name] = oid
        item = {"name": name, "kind": kind, "oid": oid}
        for key, pattern in (("syntax", r"SYNTAX\s+(.*?)\n\s*(?:UNITS|MAX-ACCESS)"), ("units", r'UNITS\s+"([^"]*)"'),
                             ("access", r"MAX-ACCESS\s+([\w-]+)"), ("description", r'DESCRIPTION\s+"([^"]*)"'),
                             ("index", r"INDEX\s+\{([^}]*)\}")):
            found = re.search(pattern, body, re.S)
            item[key] = " ".join(found.group(1).split()) if found else ""
        out.append(item)
    return out


def render_mib() -> str:
    rows = ["| OID | name | syntax | units | access | meaning |", "|---|---|---|---|---|---|"]
    for o in mib_objects():
        if o["kind"] in ("OBJECT-GROUP", "MODULE-COMPLIANCE"):
            continue
        what = o["description"] or o["kind"].lower()
        if o["index"]:
            what += f" (index: {o['index']})"
        rows.append(f"| `{o['oid']}` | {o['name']} | {cell(o['syntax'])} | {o['units']} | {o['access']} | "
                    f"{cell(what)} |")
    return "\n".join(rows)


def render_oids() -> str:
    """Every object the simulated node serves, by module and group (the columns are `.N` of the group)."""
    from erni.sim import manet_mib as mib

    groups: dict[tuple[int, ...], list[Any]] = {}
    for oid, obj in sorted(mib.OBJECTS.items()):
        groups.setdefault(oid[:-1], []).append(obj)
    rows = ["| OID | module | objects |", "|---|---|---|"]
    for base, objs in groups.items():
        names = ", ".join(f"{o.oid[-1]} {o.name}" + (" (**read-write**)" if o.access == "read-write" else "")
                          for o in objs)
        rows.append(f"| `{'.'.join(map(str, base))}` | {objs[0].module} | {names} |")
    return "\n".join(rows)


# -- benchmarks --------------------------------------------------------------------------------


def results() -> list[dict[str, Any]]:
    """Every benchmark's latest results (bench/results/NAME.json), by name."""
    return [json.loads(p.read_text(encoding="utf-8")) | {"name": p.stem} for p in sorted(RESULTS.glob("*.json"))]


def render_benchmarks() -> str:
    lines = ["| benchmark | target | goal | floor | latest | met |", "|---|---|---|---|---|---|"]
    runs = []
    for r in results():
        for t in r["targets"]:
            met = {True: "yes", False: "**no**", None: "reported"}[t.get("met")]
            lines.append(f"| [{r['name']}](#{r['name']}) | {cell(t['target'])} | {cell(t.get('goal', ''))} | "
                         f"{cell(t.get('floor', ''))} | {cell(t['figure'])} | {met} |")
        runs += [f"### {r['name']}", "", cell(r.get("about", "")), "",
                 f"- command: {code(r['command'])}", f"- commit: `{r['commit']}` ({cell(r.get('date', ''))})",
                 f"- machine: {cell(r.get('machine', ''))}", ""]
        for table in r.get("tables", []):
            runs += [f"#### {cell(table['title'])}", "", table["markdown"], ""]
    return "\n".join(lines + ["", "## How each was measured", "", *runs])


RENDERERS: dict[str, Callable[[], str]] = {
    "cli": render_cli, "settings": render_settings, "agent": render_agent, "tasks": render_tasks,
    "policy": render_policy, "wire": render_wire, "mib": render_mib, "oids": render_oids,
    "benchmarks": render_benchmarks,
}


def render(name: str) -> str:
    """The generated Markdown of one reference part."""
    return RENDERERS[name]()


def expand(markdown: str) -> str:
    """`markdown` with every reference marker replaced by its generated part."""
    return MARKER.sub(lambda m: render(m.group(1)), markdown)


def on_page_markdown(markdown: str, page: Any, config: Any, files: Any) -> str:
    """MkDocs event: fill in the generated parts of a page."""
    return expand(markdown)
