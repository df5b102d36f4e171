"""The spoken and typed command grammar: `[<subject>] <verb> <object>` over the task language.

`parse(text)` turns one utterance into a `Command` (who, what, with which parameters, in
task-language units: metres and degrees) or raises `Refusal` whose message is the short
sentence the operator hears ("How far?", "I didn't understand fly"). Numbers may be words
("two point five", "minus three", "one hundred twenty") or digits; distances may be in
metres (the default), centimetres, feet or inches. `vocabulary()` lists every word the
grammar knows, for a speech recogniser restricted to them.
"""

from __future__ import annotations

import re
from dataclasses import dataclass, field
from typing import Any

from erni.blackboard.errors import ErniError
from erni.blackboard.tasks import PREPOSITIONS

# Actions the grammar always knows; deployment strategies come from the task language's
# `Deploy` verb (spread, widep, relay, patrol, and any other registered there).
STANDARD_ACTIONS = ("goto", "forward", "backward", "turn", "stop", "cancel", "randomwalk", "teleport")
STRATEGY_VERB = "Deploy"

ONES = {"zero": 0, "oh": 0, "one": 1, "two": 2, "three": 3, "four": 4, "five": 5, "six": 6,
        "seven": 7, "eight": 8, "nine": 9}
TEENS = {"ten": 10, "eleven": 11, "twelve": 12, "thirteen": 13, "fourteen": 14, "fifteen": 15,
         "sixteen": 16, "seventeen": 17, "eighteen": 18, "nineteen": 19}
TENS = {"twenty": 20, "thirty": 30, "forty": 40, "fifty": 50, "sixty": 60, "seventy": 70,
        "eighty": 80, "ninety": 90}
NEGATIVE = {"minus", "negative"}
UNITS = {"metre": 1.0, "metres": 1.0, "meter": 1.0, "meters": 1.0, "m": 1.0,
         "centimetre": 0.01, "centimetres": 0.01, "centimeter": 0.01, "centimeters": 0.01, "cm": 0.01,
         "foot": 0.3048, "feet": 0.3048, "ft": 0.3048, "inch": 0.0254, "inches": 0.0254}
DEGREES = {"degree", "degrees", "deg"}
EVERYONE = {"everyone", "everybody", "all", "team"}
FILLER = {"please", "now"}
MOVE = {"go", "move", "drive", "head"}

ATTENTION = ("attention", "wake up")
_SPOKEN_STRATEGIES = {"spread", "widep", "relay", "patrol"}
SLEEP = ("go to sleep", "sleep", "stand by")

_TOKEN = re.compile(r"\[unk\]|-?\d+(?:\.\d+)?|-?\.\d+|[a-z]+")


class Refusal(ErniError):
    """An utterance that asks for nothing the team can do; the message is what to say back."""


@dataclass(frozen=True)
class Command:
    """One understood utterance: a control word, or an action for some robots.

    `kind` is "attention", "sleep" or "action". `robots` holds the robot numbers named,
    `everyone` is True for "everyone"/"all robots", and neither means "the last targets".
    """

    kind: str
    action: str = ""
    params: dict[str, Any] = field(default_factory=dict)
    robots: tuple[int, ...] = ()
    everyone: bool = False

    @property
    def names_targets(self) -> bool:
        """True when the utterance said who it is for."""
        return self.everyone or bool(self.robots)


def strategies() -> list[str]:
    """Return the deployment strategies of the task language (the `Deploy` prepositions)."""
    return [name for (verb, name) in PREPOSITIONS if verb == STRATEGY_VERB]


def _plain_strategies() -> dict[str, str]:
    """Strategies without a spoken form of their own, said by name: words -> name."""
    found = {}
    for (verb, name), prep in PREPOSITIONS.items():
        if verb != STRATEGY_VERB or name in _SPOKEN_STRATEGIES:
            continue
        if not any(f.is_required() for f in prep.params.model_fields.values()):
            found[name.replace("_", " ")] = name
    return found


def tokens(text: str) -> list[str]:
    """Split an utterance into lower-case words and numbers (punctuation dropped)."""
    return _TOKEN.findall(text.lower().replace("go-to", "go to"))


def _round(value: float) -> float:
    return round(value, 6)


class _Reader:
    """A cursor over the tokens of one utterance."""

    def __init__(self, words: list[str]) -> None:
        self.words = words
        self.i = 0

    def peek(self, ahead: int = 0) -> str:
        j = self.i + ahead
        return self.words[j] if j < len(self.words) else ""

    def take(self, *options: str) -> str:
        """Consume and return the next word if it is one of `options`, else return ''."""
        word = self.peek()
        if word and word in options:
            self.i += 1
            return word
        return ""

    def take_seq(self, phrase: str) -> bool:
        """Consume a multi-word phrase if it comes next."""
        parts = phrase.split()
        if self.words[self.i:self.i + len(parts)] == parts:
            self.i += len(parts)
            return True
        return False

    def rest(self) -> list[str]:
        return self.words[self.i:]

    def done(self) -> bool:
        while self.take(*FILLER):
            pass
        return self.i >= len(self.words)

    # -- numbers ---------------------------------------------------------------------------

    def number(self) -> float | None:
        """Consume a number in digits or words; return None (consuming nothing) if there is none."""
        start = self.i
        sign = -1.0 if self.take(*NEGATIVE) else 1.0
        word = self.peek()
        value: float | None = None
        if re.fullmatch(r"-?\d+(?:\.\d+)?|-?\.\d+", word):
            self.i += 1
            value = float(word)
        else:
            value = self._integer_words()
            if value is not None and self.peek() == "point":
                self.i += 1
                digits = ""
                while self.peek() in ONES:
                    digits += str(ONES[self.words[self.i]])
                    self.i += 1
                if not digits:
                    self.i = start
                    return None
                value = float(f"{int(value)}.{digits}")
        if value is None:
            self.i = start
            return None
        return sign * value

    def _integer_words(self) -> float | None:
        start = self.i
        total = 0
        if (self.peek() == "a" or self.peek() in ONES) and self.peek(1) == "hundred":
            total = 100 * ONES.get(self.peek(), 1)
            self.i += 2
            self.take("and")
        word = self.peek()
        if word in TEENS:
            total += TEENS[word]
            self.i += 1
        elif word in TENS:
            total += TENS[word]
            self.i += 1
            if self.peek() in ONES and self.peek() not in ("zero", "oh"):
                total += ONES[self.words[self.i]]
                self.i += 1
        elif word in ONES and (self.i == start or word not in ("zero", "oh")):
            total += ONES[word]
            self.i += 1
        elif self.i == start:
            return None
        return total

    def distance(self) -> float | None:
        """Consume `<number> [<unit>]`; return metres, or None when no number comes next."""
        value = self.number()
        if value is None:
            return None
        unit = self.take(*UNITS)
        return _round(value * (UNITS[unit] if unit else 1.0))

    def robot_number(self) -> int | None:
        """Consume a robot number; None (consuming nothing) when no number comes next."""
        value = self.number()
        if value is None:
            return None
        if value != int(value) or value < 0:
            raise Refusal(f"I don't know robot {value:g}")
        return int(value)


def parse(text: str) -> Command:
    """Parse one utterance into a Command, or raise Refusal with the reason to say back."""
    words = tokens(text)
    if not words:
        raise Refusal("I didn't hear a command")
    r = _Reader(words)
    for phrase in ATTENTION:
        if r.take_seq(phrase) and r.done():
            return Command("attention")
        r.i = 0
    for phrase in SLEEP:
        if r.take_seq(phrase) and r.done():
            return Command("sleep")
        r.i = 0
    robots, everyone = _subject(r)
    action, params = _verb_object(r)
    if not r.done():
        raise Refusal(f"I didn't understand {' '.join(r.rest())}")
    return Command("action", action, params, robots, everyone)


def _subject(r: _Reader) -> tuple[tuple[int, ...], bool]:
    if r.take(*EVERYONE):
        r.take("robots")
        return (), True
    if not r.take("robot", "robots"):
        return (), False
    first = r.robot_number()
    if first is None:
        raise Refusal("Which robot?")
    numbers = [first]
    while True:
        mark = r.i
        r.take("and")
        r.take("robot")
        more = r.robot_number()
        if more is None:
            r.i = mark
            break
        numbers.append(more)
    return tuple(dict.fromkeys(numbers)), False


def _verb_object(r: _Reader) -> tuple[str, dict[str, Any]]:
    word = r.peek()
    if not word:
        raise Refusal("What should they do?")
    if r.take("stop", "halt", "freeze"):
        return "stop", {}
    if r.take("cancel", "abort"):
        r.take("that", "it")
        return "cancel", {}
    if r.take_seq("random walk") or r.take("randomwalk", "wander", "explore"):
        r.take("around")
        return "randomwalk", {}
    if r.take("spread"):
        r.take("out")
        d = r.distance()
        return "spread", {} if d is None else {"distance": _positive(d)}
    if r.take("cover") or r.take_seq("deploy to"):
        return "widep", _point(r)
    if r.take("relay"):
        return "relay", _relay(r)
    if r.take("patrol"):
        return "patrol", _patrol(r)
    for words, name in _plain_strategies().items():
        if r.take_seq(words):
            return name, {}
    if r.take("teleport", "jump"):
        r.take("to")
        return "teleport", _point(r, heading=True)
    if r.take("turn", "rotate"):
        return "turn", _turn(r)
    if r.take("goto"):
        return "goto", _point(r)
    moved = r.take(*MOVE)
    if moved and r.take("to"):
        return "goto", _point(r)
    if r.take("forward", "forwards", "ahead"):
        return "forward", _distance(r)
    if r.take("back", "backward", "backwards", "backup", "reverse"):
        r.take("up")
        return "backward", _distance(r)
    if moved:
        raise Refusal("Go where?")
    if word == "[unk]":
        raise Refusal("I didn't understand")
    raise Refusal(f"I didn't understand {word}")


def _positive(d: float) -> float:
    if d <= 0:
        raise Refusal("The distance must be more than zero")
    return d


def _distance(r: _Reader) -> dict[str, Any]:
    d = r.distance()
    if d is None:
        raise Refusal("How far?")
    return {"distance": _positive(d)}


def _relay(r: _Reader) -> dict[str, Any]:
    """`relay between [robot] A and [robot] B`: robot numbers, named by the dialogue."""
    r.take("between", "for")
    ends = []
    for _ in range(2):
        r.take("robot")
        end = r.robot_number()
        if end is None:
            raise Refusal("Relay between which robots?")
        ends.append(end)
        r.take("and")
    return {"source": ends[0], "destination": ends[1]}


def _patrol(r: _Reader) -> dict[str, Any]:
    """`patrol [from] X1 Y1 to X2 Y2`: the territory block's corners."""
    r.take("from")
    a = _point(r)
    if not r.take("to"):
        raise Refusal("Patrol from where to where?")
    b = _point(r)
    return {"xmin": min(a["x"], b["x"]), "ymin": min(a["y"], b["y"]),
            "xmax": max(a["x"], b["x"]), "ymax": max(a["y"], b["y"])}


def _turn(r: _Reader) -> dict[str, Any]:
    if r.take("around"):
        return {"angle": 180.0}
    side = r.take("left", "right")
    r.take("by")
    angle = r.number()
    if angle is not None:
        r.take(*DEGREES)
    if not side:
        side = r.take("left", "right")
    if angle is None:
        if not side:
            raise Refusal("Turn which way?")
        angle = 90.0
    if side == "right":
        angle = -angle
    return {"angle": _round(angle)}


def _point(r: _Reader, heading: bool = False) -> dict[str, Any]:
    r.take("x")
    x = r.distance()
    r.take("and", "comma")
    r.take("y")
    y = r.distance() if x is not None else None
    if x is None or y is None:
        raise Refusal("Where to? Say x and y")
    params: dict[str, Any] = {"x": x, "y": y}
    if heading and r.take("facing", "heading"):
        h = r.number()
        if h is None:
            raise Refusal("Facing which heading?")
        r.take(*DEGREES)
        params["heading"] = _round(h)
    return params


def vocabulary() -> list[str]:
    """Every word the grammar knows, for a recogniser restricted to them."""
    words: set[str] = set()
    for group in (ONES, TEENS, TENS, NEGATIVE, UNITS, DEGREES, EVERYONE, FILLER, MOVE):
        words.update(group)
    for phrase in ATTENTION + SLEEP:
        words.update(phrase.split())
    for spoken in _plain_strategies():
        words.update(spoken.split())
    words.update("""spread out cover deploy relay between for patrol from robot robots and a hundred point stop halt freeze cancel abort that it random walk
        wander explore around teleport jump to turn rotate left right by goto forward forwards
        ahead back backward backwards reverse up x y comma facing heading""".split())
    words -= {"m", "cm", "ft", "deg", "randomwalk", "goto", "backup"}  # written forms only
    return sorted(words)
