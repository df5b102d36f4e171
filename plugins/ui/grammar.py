"""The spoken and typed command grammar: `[<subject>] <verb> <object>` over the task language.

`parse(text)` turns one utterance into a `Command` (who, what, with which parameters, in
task-language units: metres, degrees, metres per second) or raises `Refusal` whose message is
the short sentence the operator hears, saying what was expected ("How far? Say a distance, like
forward 2 metres", "I didn't understand fly; did you mean forward?"). Numbers may be words
("two point five", "minus three", "one hundred twenty", "half a") or digits; distances may be
in metres (the default), centimetres, feet or inches. Politeness and fillers ("please", "uh",
"hey", "could you") are dropped wherever they stand. Naming robots without a verb selects them;
questions ("robot one status", "where are you", "how many robots") are queries answered from
the team's state. `vocabulary()` lists every word the grammar knows and `PHRASES` the fixed
phrases, for a speech recogniser restricted to them (see `erni.plugins.ui.jsgf`).
"""

from __future__ import annotations

import difflib
import re
from dataclasses import dataclass, field
from typing import Any

from erni.blackboard.errors import ErniError
from erni.blackboard.tasks import PREPOSITIONS

# Actions the grammar always knows; deployment strategies come from the task language's
# `Deploy` verb (spread, widep, relay, patrol, and any other registered there).
STANDARD_ACTIONS = ("goto", "forward", "backward", "turn", "stop", "cancel", "randomwalk", "teleport",
                    "velocity", "avoid_obstacles", "clear")
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
EVERYONE_PHRASES = ("every robot", "all of you", "you all")
MOVE = {"go", "move", "drive", "head", "come"}
STOP_WORDS = ("stop", "halt", "freeze")

# Dropped wherever they stand: politeness, hesitation, address.
FILLER = {"please", "uh", "um", "umm", "uhm", "er", "erm", "ah", "hey", "okay", "ok", "now", "kindly",
          "thanks", "just", "alright", "the"}
FILLER_PHRASES = ("thank you", "could you", "can you", "would you", "will you")

ATTENTION = ("attention", "wake up", "listen", "listen up")
SLEEP = ("go to sleep", "sleep", "stand by")
# The answers to a read-back ("Robot 1, go forward 52 metres: say yes to confirm").
CONFIRM = ("yes", "confirm", "yes confirm", "affirmative")
DENY = ("no", "negative")
_SPOKEN_STRATEGIES = {"spread", "widep", "relay", "patrol"}

# Questions answered from the team's state: kind -> phrases said after an optional subject.
QUESTIONS: dict[str, tuple[str, ...]] = {
    "status": ("status", "status report", "report", "report status", "how are you", "how are you doing",
               "what is your status", "what is their status"),
    "where": ("where are you", "where are they", "where", "position", "location", "what is your position",
              "what is their position"),
    "doing": ("what are you doing", "what are they doing", "task", "what is your task"),
    "battery": ("battery", "battery level", "what is your battery", "what is your battery level",
                "how is your battery"),
    "link": ("link", "link quality", "what is your link", "what is your link quality", "how is your link"),
}
COUNT_QUESTIONS = ("how many robots", "how many robots are there", "how many robots are up", "how many")

_TOKEN = re.compile(r"\[unk\]|-?\d+(?:\.\d+)?|-?\.\d+|[a-z]+")
_NUMBER = re.compile(r"-?\d+(?:\.\d+)?|-?\.\d+")


class Refusal(ErniError):
    """An utterance that asks for nothing the team can do; the message is what to say back."""


@dataclass(frozen=True)
class Command:
    """One understood utterance: a control word, a selection, a question, or an action.

    `kind` is "attention", "sleep", "confirm" and "deny" (the answers to a read-back), "select"
    (robots named without a verb), "query" (`action`
    is the question: status, where, doing, battery, link, count) or "action". `robots` holds the
    robot numbers named, `everyone` is True for "everyone"/"all robots", and neither means "the
    last targets".
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

    @property
    def is_stop(self) -> bool:
        """True for a stop ("stop", "everyone halt", "robot 2 freeze"): never gated, never refused."""
        return self.kind == "action" and self.action == "stop"


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
    return _TOKEN.findall(text.lower().replace("go-to", "go to").replace("m/s", "metres per second"))


def without_fillers(words: list[str]) -> list[str]:
    """Drop politeness and hesitation words and phrases wherever they stand."""
    out: list[str] = []
    i = 0
    while i < len(words):
        pair = " ".join(words[i:i + 2])
        if pair in FILLER_PHRASES:
            i += 2
            continue
        if words[i] not in FILLER:
            out.append(words[i])
        i += 1
    return out


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

    def take_rest(self, phrases: tuple[str, ...]) -> bool:
        """Consume the rest of the utterance if it is exactly one of `phrases`."""
        rest = " ".join(self.words[self.i:])
        if rest in phrases:
            self.i = len(self.words)
            return True
        return False

    def rest(self) -> list[str]:
        return self.words[self.i:]

    def done(self) -> bool:
        return self.i >= len(self.words)

    # -- numbers ---------------------------------------------------------------------------

    def number(self) -> float | None:
        """Consume a number in digits or words; return None (consuming nothing) if there is none."""
        start = self.i
        sign = -1.0 if self.take(*NEGATIVE) else 1.0
        word = self.peek()
        value: float | None = None
        if _NUMBER.fullmatch(word):
            self.i += 1
            value = float(word)
        elif word == "half" or (word in ("a", "an") and self.peek(1) == "half"):
            self.i += 1 if word == "half" else 2
            self.take("a", "an")
            value = 0.5
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
        if self.words[self.i:self.i + 3] == ["and", "a", "half"]:
            self.i += 3
            value += 0.5
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
            raise Refusal(f"I don't know robot {value:g}; robots have whole numbers, like robot 3")
        return int(value)


def parse(text: str, wake: tuple[str, ...] = ATTENTION) -> Command:
    """Parse one utterance into a Command, or raise Refusal with the reason to say back.

    `wake`: the phrases that wake a standing-by dialogue (kind "attention"); default `ATTENTION`.
    """
    words = without_fillers(tokens(text))
    if not words:
        raise Refusal("I didn't hear a command")
    r = _Reader(words)
    if r.take_rest(tuple(wake)):
        return Command("attention")
    if r.take_rest(SLEEP):
        return Command("sleep")
    if r.take_rest(CONFIRM):
        return Command("confirm")
    if r.take_rest(DENY):
        return Command("deny")
    if r.take_rest(COUNT_QUESTIONS):
        return Command("query", "count")
    asked = _question_about(r)
    if asked is not None:
        return asked
    robots, everyone = _subject(r)
    if r.done():
        if robots or everyone:
            return Command("select", robots=robots, everyone=everyone)
        raise Refusal("I didn't hear a command")
    for kind, phrases in QUESTIONS.items():
        if r.take_rest(phrases):
            return Command("query", kind, robots=robots, everyone=everyone)
    action, params = _verb_object(r)
    if not robots and not everyone and not r.done():
        robots, everyone = _subject(r)  # "stop, everyone", "turn left robot two"
    if not r.done():
        raise Refusal(f"I didn't understand {' '.join(r.rest())}; say one command at a time, like "
                      "robot 1 go forward 2 metres")
    return Command("action", action, params, robots, everyone)


def _question_about(r: _Reader) -> Command | None:
    """`where is robot 2`, `what is robot 2 doing`, `where is everyone`: a question naming its subject."""
    start = r.i
    kind = ""
    if r.take_seq("where is") or r.take_seq("where are"):
        kind = "where"
    elif r.take_seq("what is") or r.take_seq("what are"):
        kind = "doing"
    elif r.take_seq("how is") or r.take_seq("how are"):
        kind = "status"
    if not kind:
        return None
    if r.peek() not in ("robot", "robots", *EVERYONE):
        r.i = start
        return None
    robots, everyone = _subject(r)
    if kind == "doing":
        if r.take_rest(("doing",)):
            return Command("query", "doing", robots=robots, everyone=everyone)
        for other in ("battery", "link", "status", "position"):
            if r.take_rest((other, f"{other} level", f"{other} quality")):
                return Command("query", "where" if other == "position" else other, robots=robots, everyone=everyone)
        raise Refusal("What about them? Ask what is robot 2 doing, or robot 2 status")
    if not r.done():
        r.take("doing")
    if not r.done():
        raise Refusal(f"I didn't understand {' '.join(r.rest())}; ask where is robot 2, or robot 2 status")
    return Command("query", kind, robots=robots, everyone=everyone)


def _subject(r: _Reader) -> tuple[tuple[int, ...], bool]:
    if any(r.take_seq(phrase) for phrase in EVERYONE_PHRASES):
        return (), True
    if r.take(*EVERYONE):
        r.take("robots")
        return (), True
    if not r.take("robot", "robots"):
        return (), False
    r.take("number")
    first = r.robot_number()
    if first is None:
        raise Refusal("Which robot? Say robot and its number, like robot 3")
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


# The spoken forms of each action, in JSGF over the rules <number>, <distance>, <point>, <n> and
# <unit> of erni.plugins.ui.jsgf. The speech recogniser decodes these forms and nothing else, so a
# form added here is heard as well as typed; tests/ui/test_spoken_grammar.py parses sentences drawn from
# every form and checks they mean the action named.
_STOP = " | ".join(STOP_WORDS)
SPOKEN_ACTIONS: dict[str, tuple[str, ...]] = {
    "stop": (f"({_STOP}) [everything | moving]",),
    "cancel": ("(cancel | abort) [that | it | everything | all tasks]", "undo [that | it]"),
    "clear": ("clear [all | everything] [tasks]",),
    "randomwalk": ("[do a | start a] random walk", "(wander | explore) [around]"),
    "avoid_obstacles": ("avoid obstacles [on | off]", "stop avoiding obstacles", "do not avoid obstacles"),
    "speed": ("[go | move | drive] (faster | slower | quicker)", "speed up", "slow down",
              "set (speed | velocity) [to] <number> [<unit> per second]"),
    "velocity": ("(drive | move | go) at <number> [<unit> per second]",),
    "spread": ("spread [out] [<distance>]",),
    "widep": ("cover <point>", "deploy to <point>"),
    "relay": ("relay between [robot] <n> and ([robot] <n> | control [node] | base [station])",),
    "patrol": ("patrol [from] <point> to <point>",),
    "teleport": ("(teleport | jump) [to] <point> [facing <number> [degrees]]",),
    "turn": ("(turn | rotate) around", "(turn | rotate) (left | right) [<number> [degrees]]",
             "(turn | rotate) <number> [degrees] [left | right]"),
    "goto": ("(go | move | drive | head | come) to <point>",),
    "goto_robot": ("(go | move | drive | head | come) to robot <n>",),
    "forward": ("[go | move | drive | head] (forward | forwards | ahead | straight) <distance>",),
    "backward": ("[go | move | drive | head] (back | backward | backwards | reverse) [up] <distance>",),
}

# Words that begin a command, for "did you mean ...?"
VERB_WORDS = ("stop", "halt", "freeze", "cancel", "abort", "clear", "random", "wander", "explore", "spread",
              "cover", "deploy", "relay", "patrol", "teleport", "jump", "turn", "rotate", "go", "move", "drive",
              "head", "forward", "ahead", "back", "backward", "reverse", "velocity", "speed", "set", "avoid",
              "attention", "sleep", "status", "where", "battery", "link")


def did_you_mean(word: str) -> str:
    """Return "; did you mean X?" for the closest command word, or a hint of what a command looks like."""
    close = difflib.get_close_matches(word, VERB_WORDS, n=1, cutoff=0.6)
    if close:
        return f"; did you mean {close[0]}?"
    return "; say a command like robot 1 go forward 2 metres"


Found = tuple[str, dict[str, Any]] | None
"""An action and its parameters, or None when the words are not of this kind of command."""


def _verb_object(r: _Reader) -> tuple[str, dict[str, Any]]:
    word = r.peek()
    if not word:
        raise Refusal("What should they do?")
    if r.take_seq("stop avoiding obstacles") or r.take_seq("do not avoid obstacles") \
            or r.take_seq("don t avoid obstacles"):
        return "avoid_obstacles", {"enabled": False}
    r.take_seq("do a") or r.take_seq("start a") or r.take("start", "do")
    for kind in (_control_verb, _speed_verb, _strategy_verb, _motion_verb):
        found = kind(r)
        if found is not None:
            return found
    if word == "[unk]":
        raise Refusal("I didn't understand; say a command like robot 1 go forward 2 metres")
    raise Refusal(f"I didn't understand {word}{did_you_mean(word)}")


def _control_verb(r: _Reader) -> Found:
    """stop, cancel, clear, random walk, avoid obstacles."""
    if r.take(*STOP_WORDS):
        while r.take(*STOP_WORDS, "everything", "moving", "all"):
            pass
        return "stop", {}
    if r.take("cancel", "abort", "undo"):
        that = r.take("that", "it", "this")
        every = r.take("everything") or r.take_seq("all tasks") or r.take("tasks", "task", "all")
        return "cancel", {} if every and not that else {"last": True}  # "cancel that": the last command
    if r.take("clear"):
        r.take("all", "everything")
        r.take("tasks", "behaviours", "behaviors", "stack")
        return "clear", {}
    if r.take_seq("random walk") or r.take("randomwalk", "wander", "explore"):
        r.take("around")
        return "randomwalk", {}
    if r.take("avoid"):
        if not r.take("obstacles"):
            raise Refusal("Avoid what? Say avoid obstacles")
        if r.take("off"):
            return "avoid_obstacles", {"enabled": False}
        r.take("on")
        params: dict[str, Any] = {"enabled": True}
        if r.take("at", "within", "by"):
            params["distance"] = _distance(r)["distance"]
        return "avoid_obstacles", params
    return None


def _speed_verb(r: _Reader) -> Found:
    """faster, slower, a cruise speed, a held velocity."""
    mark = r.i
    r.take(*MOVE)
    if r.take("faster", "quicker") or r.take_seq("speed up"):
        return "speed", {"change": "faster"}
    if r.take("slower") or r.take_seq("slow down"):
        return "speed", {"change": "slower"}
    r.i = mark
    if r.take_seq("set velocity") or r.take_seq("set speed") or r.take("velocity", "speed"):
        return "speed", _cruise(r)  # the cruise speed of later moves
    if r.take_seq("drive at") or r.take_seq("move at") or r.take_seq("go at"):
        return "velocity", _velocity(r)
    return None


def _strategy_verb(r: _Reader) -> Found:
    """The deployment strategies: spread, cover, relay, patrol and those without parameters."""
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
    return None


def _motion_verb(r: _Reader) -> Found:
    """teleport, turn, go to (a point or a robot), forward, backward."""
    if r.take("teleport", "jump"):
        r.take("to")
        return "teleport", _point(r, heading=True)
    if r.take("turn", "rotate"):
        return "turn", _turn(r)
    if r.take("goto"):
        return "goto", _point(r)
    moved = r.take(*MOVE)
    if moved and r.take("to"):
        if r.take("robot"):  # "go to robot 2", "come to robot 1": that robot's pose, stopping short
            n = r.robot_number()
            if n is None:
                raise Refusal("Which robot? Say go to robot 2")
            return "goto_robot", {"robot": n}
        return "goto", _point(r)
    if r.take("forward", "forwards", "ahead", "straight"):
        r.take("ahead")
        return "forward", _distance(r)
    if r.take("back", "backward", "backwards", "backup", "reverse"):
        r.take("up")
        return "backward", _distance(r)
    if moved:
        raise Refusal("Go where? Say go to 3 4, go forward 2 metres or go back 1 metre")
    return None


def _positive(d: float) -> float:
    if d <= 0:
        raise Refusal("The distance must be more than zero")
    return d


def _distance(r: _Reader) -> dict[str, Any]:
    d = r.distance()
    if d is None:
        raise Refusal("How far? Say a distance, like forward 2 metres")
    return {"distance": _positive(d)}


def _velocity(r: _Reader) -> dict[str, Any]:
    """`[set velocity|speed] [to] <number> [<unit> [per second]]`: metres per second, in -2..2."""
    r.take("to", "of")
    v = r.distance()
    if v is None:
        raise Refusal("How fast? Say set velocity to 0.3 metres per second")
    r.take_seq("per second") or r.take("s")
    if abs(v) > 2.0:
        raise Refusal(f"{v:g} metres per second is too fast; at most 2")
    return {"v": v}


def _cruise(r: _Reader) -> dict[str, Any]:
    """`set speed|velocity [to] <number> [...]`: the cruise speed of later moves, in 0..2 m/s."""
    v = _velocity(r)["v"]
    if v <= 0:
        raise Refusal(f"A speed of {v:g} is not a cruise speed; say set speed to 0.3, or stop")
    return {"speed": v}


def _relay(r: _Reader) -> dict[str, Any]:
    """`relay between [robot] A and [robot] B`: robot numbers (0 = the control node), named by the dialogue."""
    r.take("between", "for")
    ends = []
    for _ in range(2):
        if r.take("control", "base") or r.take_seq("control node"):
            r.take("node", "station")
            ends.append(0)
        else:
            r.take("robot")
            end = r.robot_number()
            if end is None:
                raise Refusal("Relay between which robots? Say relay between robot 1 and robot 3")
            ends.append(end)
        r.take("and")
    return {"source": ends[0], "destination": ends[1]}


def _patrol(r: _Reader) -> dict[str, Any]:
    """`patrol [from] X1 Y1 to X2 Y2`: the territory block's corners."""
    r.take("from")
    a = _point(r)
    if not r.take("to"):
        raise Refusal("Patrol from where to where? Say patrol from 0 0 to 5 5")
    b = _point(r)
    return {"xmin": min(a["x"], b["x"]), "ymin": min(a["y"], b["y"]),
            "xmax": max(a["x"], b["x"]), "ymax": max(a["y"], b["y"])}


def _turn(r: _Reader) -> dict[str, Any]:
    if r.take("around"):
        return {"angle": 180.0}
    r.take("to")
    side = r.take("left", "right")
    r.take("by")
    angle = r.number()
    if angle is not None:
        r.take(*DEGREES)
    if not side:
        r.take("to")
        side = r.take("left", "right")
    if angle is None:
        if not side:
            raise Refusal("Turn which way? Say turn left, turn right 45 degrees or turn around")
        angle = 90.0
    if side == "right":
        angle = -angle
    return {"angle": _round(angle)}


def _point(r: _Reader, heading: bool = False) -> dict[str, Any]:
    if r.take("origin"):
        x: float | None = 0.0
        y: float | None = 0.0
    else:
        r.take("x")
        x = r.distance()
        r.take("and", "comma")
        r.take("y")
        y = r.distance() if x is not None else None
    if x is None or y is None:
        raise Refusal("Where to? Say x and y, like go to 3 4")
    params: dict[str, Any] = {"x": x, "y": y}
    if heading and r.take("facing", "heading"):
        h = r.number()
        if h is None:
            raise Refusal("Facing which heading? Say facing 90 degrees")
        r.take(*DEGREES)
        params["heading"] = _round(h)
    return params


# Fixed phrases of the grammar (beside numbers, units, subjects): for recognisers and the docs.
PHRASES = """spread out cover deploy to relay between for control node base station patrol from robot robots
    number and a an half hundred point stop halt freeze everything moving cancel abort that it tasks task clear
    behaviours stack random walk wander explore around teleport jump to turn rotate left right by goto forward
    forwards ahead straight back backward backwards reverse up x y comma facing heading origin avoid obstacles
    avoiding on off at within do not start set velocity speed per second of every you faster quicker slower slow
    down undo this""".split()


def vocabulary() -> list[str]:
    """Every word the grammar knows, for a recogniser restricted to them."""
    words: set[str] = set()
    for group in (ONES, TEENS, TENS, NEGATIVE, UNITS, DEGREES, EVERYONE, FILLER, MOVE):
        words.update(group)
    for phrase in ATTENTION + SLEEP + CONFIRM + DENY + FILLER_PHRASES + COUNT_QUESTIONS:
        words.update(phrase.split())
    for phrases in QUESTIONS.values():
        for phrase in phrases:
            words.update(phrase.split())
    words.update("where what how is are doing".split())
    for spoken in _plain_strategies():
        words.update(spoken.split())
    words.update(PHRASES)
    # written forms and spellings of hesitations that pronouncing dictionaries lack: typed only
    words -= {"m", "cm", "ft", "deg", "randomwalk", "goto", "backup", "t", "s", "ok", "erm", "uhm", "umm"}
    return sorted(words)
