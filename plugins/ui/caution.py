"""When an operator's command waits for a "yes" before it is carried out, and why.

Spoken commands (`read_back` set) are read back when they are risky however sure the hearing; typed
ones (`confirm_beyond` set) are confirmed once when they would leave the map. A stop never waits.
The `Dialogue` asks its `Caution` about each command it understood.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, Generic, TypeVar, overload

from erni.blackboard import Task
from erni.plugins.ui.grammar import _NUMBER, ONES, STRATEGY_VERB, TEENS, TENS, tokens

if TYPE_CHECKING:
    from erni.plugins.ui.dialogue import Reply, RobotView


V = TypeVar("V")


class Cautious(Generic[V]):
    """An attribute of a dialogue that its `Caution` holds: `dialogue.read_back_numbers = False` changes
    what the dialogue reads back."""

    def __set_name__(self, owner: type[Any], name: str) -> None:
        self.name = name

    @overload
    def __get__(self, dialogue: None, owner: type[Any] | None = None) -> Cautious[V]: ...

    @overload
    def __get__(self, dialogue: object, owner: type[Any] | None = None) -> V: ...

    def __get__(self, dialogue: Any, owner: type[Any] | None = None) -> V | Cautious[V]:
        if dialogue is None:
            return self  # read on the class
        value: V = getattr(dialogue.caution, self.name)
        return value

    def __set__(self, dialogue: Any, value: V) -> None:
        setattr(dialogue.caution, self.name, value)


def _num(v: float) -> str:
    """A number as the dialogue says it: at most two decimals, no trailing zeros."""
    return f"{round(v, 2):g}"


@dataclass
class Caution:
    """What makes a command wait for a "yes": the read-back and confirmation bounds of one dialogue."""

    read_back: float | None = None  # metres: a longer move is read back first; None: nothing is read back
    # metres (math.inf: no bound): with `read_back` None (typed), a move that leaves the map is confirmed
    # once, and where `area` cannot tell, one longer than this; None: typed moves run at once
    confirm_beyond: float | None = None
    read_back_numbers: bool = False  # a motion command heard with a number is read back too
    area: tuple[float, float, float, float] | None = None  # xmin, ymin, xmax, ymax of the map

    def risk(self, reply: Reply, views: Mapping[str, RobotView]) -> str:
        """Why a command waits for a "yes" before it is carried out; '' when it is carried out at once.

        Spoken (`read_back` set), however sure the hearing: a command to several robots, a clear, a
        teleport, a deployment, a held velocity, a move that leaves the map or is longer than
        `read_back` metres, and with `read_back_numbers` one that says a number. Typed (`confirm_beyond`
        set): only a move that leaves the map (`beyond`). A stop never waits.
        """
        if reply.action == "stop" or not (reply.tasks or reply.action == "speed"):
            return ""
        if self.read_back is None:
            if self.confirm_beyond is None:
                return ""
            return next((why for t in reply.tasks if (why := self.beyond(t, views, self.confirm_beyond))), "")
        if len(set(reply.targets)) > 1:
            return "several robots"
        if not reply.tasks:
            return ""  # a cruise speed for one robot
        for t in reply.tasks:
            if t.preposition == "clear":  # ends every tasked behaviour: a held stop, the network guard's too
                return "clear"
            if t.preposition == "teleport":  # on a real robot a teleport re-bases its odometry
                return "teleport"
            if t.verb == STRATEGY_VERB:  # a deployment moves the robot for as long as it runs
                return "deployment"
        for t in reply.tasks:
            why = self.beyond(t, views, self.read_back, always=True)
            if why:
                return why
        if self.read_back_numbers and quantities(reply.heard):
            return "number"
        return ""

    def beyond(self, t: Task, views: Mapping[str, RobotView], limit: float, always: bool = False) -> str:
        """Whether a task's move leaves the map: "off the map" when it ends outside `area` (a goal, the
        end of a forward or backward from the robot's pose and heading, a patrol block's corner);
        "unbounded" for a held velocity; "far" when it is longer than `limit` metres: `always`, or only
        where `area` cannot tell (no floor plan, or no pose to measure a forward or backward from)."""
        p = t.params.model_dump()
        v = views.get(t.destination or "")
        here = (v.x, v.y) if v is not None and v.x is not None and v.y is not None else None
        ends: list[tuple[float, float]] = []
        length: float | None = None
        if t.preposition in ("forward", "backward"):
            length = p["distance"]
            if here is not None and v is not None and v.theta is not None:
                d = length if t.preposition == "forward" else -length
                ends.append((here[0] + d * math.cos(v.theta), here[1] + d * math.sin(v.theta)))
        elif t.preposition == "velocity":
            return "unbounded" if p["v"] != 0 else ""
        elif t.preposition in ("goto", "teleport", "widep") and "x" in p and "y" in p:
            ends.append((p["x"], p["y"]))
            if here is not None:
                length = math.hypot(p["x"] - here[0], p["y"] - here[1])
        elif t.preposition == "patrol":
            ends += [(p["xmin"], p["ymin"]), (p["xmax"], p["ymax"])]
        if self.area is not None and ends:
            xmin, ymin, xmax, ymax = self.area
            if not all(xmin <= x <= xmax and ymin <= y <= ymax for x, y in ends):
                return "off the map"
            if not always:
                return ""  # on the map: the floor plan decides
        return "far" if length is not None and length > limit else ""

    def why(self, risk: str) -> str:
        """A typed command's confirmation says why it is asked."""
        if risk == "off the map":
            xmin, ymin, xmax, ymax = self.area or (0.0, 0.0, 0.0, 0.0)
            return f"it ends off the map (x {_num(xmin)} to {_num(xmax)}, y {_num(ymin)} to {_num(ymax)})"
        if risk == "unbounded":
            return "it drives until stopped"
        return f"more than {_num(self.confirm_beyond or 0.0)} metres"


_NUMBER_WORDS = {*ONES, *TEENS, *TENS, "hundred", "thousand", "point"}
_ROBOT_LIST = {"robot", "robots", "and"}  # "robots one two and three", "relay between robot 1 and ..."


def quantities(text: str) -> bool:
    """Whether an utterance says a quantity (a distance, an angle, a coordinate): a number that does
    not name a robot ("robot 2 turn 180 degrees" does, "robots one and two stop" does not)."""
    naming = False  # inside a list of robot numbers
    for w in tokens(text):
        number = w in _NUMBER_WORDS or _NUMBER.fullmatch(w) is not None
        if number and not naming:
            return True
        naming = w in ("robot", "robots") or (naming and (number or w in _ROBOT_LIST))
    return False
