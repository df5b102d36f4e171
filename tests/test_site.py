"""The documentation site: it builds with warnings as errors, its reference is generated from the
code and complete, and its pages (and the README) keep the rules a reader relies on.

- `mkdocs build --strict` passes (broken links and anchors, pages left out of the navigation and
  mkdocstrings' warnings are errors);
- no commit hash, issue number or development history ("the sixteenth round") in README.md or a
  page of the site;
- no paragraph, list item or table cell longer than `MAX_WORDS` words;
- every `erni` command and option, every plugin and setting (with its meaning, and its unit where
  it has one), every verb and preposition, every message and frame kind and every object of the
  MIB module appears in the generated reference;
- every benchmark script has its latest results in bench/results/NAME.json, which the benchmarks
  page shows.

The generated parts are read through `docs/hooks.py`, the same code the site's build runs.
"""

from __future__ import annotations

import argparse
import importlib.util
import json
import os
import re
import subprocess
import sys
from pathlib import Path
from types import ModuleType

import pytest

ROOT = Path(__file__).resolve().parents[1]
DOCS = ROOT / "docs"
MAX_WORDS = 120
README_LIMIT = 12_000
TEST_COMMAND = ("python3 -m venv .venv && . .venv/bin/activate\n"
                "pip install -r requirements.lock && pip install --no-deps -e . && python3 -m pytest -q")


def _hooks() -> ModuleType:
    spec = importlib.util.spec_from_file_location("erni_docs_hooks", DOCS / "hooks.py")
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


HOOKS = _hooks()
PAGES = sorted(DOCS.rglob("*.md"))


def page_text(path: Path) -> str:
    """A page as the site shows it: its generated parts filled in."""
    return HOOKS.expand(path.read_text(encoding="utf-8"))


def texts() -> list[tuple[str, str]]:
    """(name, Markdown) of README.md and of every page of the site, generated parts included."""
    return [("README.md", (ROOT / "README.md").read_text(encoding="utf-8")),
            *((str(p.relative_to(ROOT)), page_text(p)) for p in PAGES)]


# -- the build ---------------------------------------------------------------------------------


def test_the_site_builds_with_warnings_as_errors(tmp_path: Path) -> None:
    env = {**os.environ, "NO_MKDOCS_2_WARNING": "1"}
    out = subprocess.run([sys.executable, "-m", "mkdocs", "build", "--strict", "--site-dir", str(tmp_path / "site")],
                         cwd=ROOT, capture_output=True, text=True, timeout=300, env=env)
    assert out.returncode == 0, out.stdout + out.stderr
    built = {p.relative_to(tmp_path / "site").as_posix() for p in (tmp_path / "site").rglob("index.html")}
    for page in PAGES:
        rel = page.relative_to(DOCS).with_suffix("")
        html = "index.html" if rel.name == "index" and rel.parent == Path(".") else f"{rel.as_posix()}/index.html"
        assert html.replace("/index/index.html", "/index.html") in built, f"{page} was not built"
    api = (tmp_path / "site" / "reference" / "api" / "index.html").read_text(encoding="utf-8")
    for name in ("erni.Plugin", "erni.Task", "erni.testing.agent_with", "erni.testing.MockTeam"):
        assert f'id="{name}"' in api, f"the API reference lacks {name}"


def test_no_generated_page_is_committed() -> None:
    """The reference pages hold markers where the tables go; their tables come from the code."""
    wanted = {"cli.md": "cli", "agent-config.md": "agent", "settings.md": "settings", "tasks.md": "tasks",
              "policy.md": "policy", "wire.md": "wire", "mib.md": "mib", "benchmarks.md": "benchmarks"}
    for page, marker in wanted.items():
        text = (DOCS / "reference" / page).read_text(encoding="utf-8")
        assert f"<!-- erni-reference: {marker} -->" in text, f"reference/{page} lost its generated part"
        assert text.count("\n|") < 20, f"reference/{page} holds a table that should be generated"
    assert not (ROOT / "site").exists() or not subprocess.run(
        ["git", "ls-files", "site"], cwd=ROOT, capture_output=True, text=True).stdout.strip()


# -- the README ------------------------------------------------------------------------------


def test_the_readme_is_a_front_door() -> None:
    text = (ROOT / "README.md").read_text(encoding="utf-8")
    assert len(text) <= README_LIMIT, f"README.md is {len(text)} characters; at most {README_LIMIT}"
    assert f"```sh\n{TEST_COMMAND}\n```" in text, "the README's test command is what CI runs (.ci/run)"
    assert TEST_COMMAND.splitlines()[1] in (ROOT / ".ci" / "run").read_text(encoding="utf-8")
    assert "```sh\nmkdocs serve\n```" in text, "the README says how to read the site locally"
    for figure in re.findall(r"!\[[^\]]+\]\(([^)]+)\)", text):
        assert (ROOT / figure).is_file(), figure
    for link in re.findall(r"\]\((docs/[^)#]+)", text):
        assert (ROOT / link).is_file(), f"README links to {link}, which is not there"


def test_the_readme_states_the_pythons_and_the_lock_truly() -> None:
    import tomllib

    text = " ".join((ROOT / "README.md").read_text(encoding="utf-8").split())
    project = tomllib.loads((ROOT / "pyproject.toml").read_text(encoding="utf-8"))["project"]
    assert project["requires-python"] == ">=3.11" and "CPython 3.11, 3.12 and 3.13" in text
    assert "`requirements.lock` pins, with hashes" in text and (ROOT / "requirements.lock").is_file()
    assert "--generate-hashes" in (ROOT / "tools" / "lock.sh").read_text(encoding="utf-8")


# -- what a reader is not told ---------------------------------------------------------------------

HISTORY = [
    (re.compile(r"\b(?=[0-9a-f]*[a-f])(?=[0-9a-f]*[0-9])[0-9a-f]{7,40}\b"), "a commit hash"),
    (re.compile(r"\bissues? #?\d+|(?<![\w&])#\d+\b", re.I), "an issue number"),
    (re.compile(r"\b(first|second|third|fourth|fifth|sixth|seventh|eighth|ninth|tenth|eleventh|twelfth|"
                r"thirteenth|fourteenth|fifteenth|sixteenth|\d+(st|nd|rd|th)) round\b|\bround \d+\b", re.I),
     "a round of development"),
    (re.compile(r"BENCHMARKS\.md|RELIABILITY\.md|\bdocs/(gui|mission|plugins|ros2|sim|zenoh)\.md\b"),
     "a file that is no longer there"),
    (re.compile(r"\b(measured again at|until commit|before the change|in the latest two)\b", re.I),
     "development history"),
]


def _history(name: str, text: str) -> list[str]:
    found = []
    for number, line in enumerate(text.splitlines(), 1):
        if name.endswith("reference/benchmarks.md") and line.startswith("- commit: "):
            continue  # the benchmarks page names the commit each figure was measured at, by design
        if line.startswith("    --hash="):
            continue
        for pattern, what in HISTORY:
            for m in pattern.finditer(line):
                found.append(f"{name}:{number}: {what}: {m.group(0)!r}")
    return found


def test_no_development_history_in_the_readme_or_the_site() -> None:
    found = [f for name, text in texts() for f in _history(name, text)]
    assert not found, "\n".join(found)


# -- short paragraphs ------------------------------------------------------------------------------


def units(text: str) -> list[tuple[int, str]]:
    """(line, text) of every paragraph, list item and table cell outside code blocks."""
    out: list[tuple[int, str]] = []
    current: list[str] = []
    start = 0
    fence = False

    def flush() -> None:
        if current:
            out.append((start, " ".join(current)))
        current.clear()

    for number, line in enumerate(text.splitlines(), 1):
        if line.startswith("```"):
            flush()
            fence = not fence
            continue
        stripped = line.strip()
        if fence or not stripped or stripped.startswith(("#", "<!--", "![")):
            flush()
            continue
        if stripped.startswith("|"):
            flush()
            out += [(number, c) for c in stripped.strip("|").split("|")]
            continue
        if re.match(r"([-*+]|\d+\.)\s", stripped):
            flush()
            start = number
        elif not current:
            start = number
        current.append(stripped)
    flush()
    return out


def test_no_paragraph_list_item_or_cell_is_longer_than_the_limit() -> None:
    long = [f"{name}:{line}: {len(unit.split())} words: {unit[:80]}..."
            for name, text in texts() for line, unit in units(text) if len(unit.split()) > MAX_WORDS]
    assert not long, f"longer than {MAX_WORDS} words (split them):\n" + "\n".join(long)


def test_the_word_count_sees_paragraphs_items_and_cells() -> None:
    text = "para one\nstill one\n\n- item\n  more item\n- next\n\n| a b | c |\n\n```\nnot counted\n```\n"
    assert [u for _, u in units(text)] == ["para one still one", "- item more item", "- next", " a b ", " c "]


# -- the generated reference is complete ------------------------------------------------------------


def test_every_command_and_option_is_in_the_reference() -> None:
    page = page_text(DOCS / "reference" / "cli.md")
    commands = HOOKS.commands()
    assert {"erni agent", "erni sim", "erni task", "erni keys issue"} <= {words for words, _, _ in commands}
    for words, parser, _ in commands:
        assert f"## {words} {{#" in page, f"{words} has no section"
        section = page.split(f"## {words} {{#", 1)[1].split("\n## ", 1)[0]
        for action in parser._actions:
            if isinstance(action, (argparse._HelpAction, argparse._SubParsersAction)):
                continue
            shown = action.metavar if isinstance(action.metavar, str) else action.dest
            rows = [line for line in section.splitlines() if line.startswith("| `")]  # the options table
            for option in action.option_strings or [shown]:
                assert any(re.search(rf"`\[?{re.escape(option)}", row) for row in rows), \
                    f"{words}: {option} is not in its options table"
            assert action.help is None or action.help == argparse.SUPPRESS or len(action.help) > 3, \
                f"{words}: {action.option_strings or action.dest} has no help"


# settings without a physical unit: shares, qualities, counts of steps, weights, gains
DIMENSIONLESS = {"min_link_quality", "resume_quality", "progress_step", "udp_loss", "obstacle_weight"}


def test_every_plugin_and_setting_is_in_the_reference_with_its_meaning() -> None:
    page = page_text(DOCS / "reference" / "settings.md")
    found = HOOKS.plugins()
    assert {"transport", "motion", "mobinet", "mission", "ui", "ros2", "foxglove", "echo"} <= {n for n, _, _ in found}
    missing = []
    for name, _, model in found:
        assert f"## `{name}` {{#{name}}}" in page, f"plugin {name} has no section"
        section = page.split(f"## `{name}` {{#{name}}}", 1)[1].split("\n## ", 1)[0]
        for setting, field, _ in HOOKS.settings_rows(model):
            if f"| `{setting}` |" not in section:
                missing.append(f"{name}.{setting}: not in the reference")
            if not field.description:
                missing.append(f"{name}.{setting}: no description (Field(description=...)) to say what it means")
            if field.annotation in (float, float | None) and not HOOKS.unit_of(field.description) \
                    and setting.rsplit(".", 1)[-1] not in DIMENSIONLESS:
                missing.append(f"{name}.{setting}: a number without a unit in its description, e.g. '(s)'")
    agent = page_text(DOCS / "reference" / "agent-config.md")
    from erni.blackboard.config import AgentSection

    for setting, field, _ in HOOKS.settings_rows(AgentSection):
        if f"| `{setting}` |" not in agent or not field.description:
            missing.append(f"[agent] {setting}: not in the reference with a description")
    assert not missing, "\n".join(missing)


def test_the_unit_is_read_from_the_description() -> None:
    assert HOOKS.unit_of("give up after this long (s)") == "s"
    assert HOOKS.unit_of("UDP receive buffer (bytes; 0 = the kernel's default)") == "bytes"
    assert HOOKS.unit_of("rate of the watches (Hz)") == "Hz"
    assert HOOKS.unit_of("volts below which a robot is drawn pink") == "V"
    assert HOOKS.unit_of("a share of the datagrams") == ""


def test_every_verb_and_preposition_is_in_the_reference() -> None:
    from erni.blackboard.tasks import PREPOSITIONS, VERBS

    page = page_text(DOCS / "reference" / "tasks.md")
    for verb in VERBS:
        assert f"| `{verb}` |" in page, verb
    for (verb, name), prep in PREPOSITIONS.items():
        assert f"| {verb} | `{name}` |" in page, (verb, name)
        for param in prep.params.model_fields:
            assert f"`{param}`" in page, (verb, name, param)


def test_the_policy_frames_and_mib_are_in_the_reference() -> None:
    from erni.transport import policy, wire

    page = page_text(DOCS / "reference" / "policy.md")
    for kind in ("task.add", "task.relay", "task.cancel", "task.result", "status", "watch.request", "beacon"):
        assert f"`{kind}`" in page, kind
    for type_name in policy.STATUS:
        assert f"| `{type_name}` |" in page, type_name
    for (sender, receiver) in policy.TASKS:
        assert f"| {sender} | {receiver} |" in page, (sender, receiver)
    page = page_text(DOCS / "reference" / "wire.md")
    for byte, name in wire.KINDS.items():
        assert f"| `{chr(byte)}` (`{byte:#04x}`) | {name} |" in page, name
    page = page_text(DOCS / "reference" / "mib.md")
    defined = re.findall(r"^(\w+) OBJECT-TYPE", HOOKS.MIB.read_text(encoding="utf-8"), re.M)
    assert len(defined) > 10
    for name in defined:
        assert f"| {name} |" in page, f"{name} of ERNI-MOBINET-MIB is not in the reference"
    from erni.sim import manet_mib

    for obj in manet_mib.OBJECTS.values():
        assert f" {obj.name}" in page, f"served object {obj.name} is not in the reference"


def test_the_mib_reader_resolves_the_module() -> None:
    objects = {o["name"]: o for o in HOOKS.mib_objects()}
    assert objects["erniPosX"]["oid"] == "1.3.6.1.4.1.32473.1.1.4"
    assert objects["erniPosX"]["units"] == "millimetres" and objects["erniPosX"]["access"] == "read-write"


# -- benchmarks -----------------------------------------------------------------------------------


def test_every_benchmark_has_its_latest_results_on_the_page() -> None:
    scripts = sorted(p.stem for p in (ROOT / "bench").glob("bench_*.py"))
    results = {r["name"]: r for r in HOOKS.results()}
    assert sorted(results) == scripts, "each bench/bench_NAME.py writes bench/results/bench_NAME.json"
    page = page_text(DOCS / "reference" / "benchmarks.md")
    for name, r in results.items():
        assert r["command"].startswith(f"python bench/{name}.py"), (name, r["command"])
        assert re.fullmatch(r"[0-9a-f]{7,40}", r["commit"]), (name, r["commit"])
        assert r["machine"] and r["date"] and r["targets"], name
        for t in r["targets"]:
            assert set(t) >= {"target", "goal", "floor", "figure", "met"}, (name, t)
            assert t["met"] in (True, False, None), (name, t)
            assert HOOKS.cell(t["figure"]) in page, (name, t["figure"])
        assert f"### {name}" in page


def test_the_results_writer_writes_what_the_page_reads(tmp_path: Path) -> None:
    sys.path.insert(0, str(ROOT / "bench"))
    try:
        import results as writer
    finally:
        sys.path.remove(str(ROOT / "bench"))
    path = writer.write("bench_example", [writer.target("a target", "≤ 2x", "a floor", "1.5x", True)],
                        about="an example", argv=["--rounds", "3"], path=tmp_path / "bench_example.json")
    data = json.loads(path.read_text(encoding="utf-8"))
    assert data["command"] == "python bench/bench_example.py --rounds 3"
    assert re.fullmatch(r"[0-9a-f]{7,40}", data["commit"]) and data["machine"] and data["date"]
    assert data["targets"] == [{"target": "a target", "goal": "≤ 2x", "floor": "a floor", "figure": "1.5x",
                                "met": True}]


@pytest.mark.parametrize("page", [p for p in PAGES if p.name != "index.md" or p.parent == DOCS],
                         ids=lambda p: str(p.relative_to(DOCS)))
def test_every_page_has_one_title(page: Path) -> None:
    text = re.sub(r"^```.*?^```", "", page.read_text(encoding="utf-8"), flags=re.S | re.M)
    assert text.startswith("# ") and len(re.findall(r"^# ", text, re.M)) == 1, f"{page}: one '# Title', first"
