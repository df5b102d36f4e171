"""`erni agent CONFIG`: run one agent until SIGINT or SIGTERM (the work is `erni.launch`'s)."""

from __future__ import annotations

from typing import Any

from erni.launch import add_arguments, run

__all__ = ["add_arguments", "register", "run"]


def register(sub: Any) -> None:
    """Add the `agent` sub-command."""
    p = sub.add_parser("agent", help="run one agent from a TOML config until Ctrl-C",
                       description="Run one agent (robot or control node) from a TOML config.")
    add_arguments(p)
    p.set_defaults(func=run)
