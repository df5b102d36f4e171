"""The task language (paper 004, Table 2): verbs, prepositions with typed parameters, results.

A `Task` names a verb (`NetWatch`, `BotMotion`, `RemoteBotMotion`, or an extension), a
preposition (the sub-task, e.g. `goto`), and parameters validated by the preposition's own
pydantic model. Invalid tasks are refused with a `TaskError` whose message names the field:
`goto: missing 'x'`. Units everywhere: metres, seconds, degrees for task parameters.
"""

from __future__ import annotations

import enum
import json
import math
import types
from dataclasses import dataclass
from typing import Any, ClassVar, Self, TypeVar, Union, get_args, get_origin

from pydantic import (
    ConfigDict,
    Field,
    SerializeAsAny,
    ValidationError,
    field_validator,
    model_validator,
)

from erni.blackboard.clock import wall
from erni.blackboard.errors import TaskError, describe_validation, shown
from erni.blackboard.objects import BBObject, FiniteJson, Model
from erni.blackboard.text import Name, NameOrEmpty
from erni.blackboard.world import Link as Link
from erni.blackboard.world import Neighbor as Neighbor
from erni.blackboard.world import NetInfo as NetInfo
from erni.blackboard.world import Pose as Pose
from erni.blackboard.world import Position as Position
from erni.blackboard.world import Route as Route
from erni.blackboard.world import best_links as best_links


def _is_number(annotation: Any) -> bool:
    """True for `float`, `int` and their optional forms (`float | None`)."""
    if annotation in (float, int):
        return True
    if get_origin(annotation) in (Union, types.UnionType):
        args = [a for a in get_args(annotation) if a is not type(None)]
        return bool(args) and all(a in (float, int) for a in args)
    return False


class Params(Model):
    """Base of every preposition's parameters: unknown keys are refused, numbers are strict.

    Each preposition of the built-in language has its own class, so a plugin dispatches with
    `match task.params: case GotoParams(x=x, y=y): ...` and a type checker knows the fields.
    A number field never takes a boolean (`x=true` is not 1.0), NaN or an infinity (JSON
    cannot carry those: they would travel as null); a numeric string ("1.5") is read as a number.
    """

    model_config = ConfigDict(frozen=True, extra="forbid", allow_inf_nan=False)

    @model_validator(mode="before")
    @classmethod
    def _strict_numbers(cls, data: Any) -> Any:
        if not isinstance(data, dict):
            return data
        for name, value in data.items():
            field = cls.model_fields.get(name) if isinstance(name, str) else None
            if field is None or value is None or not _is_number(field.annotation):
                continue
            if isinstance(value, bool):
                raise ValueError(f"{name}: expected a number, got {value} (a boolean)")
            if isinstance(value, float) and not math.isfinite(value):
                raise ValueError(f"{name}: expected a finite number, got {value}")
        return data


P = TypeVar("P", bound=Params)


# --- parameter models -------------------------------------------------------------------


class NoParams(Params):
    """No parameters."""


class StopParams(Params):
    """BotMotion stop: end every motion on the robot and halt; or, with `hold`, pause what runs."""

    hold: bool = Field(False, description="true: pause the motions while this task stands (the network "
                       "guard's hold); false: end them all")
    by: str | None = Field(None, max_length=64, description="who asked, named in the ended tasks' results; "
                           "the task's source if omitted")


class ClearParams(NoParams):
    """BotMotion clear: empty the behaviour stack."""


class WatchParams(Params):
    rate_hz: float = Field(1.0, gt=0, le=100, description="monitoring rate (Hz)")


class NodePositionParams(WatchParams):
    """NetWatch node_position."""


class TopologyParams(WatchParams):
    """NetWatch network_topology."""


class NeighborListParams(WatchParams):
    """NetWatch neighbor_list."""


class PathCostParams(WatchParams):
    destination: str | None = Field(None, description="node name or address; all if omitted")


class LinkQualityParams(WatchParams):
    neighbor: str | None = Field(None, description="one neighbour; all if omitted")


class RandomWalkParams(Params):
    speed: float = Field(0.3, gt=0, le=2.0, description="cruise speed (m/s)")
    duration: float | None = Field(None, gt=0, description="stop after this long (s)")
    seed: int | None = Field(None, description="random seed for a repeatable walk")


class GotoParams(Params):
    x: float = Field(description="goal x (m)")
    y: float = Field(description="goal y (m)")
    speed: float = Field(0.3, gt=0, le=2.0, description="cruise speed (m/s)")
    tolerance: float = Field(0.1, gt=0, description="arrival radius (m)")
    timeout: float | None = Field(None, gt=0, description="fail after this long (s)")


class TurnParams(Params):
    angle: float = Field(description="relative turn (deg, positive = left/counter-clockwise)")
    rate: float = Field(45.0, gt=0, le=360, description="turn rate (deg/s)")
    tolerance: float = Field(2.0, gt=0, description="accepted heading error (deg)")


class TeleportParams(Params):
    x: float = Field(description="new x (m)")
    y: float = Field(description="new y (m)")
    heading: float = Field(0.0, description="new heading (deg)")


class VelocityParams(Params):
    v: float = Field(0.0, ge=-2.0, le=2.0, description="linear velocity (m/s)")
    w: float = Field(0.0, ge=-360, le=360, description="angular velocity (deg/s)")
    duration: float | None = Field(None, gt=0, description="hold for this long (s)")


class AvoidParams(Params):
    distance: float = Field(0.5, gt=0, le=5.0, description="stop distance to an obstacle (m)")
    enabled: bool = Field(True, description="false removes obstacle avoidance")


class DistanceParams(Params):
    distance: float = Field(gt=0, description="distance to travel (m)")
    speed: float = Field(0.3, gt=0, le=2.0, description="speed (m/s)")
    timeout: float | None = Field(None, gt=0, description="fail after this long (s)")


class ForwardParams(DistanceParams):
    """Drive straight ahead."""


class BackwardParams(DistanceParams):
    """Drive straight back."""


class CancelParams(Params):
    task: str | None = Field(None, description="uid of the task to cancel; all if omitted")


class SayParams(Params):
    tones: list[tuple[int, int]] = Field(
        default_factory=lambda: [(10, 72)], min_length=1, max_length=20,
        description="(duration in 20 ms units, MIDI note) pairs played by the robot (ARCOS SAY)")


class WidepParams(Params):
    x: float = Field(description="point of interest x (m)")
    y: float = Field(description="point of interest y (m)")
    range: float = Field(4.5, gt=0, description="communication range R (m)")
    tolerance: float = Field(0.5, gt=0, description="arrival radius at the PoI (m)")
    period: float = Field(1.0, gt=0, description="seconds between deployment steps")


class SpreadParams(Params):
    distance: float = Field(5.0, gt=0, description="desired distance d between robots (m)")
    gain: float = Field(2.0, gt=0, description="control gain k")
    dt: float = Field(0.2, gt=0, description="control period (s)")
    range: float = Field(6.0, gt=0, description="neighbourhood range (m); about 1.2 d spreads, "
                         "much more pulls the team together")
    neighbourhood: str = Field("physical", pattern="^(physical|delaunay|gabriel)$",
                               description="physical (within range), delaunay or gabriel neighbours")
    model: str = Field("nonholonomic", pattern="^(holonomic|nonholonomic)$", description="robot model")
    duration: float | None = Field(None, gt=0, description="stop after this long (s)")


class RelayParams(Params):
    source: str = Field(description="agent at one end of the relayed flow")
    destination: str = Field(description="agent at the other end")
    tolerance: float = Field(0.05, gt=0, le=1, description="accepted link quality imbalance")


class PatrolParams(Params):
    xmin: float = Field(description="territory block (m)")
    ymin: float = Field(description="territory block (m)")
    xmax: float = Field(description="territory block (m)")
    ymax: float = Field(description="territory block (m)")
    heartbeat: float = Field(1.0, gt=0, description="seconds between heartbeats")
    silence: float = Field(5.0, gt=0, description="a neighbour silent this long has failed (s)")


# --- the language -----------------------------------------------------------------------


@dataclass(frozen=True)
class Preposition:
    """One sub-task of a verb: its parameter model and a one-line description."""

    verb: str
    name: str
    params: type[Params]
    doc: str


@dataclass(frozen=True)
class Verb:
    """A verb of the language: scope (`local` or `team`) and the plugin that handles it."""

    name: str
    scope: str
    handled_by: str
    doc: str


VERBS: dict[str, Verb] = {}
PREPOSITIONS: dict[tuple[str, str], Preposition] = {}


def register_verb(name: str, *, scope: str, handled_by: str, doc: str) -> Verb:
    """Add a verb to the language (extensions use this for new task families)."""
    verb = Verb(name, scope, handled_by, doc)
    VERBS[name] = verb
    return verb


def register_preposition(verb: str, name: str, params: type[Params], doc: str) -> Preposition:
    """Add a preposition (sub-task) with its parameter model to an existing verb."""
    if verb not in VERBS:
        raise TaskError(f"cannot register {name!r}: unknown verb {verb!r}")
    prep = Preposition(verb, normalize_preposition(name), params, doc)
    PREPOSITIONS[(verb, prep.name)] = prep
    return prep


def normalize_preposition(name: str) -> str:
    """`'Avoid obstacles'`, `'avoid-obstacles'` and `'avoid_obstacles'` name the same sub-task."""
    return "_".join(name.strip().lower().replace("-", " ").split())


def prepositions_of(verb: str) -> list[str]:
    """Return the prepositions of `verb` in registration order."""
    return [p for (v, p) in PREPOSITIONS if v == verb]


def lookup(verb: str, preposition: str) -> Preposition:
    """Return the preposition, or raise TaskError naming what is known."""
    if verb not in VERBS:
        raise TaskError(f"unknown verb {shown(verb)}; expected one of {', '.join(VERBS)}")
    key = (verb, normalize_preposition(preposition))
    if key not in PREPOSITIONS:
        raise TaskError(
            f"{verb}: unknown preposition {shown(preposition)}; expected one of "
            f"{', '.join(prepositions_of(verb))}"
        )
    return PREPOSITIONS[key]


register_verb("NetWatch", scope="local", handled_by="MobiNetControl",
              doc="subscribe to information about the network")
register_verb("BotMotion", scope="local", handled_by="RobotMotionControl",
              doc="control low-level motion behaviours")
register_verb("RemoteBotMotion", scope="team", handled_by="MissionControl",
              doc="task a remote robot's movement")

_NETWATCH: list[tuple[str, type[Params], str]] = [
    ("node_position", NodePositionParams, "positions of the nodes as the network knows them"),
    ("network_topology", TopologyParams, "links of the whole network, articulation points"),
    ("path_cost", PathCostParams, "routes: next hop, hop count and path cost"),
    ("link_quality", LinkQualityParams, "delivery ratio (0..1) of each one-hop link"),
    ("neighbor_list", NeighborListParams, "symmetric one-hop neighbours"),
]
for _name, _model, _doc in _NETWATCH:
    register_preposition("NetWatch", _name, _model, _doc)

_BOTMOTION: list[tuple[str, type[Params], str]] = [
    ("randomwalk", RandomWalkParams, "wander, turning away from obstacles"),
    ("goto", GotoParams, "drive to (x, y)"),
    ("stop", StopParams, "halt: end every motion of the robot, whoever started it, and stay halted"),
    ("turn", TurnParams, "turn in place by an angle"),
    ("teleport", TeleportParams, "set the pose (simulator moves, robot re-localises)"),
    ("clear", ClearParams, "empty the behaviour stack, cancelling its tasks"),
    ("velocity", VelocityParams, "hold a linear and angular velocity"),
    ("avoid_obstacles", AvoidParams, "override motion when an obstacle is near"),
    ("forward", ForwardParams, "drive straight ahead a distance"),
    ("backward", BackwardParams, "drive straight back a distance"),
    ("say", SayParams, "play a tone sequence on the robot (audio cue)"),
]
for _name, _model, _doc in _BOTMOTION:
    register_preposition("BotMotion", _name, _model, _doc)

_REMOTEBOTMOTION: list[tuple[str, type[Params], str]] = [
    ("randomwalk", RandomWalkParams, "the robot wanders"),
    ("goto", GotoParams, "the robot drives to (x, y), expanded into local sub-tasks"),
    ("cancel", CancelParams, "cancel one remote task; all if omitted, which is a stop: every motion of the robot ends"),
    ("teleport", TeleportParams, "set the robot's pose"),
    ("forward", ForwardParams, "the robot drives ahead a distance"),
]
for _name, _model, _doc in _REMOTEBOTMOTION:
    register_preposition("RemoteBotMotion", _name, _model, _doc)

register_verb("Deploy", scope="team", handled_by="MissionControl",
              doc="run a deployment strategy (papers 000, 001, 002)")
_DEPLOY: list[tuple[str, type[Params], str]] = [
    ("widep", WidepParams, "PoI coverage (WiDep): step toward the PoI keeping RNG connectivity"),
    ("spread", SpreadParams, "potential-field self-deployment to distance d from neighbours"),
    ("relay", RelayParams, "hold position between source and destination, balancing link quality"),
    ("patrol", PatrolParams, "patrol a territory; take over a silent neighbour's block"),
]
for _name, _model, _doc in _DEPLOY:
    register_preposition("Deploy", _name, _model, _doc)


# --- results ----------------------------------------------------------------------------


class TaskState(str, enum.Enum):
    """Where a task stands. The last three are final."""

    PENDING = "pending"
    RUNNING = "running"
    SUCCEEDED = "succeeded"
    FAILED = "failed"
    CANCELLED = "cancelled"

    @property
    def done(self) -> bool:
        """True for succeeded, failed and cancelled."""
        return self in (TaskState.SUCCEEDED, TaskState.FAILED, TaskState.CANCELLED)


class AllocationResult(Model):
    """What the performer of a task reports: state, confidence, progress and typed values."""

    model_config = ConfigDict(frozen=True, extra="forbid", allow_inf_nan=False)

    state: TaskState = TaskState.PENDING
    confidence: float = Field(1.0, ge=0.0, le=1.0)
    progress: float = Field(0.0, ge=0.0, le=1.0)
    values: dict[str, FiniteJson] = Field(default_factory=dict)
    message: str = ""
    stamp: float = Field(default_factory=wall)


class Task(BBObject):
    """A unit of work: verb + preposition + typed parameters, with the performer's result.

    The requester publishes the task; the performer publishes changes carrying `result`.
    Removing a task from the blackboard cancels it (Cougaar's rescind).
    """

    durable: ClassVar[bool] = True

    verb: str
    preposition: str
    params: SerializeAsAny[Params] = Field(default_factory=NoParams)
    source: NameOrEmpty = Field("", description="the agent that asked ('' before it is sent)")
    destination: Name | None = None
    parent: str | None = None
    result: AllocationResult | None = None
    created: float = Field(default_factory=wall)

    def __init__(self, **data: Any) -> None:
        try:
            super().__init__(**data)
        except ValidationError as err:
            raise TaskError(describe_validation(err, _label(data))) from None

    @classmethod
    def parse(cls, data: Any) -> Self:
        """Validate a task from plain data (a dict or JSON text); raise TaskError if invalid."""
        try:
            if isinstance(data, (str, bytes)):
                return cls.model_validate_json(data)
            return cls.model_validate(data)
        except ValidationError as err:
            raise TaskError(describe_validation(err, _label(data))) from None

    @model_validator(mode="before")
    @classmethod
    def _typed_params(cls, data: Any) -> Any:
        if not isinstance(data, dict):
            return data
        verb, prep = data.get("verb"), data.get("preposition")
        if not isinstance(verb, str) or not isinstance(prep, str):
            return data  # field validation reports the missing or mistyped field
        spec = lookup(verb, prep)
        raw = data.get("params")
        if raw is None:
            raw = {}
        if isinstance(raw, Params):
            if not isinstance(raw, spec.params):
                raw = raw.model_dump()
            else:
                return {**data, "preposition": spec.name}
        if not isinstance(raw, dict):
            raise TaskError(f"{spec.name}: params: expected a table of parameters, got {shown(raw)}")
        try:
            params = spec.params.model_validate(raw)
        except ValidationError as err:
            raise TaskError(describe_validation(err, spec.name)) from None
        return {**data, "preposition": spec.name, "params": params}

    @field_validator("verb")
    @classmethod
    def _known_verb(cls, verb: str) -> str:
        if verb not in VERBS:
            raise TaskError(f"unknown verb {shown(verb)}; expected one of {', '.join(VERBS)}")
        return verb

    @property
    def state(self) -> TaskState:
        """The result's state, `pending` while there is no result."""
        return self.result.state if self.result else TaskState.PENDING

    @property
    def done(self) -> bool:
        """True once the performer reported a final state."""
        return self.state.done

    def params_as(self, kind: type[P]) -> P:
        """Return the parameters typed as `kind`; TaskError when this task's preposition has others.

        `match task.params: case GotoParams(): ...` narrows the same way inside a dispatch.
        """
        if not isinstance(self.params, kind):
            raise TaskError(f"{self.verb} {self.preposition}: parameters are {type(self.params).__name__}, "
                            f"not {kind.__name__}")
        return self.params

    def with_result(self, state: TaskState | str | None = None, **fields: Any) -> Self:
        """Return this task with its result updated (unspecified fields kept)."""
        base = self.result.model_dump() if self.result else {}
        base.pop("stamp", None)
        if state is not None:
            base["state"] = TaskState(state)
        base.update(fields)
        return self.evolve(result=AllocationResult(**base))

    def describe(self) -> str:
        """One line for logs and the CLI: `BotMotion goto x=1.0 y=2.0 -> robot2`."""
        args = " ".join(f"{k}={v}" for k, v in self.params.model_dump(exclude_none=True).items())
        dest = f" -> {self.destination}" if self.destination else ""
        return f"{self.verb} {self.preposition} {args}".rstrip() + dest


def _label(data: Any) -> str:
    if isinstance(data, dict) and isinstance(data.get("preposition"), str):
        return normalize_preposition(data["preposition"])
    return "task"


def _shown_default(value: Any) -> str:
    """A default as a user writes it on the command line: JSON for lists and tables, else its str."""
    if isinstance(value, list | tuple | dict):
        return json.dumps(value)
    return str(value)


def language_table() -> str:
    """Return the task language as a Markdown table (README and `erni tasks`)."""
    rows = ["| verb | preposition | parameters (units) | what it does |", "|---|---|---|---|"]
    for (verb, name), prep in PREPOSITIONS.items():
        params = []
        for fname, f in prep.params.model_fields.items():
            req = "" if not f.is_required() else " (required)"
            default = "" if f.is_required() else f" = {_shown_default(f.get_default(call_default_factory=True))}"
            params.append(f"`{fname}`{default}{req}: {f.description or ''}".rstrip(": "))
        rows.append(f"| {verb} | `{name}` | {'; '.join(params) or '—'} | {prep.doc} |")
    return "\n".join(rows)
