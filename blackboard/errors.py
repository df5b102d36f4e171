"""The one exception root of ERNI, its subclasses named after the state that is wrong, and the one
helper that turns a pydantic validation error into a readable line."""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from pydantic import ValidationError

SHOWN_VALUE = 60
"""At most this many characters of a bad value are shown in an error message."""


class ErniError(Exception):
    """Root of every error ERNI raises on purpose."""


class ConfigError(ErniError, ValueError):
    """A configuration file, setting, scenario or world is invalid: `FILE: field.path: message`."""


class UsageError(ErniError, ValueError):
    """A function was called with an argument outside what it accepts."""


class NotFoundError(ErniError, KeyError):
    """Something was named (a node, a robot, an agent) that does not exist."""

    def __str__(self) -> str:  # KeyError would quote the message
        return str(self.args[0]) if self.args else ""


class NetworkError(ErniError, OSError):
    """A socket could not be bound, or a peer could not be reached."""


class TaskError(ErniError, ValueError):
    """A task is invalid: `goto: missing 'x'`."""


class TransactionError(ErniError):
    """The blackboard was used outside a transaction, or an object is unknown or duplicated."""


class PluginError(ErniError):
    """A plugin could not be found, loaded or configured."""


def shown(value: Any, limit: int = SHOWN_VALUE) -> str:
    """Return `repr(value)` cut to `limit` characters, so a huge bad value never floods a message."""
    text = repr(value)
    return text if len(text) <= limit else f"{text[:limit]}... ({len(text)} characters)"


def validation_problems(err: ValidationError, prefix: str = "", skip: int = 0) -> list[str]:
    """One `field.path: message` per problem of a pydantic error.

    A missing or unknown key is named after the table that lacks or has it
    (`plugin[0].settings: unknown key 'speed'`); other problems show the offending value, cut
    to a readable length. `skip` drops leading location parts (a tagged union's tag).
    """
    lines = []
    for e in err.errors():
        loc = list(e["loc"])[skip:]
        kind = e["type"]
        named = kind in ("missing", "extra_forbidden") and loc
        field = str(loc.pop()) if named else ""
        where = prefix
        for part in loc:
            if isinstance(part, int) and where:
                where += f"[{part}]"
            else:
                text = str(part) if str(part).isprintable() else repr(part)  # a key with a newline: one line
                where += f".{text}" if where else text
        if kind == "missing":
            msg = f"missing {field!r}" if field else "missing"
        elif kind == "extra_forbidden":
            msg = f"unknown key {field!r}" if field else "unknown key"
        else:
            ctx = e.get("ctx") or {}
            msg = str(ctx["error"]) if kind in ("value_error", "assertion_error") and "error" in ctx else e["msg"]
            value = e.get("input")
            if not isinstance(value, (dict, list, tuple)) and kind not in ("value_error", "assertion_error"):
                msg += f" (got {shown(value)})"
        lines.append(f"{where}: {msg}" if where else msg)
    return lines


def describe_validation(err: ValidationError, source: str = "", prefix: str = "", *, sep: str = "; ",
                        skip: int = 0) -> str:
    """Return the problems of a pydantic error as `SOURCE: field.path: message`, joined by `sep`.

    A problem that is itself an ERNI error raised without a location (a task's own message,
    `goto: missing 'y'`) already says where it is and is not prefixed again.
    """
    whole = {i for i, e in enumerate(err.errors())
             if not list(e["loc"])[skip:] and isinstance((e.get("ctx") or {}).get("error"), ErniError)}
    lines = validation_problems(err, prefix, skip)
    return sep.join(line if i in whole or not source else f"{source}: {line}" for i, line in enumerate(lines))
