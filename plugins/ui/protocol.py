"""Messages the GUI page sends over its WebSocket, validated before anything acts on them.

Text frames are JSON objects with a `type`; binary frames are microphone audio (16 kHz mono
int16 little-endian) while the page's microphone is on. `parse_message` returns the typed
message or raises `BadMessage` with one line naming what was wrong and what was expected.
Text no page sends (nested deeper than `MAX_DEPTH`, longer than `MAX_TEXT`) raises
`HostileMessage` before it is parsed: the server answers it and closes the connection.
"""

from __future__ import annotations

import json
from typing import Annotated, Any, Literal

from pydantic import ConfigDict, Field, TypeAdapter, ValidationError

from erni.blackboard.errors import ErniError, describe_validation
from erni.blackboard.objects import Model
from erni.blackboard.text import Name
from erni.transport.wire import json_depth

AgentName = Name
Number = Annotated[float, Field(allow_inf_nan=False)]


class _Msg(Model):
    model_config = ConfigDict(extra="forbid", frozen=True)


class CommandMsg(_Msg):
    """Task the robots with an action of the grammar (goto, forward, turn, stop, ...)."""

    type: Literal["command"]
    robots: list[AgentName] = Field(max_length=256)  # empty: stop means everyone; others are refused
    action: Annotated[str, Field(pattern=r"^[a-z_]{1,40}$")]
    params: dict[Annotated[str, Field(pattern=r"^[a-z_]{1,40}$")], Number | int | bool | AgentName | None] = Field(
        default_factory=dict, max_length=16)


class SayMsg(_Msg):
    """A typed utterance, with the robots selected on the page (the default targets)."""

    type: Literal["say"]
    text: Annotated[str, Field(min_length=1, max_length=300)]
    selection: list[AgentName] = Field(default_factory=list, max_length=256)


class SelectMsg(_Msg):
    """The page's selection changed."""

    type: Literal["select"]
    robots: list[AgentName] = Field(max_length=256)


class CancelTaskMsg(_Msg):
    """Cancel one task shown in the task list."""

    type: Literal["cancel_task"]
    uid: Annotated[str, Field(min_length=1, max_length=100)]


class MicMsg(_Msg):
    """The page's microphone starts or stops streaming; audio must be 16 kHz."""

    type: Literal["mic"]
    on: bool
    rate: Literal[16000] = 16000


class PingMsg(_Msg):
    """Keep-alive."""

    type: Literal["ping"]


PageMessage = Annotated[CommandMsg | SayMsg | SelectMsg | CancelTaskMsg | MicMsg | PingMsg,
                        Field(discriminator="type")]
_ADAPTER: TypeAdapter[Any] = TypeAdapter(PageMessage)
TYPES = ("command", "say", "select", "cancel_task", "mic", "ping")
MAX_DEPTH = 8  # the page's deepest message is 3 levels (an object, its params, a value)
MAX_TEXT = 32 * 1024  # a selection of 256 robot names is about 17 KiB


class BadMessage(ErniError, ValueError):
    """A page message that is not valid JSON or not one of the known messages."""


class HostileMessage(BadMessage):
    """Text no page sends (too deep or too long): answered, then the connection is closed."""


def parse_message(text: str | bytes) -> Any:
    """Return the typed page message in a JSON text, or raise BadMessage naming the problem."""
    if len(text) > MAX_TEXT:
        raise HostileMessage(f"message of {len(text)} characters; expected at most {MAX_TEXT}")
    try:
        if isinstance(text, bytes):
            text = text.decode("utf-8")
    except UnicodeDecodeError as err:
        raise BadMessage(f"message is not JSON ({err}); expected an object with a 'type'") from None
    if text.count("[") + text.count("{") > MAX_DEPTH and (depth := json_depth(text)) > MAX_DEPTH:
        # json.loads recurses once a level: deep enough, a RecursionError instead of an answer
        raise HostileMessage(f"message nested {depth} levels deep; expected at most {MAX_DEPTH}")
    try:
        data = json.loads(text)
    except ValueError as err:
        raise BadMessage(f"message is not JSON ({err}); expected an object with a 'type'") from None
    if not isinstance(data, dict) or data.get("type") not in TYPES:
        got = data.get("type") if isinstance(data, dict) else type(data).__name__
        raise BadMessage(f"unknown message type {got!r}; expected one of {', '.join(TYPES)}")
    try:
        return _ADAPTER.validate_python(data)
    except ValidationError as err:
        raise BadMessage(describe_validation(err, str(data["type"]), skip=1)) from None
