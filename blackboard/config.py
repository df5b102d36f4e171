"""Agent configuration: a TOML file validated with pydantic; errors read `FILE: field.path: message`."""

from __future__ import annotations

from pathlib import Path

from pydantic import ConfigDict, Field, ValidationError

from erni.blackboard import tomlfile
from erni.blackboard.agent import Agent, resolve_plugin, validate_settings
from erni.blackboard.errors import ConfigError, PluginError, describe_validation
from erni.blackboard.objects import FiniteAny, Model
from erni.blackboard.text import Name


class AgentSection(Model):
    """The `[agent]` table."""

    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)

    name: Name = Field(description="agent name: letters, digits, '_', '.', '-' (at most 63, the first a "
                       "letter or a digit)")
    workers: int = Field(4, ge=1, le=64, description="worker threads that run plugins")
    slow_plugin_seconds: float = Field(1.0, gt=0, le=3600, description="report plugin runs longer than this (s)")
    log_level: str = Field("INFO", pattern=r"^(DEBUG|INFO|WARNING|ERROR)$", description="least severe log level shown")
    journal: str | None = Field(None, description="SQLite file that keeps tasks across a crash; "
                                "omit for none")
    retention: float = Field(600.0, gt=0, le=10 * 365 * 86400,
                             description="finished tasks are dropped this long after they finished (s)")


class PluginSection(Model):
    """One `[[plugin]]` table."""

    model_config = ConfigDict(extra="forbid", populate_by_name=True)

    class_: str = Field(alias="class", description="'module:Class' or an entry point name")
    name: str | None = None
    enabled: bool = True
    settings: dict[str, FiniteAny] = Field(default_factory=dict)


class AgentConfig(Model):
    """A whole agent config file."""

    model_config = ConfigDict(extra="forbid")

    agent: AgentSection
    plugin: list[PluginSection] = Field(default_factory=list)


def parse_config(text: str, source: str = "<config>") -> AgentConfig:
    """Parse and validate config text held to `tomlfile`'s bounds (size, depth, numbers); raises ConfigError."""
    data = tomlfile.loads(text, source)
    try:
        return AgentConfig.model_validate(data)
    except ValidationError as err:
        raise ConfigError(describe_validation(err, source, sep="\n")) from None


def read_config(path: str | Path) -> AgentConfig:
    """Read and validate a config file (raises ConfigError)."""
    path = Path(path)
    return parse_config(tomlfile.read_text(path, "config"), str(path))


def build_agent(config: AgentConfig, source: str = "<config>") -> Agent:
    """Make an agent from a validated config; plugin errors raise ConfigError."""
    agent = Agent(config.agent.name, workers=config.agent.workers,
                  slow_plugin_seconds=config.agent.slow_plugin_seconds, journal=config.agent.journal,
                  retention=config.agent.retention)
    for i, section in enumerate(config.plugin):
        here = f"plugin[{i}]"
        if not section.enabled:
            continue
        try:
            cls = resolve_plugin(section.class_)
        except PluginError as err:
            raise ConfigError(f"{source}: {here}.class: {err}") from None
        try:
            settings = validate_settings(cls, section.settings)
        except ValidationError as err:
            raise ConfigError(describe_validation(err, source, f"{here}.settings", sep="\n")) from None
        try:
            default = section.class_ if section.class_.isidentifier() else None  # entry point name
            agent.add_plugin(cls, settings, name=section.name or default)
        except PluginError as err:
            raise ConfigError(f"{source}: {here}: {err}") from None
    return agent


def load_agent(path: str | Path) -> Agent:
    """Read a config file and build its agent (raises ConfigError)."""
    return build_agent(read_config(path), str(path))
