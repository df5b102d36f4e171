"""Agent config files: validation with `FILE: field.path: message` errors, plugin loading."""

from __future__ import annotations

from pathlib import Path

import pytest

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
    ("[agent\nname='x'", "invalid TOML"),
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
    with pytest.raises(ConfigError, match="cannot read"):
        load_agent(tmp_path / "nope.toml")
    bad = tmp_path / "bin.toml"
    bad.write_bytes(b"\xff\xfe\x00")
    with pytest.raises(ConfigError, match="not UTF-8"):
        load_agent(bad)


def test_disabled_plugins_are_skipped():
    config = parse_config("[agent]\nname='r1'\n[[plugin]]\nclass='nothing:Here'\nenabled=false")
    assert config.plugin[0].enabled is False
