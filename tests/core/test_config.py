"""Agent config files: validation with `FILE: field.path: message` errors, plugin loading."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from erni.blackboard import ConfigError
from erni.blackboard.config import load_agent, parse_config

ROOT = Path(__file__).resolve().parents[2]


def write(tmp_path: Path, text: str) -> Path:
    path = tmp_path / "agent.toml"
    path.write_text(text)
    return path


def test_example_configs_load():
    for name in ("robot.toml", "control.toml"):
        agent = load_agent(ROOT / "examples" / name)
        assert agent.plugins, name


def test_plugin_settings_are_validated_and_typed(tmp_path):
    path = write(tmp_path, """
[agent]
name = "r1"
[[plugin]]
class = "erni.plugins.echo:EchoPlugin"
name = "motion"
[plugin.settings]
delay = "0.25"
""")
    agent = load_agent(path)
    assert agent.plugin("motion").settings.delay == 0.25


@pytest.mark.parametrize("text, message", [
    ("[agent\nname='x'", "not valid TOML"),
    ("[agent]\nname = 'r1'\ncolour = 'red'", "agent: unknown key 'colour'"),
    ("[agent]\n", "agent: missing 'name'"),
    ("[agent]\nname = 'bad name!'", "agent.name: expected a name of letters, digits, '_', '.', '-'"),
    ("[agent]\nname = 'r1'\nworkers = 0", "agent.workers: Input should be greater than or equal to 1"),
    ("[agent]\nname='r1'\n[[plugin]]\nclass='nosuch.module:Thing'", "plugin[0].class: cannot import 'nosuch.module:Thing'"),
    ("[agent]\nname='r1'\n[[plugin]]\nclass='nosuchentry'", "plugin[0].class: unknown plugin 'nosuchentry'"),
    ("[agent]\nname='r1'\n[[plugin]]\nclass='erni.blackboard.tasks:Task'", "plugin[0].class: 'erni.blackboard.tasks:Task' is not a Plugin subclass"),
    ("[agent]\nname='r1'\n[[plugin]]\nclass='echo'\n[plugin.settings]\ndelay=-1", "plugin[0].settings.delay: Input should be greater than or equal to 0"),
    ("[agent]\nname='r1'\n[[plugin]]\nclass='echo'\n[plugin.settings]\nspeed=1", "plugin[0].settings: unknown key 'speed'"),
    ("[agent]\nname='r1'\n[[plugin]]\nname='x'", "plugin[0]: missing 'class'"),
    ("[agent]\nname='r1'\n[[plugin]]\nclass='echo'\n[[plugin]]\nclass='echo'", "plugin[1]: agent r1: a plugin named 'echo' is already loaded"),
])
def test_bad_configs_name_the_file_and_field(tmp_path, text, message):
    path = write(tmp_path, text)
    with pytest.raises(ConfigError) as info:
        load_agent(path)
    first = str(info.value).splitlines()[0]
    assert first.startswith(f"{path}: ")
    assert message in str(info.value)


def test_missing_and_binary_files(tmp_path):
    with pytest.raises(ConfigError, match="nope.toml: no such config file"):
        load_agent(tmp_path / "nope.toml")
    bad = tmp_path / "bin.toml"
    bad.write_bytes(b"\xff\xfe\x00")
    with pytest.raises(ConfigError, match="not UTF-8"):
        load_agent(bad)


def test_disabled_plugins_are_skipped():
    config = parse_config("[agent]\nname='r1'\n[[plugin]]\nclass='nothing:Here'\nenabled=false")
    assert config.plugin[0].enabled is False


# -- files built to hurt the reader: each a one-line error, quickly ---------------------------

def _hostile_configs() -> dict[str, str]:
    head = "[agent]\nname = 'r1'\n[[plugin]]\nclass = 'echo'\n[plugin.settings]\n"
    return {
        "deep array": head + "x = " + "[" * 3000 + "]" * 3000 + "\n",
        "deep inline tables": head + "x = " + "{a = " * 3000 + "1" + "}" * 3000 + "\n",
        "long integer": "[agent]\nname = 'r1'\nworkers = " + "9" * 100_000 + "\n",
        "dotted key": head + ".".join(["a"] * 100_000) + " = 1\n",
        "deep header": "[agent]\nname = 'r1'\n[" + ".".join(["t"] * 100_000) + "]\nx = 1\n",
        "integer beyond 64 bits": "[agent]\nname = 'r1'\nworkers = 0x" + "f" * 17 + "\n",
    }


@pytest.mark.parametrize("kind, says", [
    ("deep array", "config.toml:6: a value nested deeper than 32 levels"),
    ("deep inline tables", "config.toml:6: a key nested 33 levels deep"),
    ("long integer", "config.toml:3: a number of 100000 characters; expected at most 64"),
    ("dotted key", "config.toml:6: a key nested 100002 levels deep (tables, dotted keys, arrays); expected at most 32"),
    ("deep header", "config.toml:3: a table nested 100000 levels deep; expected at most 32"),
    ("integer beyond 64 bits", "config.toml: integer 29514790517935282585... beyond 64 bits"),
])
def test_a_config_built_to_hurt_the_reader_is_one_line_at_once(tmp_path, kind, says):
    """Nested 3,000 deep, an integer of 100,000 digits, a key of 100,000 dotted parts: `erni agent
    --check` names the file, the line and the bound in one line, within seconds (it was a 3,002-line
    RecursionError, a ValueError traceback and more than 60 s)."""
    import subprocess
    import sys
    import time

    path = tmp_path / "config.toml"
    path.write_text(_hostile_configs()[kind])
    start = time.monotonic()
    out = subprocess.run([sys.executable, "-m", "erni", "agent", str(path), "--check"], capture_output=True,
                         text=True, timeout=120)
    took = time.monotonic() - start
    assert out.returncode == 2, out.stderr[-2000:]
    assert len(out.stderr.strip().splitlines()) == 1, out.stderr[-2000:]
    assert f"{tmp_path}/{says}" in out.stderr and "Traceback" not in out.stderr
    assert took < 15, f"--check took {took:.1f} s"


def test_a_config_larger_than_the_bound_is_refused_before_it_is_read(tmp_path):
    from erni.blackboard import tomlfile

    path = tmp_path / "big.toml"
    path.write_text("[agent]\nname = 'r1'\n" + "# padding\n" * (tomlfile.MAX_BYTES // 10 + 1))
    with pytest.raises(ConfigError, match=rf"big.toml: \d+ bytes; expected a config file of at most {tomlfile.MAX_BYTES}"):
        load_agent(path)


_keys = st.from_regex(r"\A[a-z][a-z0-9_]{0,6}\Z")
_scalars = st.integers(-2**63, 2**63 - 1) | st.floats(allow_nan=False, allow_infinity=False) | st.booleans() | \
    st.text(st.characters(blacklist_categories=("Cc", "Cs")), max_size=8)


def _toml_value(value: Any, inline: bool) -> str:
    """TOML text of a value (tables inline), written here: no TOML writer is a dependency."""
    if isinstance(value, dict):
        return "{" + ", ".join(f"{k} = {_toml_value(v, True)}" for k, v in value.items()) + "}"
    if isinstance(value, list):
        return "[" + ", ".join(_toml_value(v, True) for v in value) + "]"
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, float):
        return repr(value) if "e" in repr(value) or "." in repr(value) else f"{value!r}.0"
    if isinstance(value, int):
        return str(value)
    return json.dumps(value, ensure_ascii=False)  # a TOML basic string (JSON's escapes of " and \\ are TOML's)


def _nested(depth: int) -> st.SearchStrategy[Any]:
    if depth == 0:
        return _scalars
    inner = _nested(depth - 1)
    return _scalars | st.lists(inner, max_size=2) | st.dictionaries(_keys, inner, max_size=2)


@settings(max_examples=150, deadline=None)
@given(table=st.dictionaries(_keys, _nested(12), min_size=1, max_size=3), dotted=st.integers(1, 4))
def test_any_config_within_the_bounds_reads_as_the_toml_parser_reads_it(table, dotted):
    """A file of values nested up to 12 levels and keys of up to 4 dotted parts passes the bounds'
    scan, and reads exactly as `tomllib` reads it."""
    import tomllib

    from erni.blackboard import tomlfile

    prefix = ".".join(f"p{i}" for i in range(dotted - 1))
    lines = ["[agent]", "name = 'r1'", "[extra]"]
    lines += [f"{prefix + '.' if prefix else ''}{k} = {_toml_value(v, True)}" for k, v in table.items()]
    text = "\n".join(lines) + "\n"
    assert tomlfile.loads(text, "t.toml") == tomllib.loads(text)


@settings(max_examples=60, deadline=None)
@given(depth=st.integers(33, 400), kind=st.sampled_from(["[", "{a = ", "key"]))
def test_anything_nested_beyond_the_bound_is_refused_in_one_line(depth, kind):
    from erni.blackboard import tomlfile

    if kind == "key":
        text = ".".join(["k"] * depth) + " = 1\n"
    else:
        closing = "]" if kind == "[" else "}"
        text = "x = " + kind * depth + "1" + closing * depth + "\n"
    with pytest.raises(ConfigError) as err:
        tomlfile.loads(text, "t.toml")
    assert str(err.value).startswith("t.toml:1: ") and "expected at most 32" in str(err.value)
    assert "\n" not in str(err.value)
