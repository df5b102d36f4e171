"""Messages between the GUI page and the control node over its WebSocket, typed both ways.

Inbound (what the page sends) is validated before anything acts on it; outbound (what the
server sends) is built as the types below, so the page reads the fields it was written for:
`Picture` (the state the page draws, sent as `{"type": "state", ...}` and served at
`/api/state`) and the events `HelloMsg`, `ReplyMsg`, `SelectOut`, `ErrorMsg`, `PongMsg`.

Text frames are JSON objects with a `type`; binary frames are microphone audio (16 kHz mono
int16 little-endian) while the page's microphone is on. `parse_message` returns the typed
message or raises `BadMessage` with one line naming what was wrong and what was expected.
Text no page sends (nested deeper than `MAX_DEPTH`, longer than `MAX_TEXT`) raises
`HostileMessage` before it is parsed: the server answers it and closes the connection.
"""

from __future__ import annotations

import json
import math
from typing import Annotated, Any, Literal

from pydantic import ConfigDict, Field, JsonValue, TypeAdapter, ValidationError

from erni.blackboard.errors import ErniError, describe_validation
from erni.blackboard.objects import Model
from erni.blackboard.schemas import FloorPlan
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


# -- what the server sends ------------------------------------------------------------------------
# Field names and JSON shapes are what plugins/ui/static/app.js reads (tests/ui/test_picture_types.py
# holds the two sides together). Numbers are finite (`Model`), text is str, lists are bounded where
# they are built (the log and the task list).


def _shown(value: float | None, digits: int) -> float | None:
    """`value` rounded to `digits`, or None when there is none or it is not finite."""
    return None if value is None or not math.isfinite(value) else round(value, digits)


LogLevel = Literal["info", "warn", "error", "dim"]
Param = bool | int | float | str


class _Out(Model):
    model_config = ConfigDict(extra="forbid", frozen=True)


class PoseRow(_Out):
    """A robot's pose as the page draws it, rounded (sensor noise below this redraws nothing).

    A row refuses a number that is not finite, as every model does; `of` builds one from a Pose's
    numbers and holds such a number as None (a Pose no validator checked may carry one: the codec's
    hot path trusts its decoder). The page gets null: it reads x, y or theta that is not a number as
    "position unreadable", lists the robot as faulty and draws no pose of it on the map; v, w or
    battery as null shows "–".
    """

    x: float | None
    y: float | None
    theta: float | None
    v: float | None
    w: float | None
    battery: float | None = None

    @classmethod
    def of(cls, x: float, y: float, theta: float, v: float, w: float, battery: float | None) -> PoseRow:
        """The row of a Pose's numbers, rounded (positions to mm, speeds to cm/s, the battery to 0.1 V),
        a number that is not finite as None."""
        return cls(x=_shown(x, 3), y=_shown(y, 3), theta=_shown(theta, 3), v=_shown(v, 2), w=_shown(w, 2),
                   battery=_shown(battery, 1))


class RobotRow(_Out):
    """One robot of the robot table and the map."""

    name: str
    number: int | str  # the robot's number, or the first two letters of a name without one
    up: bool
    state: Literal["ok", "warn", "lost"]
    reasons: list[str]  # why it warns: battery, stalled, motors off, bumper
    pose: PoseRow | None  # None: no Pose heard yet
    address: str
    task: str  # its running task in short (`goto x=1.0`), or ""


class LinkRow(_Out):
    """A link between two robots from their NetInfo; `stale` when old or an end is lost."""

    a: str
    b: str
    quality: float
    stale: bool


class TaskRow(_Out):
    """One row of the task list: a task sent to a robot, or one cancelled before it ended."""

    uid: str
    robot: str | None
    verb: str
    preposition: str
    text: str
    params: dict[str, Param]
    source: str
    created: float
    state: str  # a TaskState's value
    progress: float
    message: str
    values: dict[str, Param]


class Metrics(_Out):
    """The network's numbers over the robots and their links that are not stale."""

    robots: int
    up: int
    links: int
    mean_quality: float | None
    components: int
    articulation_points: list[str]
    degree: float
    network_known: bool


class LogLine(_Out):
    """A line of the page's log (`t`: wall-clock seconds)."""

    t: float
    level: LogLevel
    text: str


class SpeechState(_Out):
    """Whether the control node's recogniser runs, and why not."""

    available: bool
    error: str
    recogniser: str


class Picture(_Out):
    """What the page shows: robots, links, metrics, tasks, log, settings (the state message's body)."""

    agent: str
    verb: str
    actions: list[str]
    strategies: list[str]
    speech: SpeechState
    listening: bool
    robots: list[RobotRow]
    links: list[LinkRow]
    floorplan: FloorPlan | None
    metrics: Metrics
    tasks: list[TaskRow]
    log: list[LogLine]


class HelloMsg(_Out):
    """The first message on a WebSocket: the name the page's replies are addressed to."""

    type: Literal["hello"] = "hello"
    client: str


class ReplyMsg(_Out):
    """The answer to a command or an utterance (`client`: the page it answers; voice: every page)."""

    type: Literal["reply"] = "reply"
    text: str
    heard: str
    channel: str  # page, typed or voice
    client: str
    accepted: bool
    asked: bool = False  # a read-back or "say again?": an answer is awaited


class SelectOut(_Out):
    """The robots an utterance named become the page's selection."""

    type: Literal["select"] = "select"
    robots: list[str]


class ErrorMsg(_Out):
    """A refused command or message, in one line."""

    type: Literal["error"] = "error"
    message: str


class PongMsg(_Out):
    """The answer to a ping."""

    type: Literal["pong"] = "pong"


Event = HelloMsg | ReplyMsg | SelectOut | ErrorMsg | PongMsg
"""Every message the server sends but the state."""

JsonDict = dict[str, JsonValue]
"""A JSON object as Python data: a `Picture` dumped as the page gets it (`model_dump(mode="json")`)."""
