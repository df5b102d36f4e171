"""The operator's side of a conversation with the team: listening state, sticky targets, tasks.

A `Dialogue` hears utterances (spoken or typed), keeps whether it is listening ("attention"
/ "go to sleep") and the last robots named, and turns each understood command into the
tasks to publish, with the sentence to say back: a "Roger" that restates what will be done
("Roger: robots 5 and 6, turn right 90 degrees"), a refusal that says what was expected, or
the answer to a question, read from the team's state (`RobotView`: pose, task, battery, link).
A stop ("stop", "everyone halt", "freeze") is never gated: it acts and is answered while
standing by too, and goes to lost robots as well. Other commands to a lost robot are refused
(named) or leave it out with a warning (everyone, last targets).
`Naming` maps robot numbers to agent names (`robot3`) and back; `tasks_for` maps an action
of the grammar onto the task language in either tier (RemoteBotMotion through each robot's
MissionControl, or BotMotion straight to its motion plugin).
"""

from __future__ import annotations

import math
import re
from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field
from typing import Any

from erni.blackboard import Task
from erni.blackboard.errors import ConfigError, TaskError
from erni.blackboard.tasks import PREPOSITIONS
from erni.plugins.ui.grammar import (
    STOP_WORDS,
    STRATEGY_VERB,
    Command,
    Refusal,
    _Reader,
    _subject,
    parse,
    tokens,
    without_fillers,
)

LISTENING = "Listening"
STANDING_BY = "Standing by"
ROGER = "Roger"


class Naming:
    """Robot number <-> agent name, from a pattern such as `robot{n}` or `amigo-{n}`."""

    def __init__(self, pattern: str = "robot{n}") -> None:
        if pattern.count("{n}") != 1:
            raise ConfigError(f"robot naming {pattern!r}: expected a pattern with one {{n}}, e.g. 'robot{{n}}'")
        head, tail = pattern.split("{n}")
        self.pattern = pattern
        self._re = re.compile(re.escape(head) + r"(\d+)" + re.escape(tail))

    def name(self, number: int) -> str:
        """Return the agent name of robot `number`."""
        return self.pattern.replace("{n}", str(number))

    def number(self, name: str) -> int | None:
        """Return the robot number in an agent name, or None if the name does not follow the pattern."""
        m = self._re.fullmatch(name)
        return int(m.group(1)) if m else None

    def spoken(self, name: str) -> str:
        """`robot 3` for robot3; the agent name itself outside the pattern."""
        n = self.number(name)
        return f"robot {n}" if n is not None else name


@dataclass(frozen=True)
class RobotView:
    """What the operator can be told about one robot: from its Pose, its tasks and its transport peer."""

    name: str
    up: bool = True
    x: float | None = None
    y: float | None = None
    theta: float | None = None  # radians
    battery: float | None = None  # volts
    doing: str = ""  # the running task in words; "" when idle
    silent: float | None = None  # seconds since it was last heard
    link: float | None = None  # best link quality to a neighbour, 0..1


def spoken_list(numbers: Iterable[Any]) -> str:
    """Return `5`, `5 and 6`, `4, 5 and 6`."""
    items = [str(n) for n in numbers]
    return items[0] if len(items) == 1 else ", ".join(items[:-1]) + " and " + items[-1]


def tasks_for(action: str, params: Mapping[str, Any], robots: Iterable[str], *, verb: str,
              source: str) -> list[Task]:
    """Return one task per robot for a grammar action, in the configured tier.

    Deployment strategies are `Deploy` tasks in either tier. With `verb = "RemoteBotMotion"`,
    prepositions the team verb lacks go as BotMotion straight to the robot (turn, backward,
    velocity, avoid_obstacles, clear), and `stop` becomes RemoteBotMotion `cancel` (cancel the
    robot's remote tasks and stop it). With `verb = "BotMotion"`, `stop` and `cancel` become
    `clear` (empty the behaviour stack, which halts the robot).
    """
    prep, args = action, dict(params)
    if (STRATEGY_VERB, prep) in PREPOSITIONS:
        verb = STRATEGY_VERB  # deployment strategies have a verb of their own, run by MissionControl
    elif verb == "BotMotion":
        if prep in ("stop", "cancel"):
            prep = "clear"
    elif (verb, prep) not in PREPOSITIONS:
        if prep == "stop":
            prep = "cancel"
        else:
            verb = "BotMotion"
    if (verb, prep) not in PREPOSITIONS:
        raise Refusal(f"They can't {action.replace('_', ' ')}")
    tasks = []
    for robot in robots:
        try:
            tasks.append(Task(verb=verb, preposition=prep, params=args, source=source, destination=robot))
        except TaskError as err:
            raise Refusal(f"I can't do that: {err}") from None
    return tasks


def _num(v: float) -> str:
    return f"{round(v, 2):g}"


def _metres(d: float) -> str:
    return f"{_num(d)} metre" + ("" if d == 1 else "s")


def restate(action: str, params: Mapping[str, Any], ends: Mapping[str, str] | None = None) -> str:
    """What an action will do, in words: `turn right 90 degrees`, `go to x 4, y 5`."""
    p = params
    if action == "goto":
        return f"go to x {_num(p['x'])}, y {_num(p['y'])}"
    if action in ("forward", "backward"):
        return f"go {'forward' if action == 'forward' else 'back'} {_metres(p['distance'])}"
    if action == "turn":
        a = p["angle"]
        if abs(a) == 180:
            return "turn around"
        return f"turn {'left' if a >= 0 else 'right'} {_num(abs(a))} degrees"
    if action == "teleport":
        return f"teleport to x {_num(p['x'])}, y {_num(p['y'])}" + (
            f", facing {_num(p['heading'])} degrees" if "heading" in p else "")
    if action == "velocity":
        return f"drive at {_num(p['v'])} metres per second"
    if action == "avoid_obstacles":
        return ("avoid obstacles" + (f" at {_metres(p['distance'])}" if "distance" in p else "")
                if p.get("enabled", True) else "stop avoiding obstacles")
    if action == "spread":
        return "spread out" + (f" to {_metres(p['distance'])}" if "distance" in p else "")
    if action == "widep":
        return f"cover x {_num(p['x'])}, y {_num(p['y'])}"
    if action == "relay":
        named = ends or {k: str(p[k]) for k in ("source", "destination")}
        return f"relay between {named['source']} and {named['destination']}"
    if action == "patrol":
        return f"patrol from {_num(p['xmin'])}, {_num(p['ymin'])} to {_num(p['xmax'])}, {_num(p['ymax'])}"
    return {"stop": "stop", "cancel": "cancel your tasks", "clear": "clear your behaviours",
            "randomwalk": "random walk"}.get(action, action.replace("_", " "))


@dataclass
class Reply:
    """What the dialogue answers to one utterance."""

    heard: str
    say: str | None = None
    tasks: list[Task] = field(default_factory=list)
    targets: list[str] = field(default_factory=list)
    accepted: bool = False
    action: str = ""
    stop: bool = False  # a stop: sent whatever the listening state


Team = Mapping[str, RobotView] | Iterable[str]


class Dialogue:
    """Listening state and sticky targets of one operator; `hear()` answers each utterance."""

    def __init__(self, naming: Naming | None = None, *, verb: str = "RemoteBotMotion", source: str = "control",
                 listening: bool = True, control: str = "control") -> None:
        self.naming = naming or Naming()
        self.verb = verb
        self.source = source
        self.control = control  # agent name of the control node: "relay between robot 1 and control"
        self.listening = listening
        self.targets: list[str] = []

    def select(self, robots: Iterable[str]) -> None:
        """Make these robots the current targets (the GUI's selection)."""
        self.targets = list(dict.fromkeys(robots))

    def _order(self, names: Iterable[str]) -> list[str]:
        return sorted(set(names), key=lambda n: (self.naming.number(n) is None, self.naming.number(n) or 0, n))

    def _views(self, team: Team) -> dict[str, RobotView]:
        if isinstance(team, Mapping):
            return {name: team[name] for name in self._order(team)}
        return {name: RobotView(name) for name in self._order(team)}

    def hear(self, text: str, team: Team) -> Reply:
        """Answer one utterance given the robots the team has now (agent names, or their views)."""
        views = self._views(team)
        reply = Reply(text)
        try:
            cmd = parse(text)
        except Refusal as why:
            rescued = _stop_in(text)
            if rescued is None:
                if self.listening:
                    reply.say = str(why)
                return reply
            cmd = rescued
        if cmd.kind == "attention":
            self.listening = True
            reply.say, reply.accepted = LISTENING, True
            return reply
        if cmd.is_stop:
            return self._stop(cmd, views, reply)
        if not self.listening:
            return reply  # ignored until the next "attention"
        if cmd.kind == "sleep":
            self.listening = False
            reply.say, reply.accepted = STANDING_BY, True
            return reply
        try:
            if cmd.kind == "select":
                return self._select(cmd, views, reply)
            if cmd.kind == "query":
                return self._query(cmd, views, reply)
            targets, note = self._targets(cmd, views)
            ends = self._relay_ends(cmd, views, targets) if cmd.action == "relay" else None
            params = {**cmd.params, **ends} if ends else cmd.params
            reply.tasks = tasks_for(cmd.action, params, targets, verb=self.verb, source=self.source)
        except Refusal as why:
            reply.say = str(why)
            return reply
        self.targets = targets
        reply.targets, reply.action = list(targets), cmd.action
        spoken_ends = {k: self._spoken(v) for k, v in ends.items()} if ends else None
        reply.say = f"{ROGER}: {self.who(targets, cmd.everyone, views)}, {restate(cmd.action, cmd.params, spoken_ends)}"
        reply.say += f" ({note})" if note else ""
        reply.accepted = True
        return reply

    # -- who -------------------------------------------------------------------------------

    def _spoken(self, name: str) -> str:
        return "the control node" if name == self.control else self.naming.spoken(name)

    def who(self, names: list[str], everyone: bool, views: Mapping[str, RobotView]) -> str:
        if everyone and len(names) > 1 and set(names) == set(views):
            return "everyone"
        numbers = [self.naming.number(n) for n in names]
        if all(n is not None for n in numbers):
            return ("robot " if len(names) == 1 else "robots ") + spoken_list(numbers)
        return spoken_list(names)

    def _lost(self, names: list[str], views: Mapping[str, RobotView]) -> str:
        """`robot 3 is lost (not heard for 12 s)`, `robots 3 and 4 are lost`."""
        lost = [n for n in names if not views[n].up]
        if not lost:
            return ""
        silent = [views[n].silent for n in lost]
        since = f" (not heard for {max(s for s in silent if s is not None):.0f} s)" if any(
            s is not None for s in silent) else ""
        verb = "is" if len(lost) == 1 else "are"
        return f"{self.who(lost, False, views)} {verb} lost{since}"

    def _named(self, cmd: Command, views: Mapping[str, RobotView]) -> list[str]:
        """The robots an utterance names, refusing numbers the team does not have."""
        if cmd.everyone:
            if not views:
                raise Refusal("I don't know any robots yet")
            return list(views)
        names = [self.naming.name(n) for n in cmd.robots]
        missing = [n for n, name in zip(cmd.robots, names) if name not in views]
        if missing:
            noun = "robot" if len(missing) == 1 else "robots"
            have = [self.naming.number(n) for n in views]
            known = f"; I know robots {spoken_list(have)}" if views and all(h is not None for h in have) else ""
            raise Refusal(f"I don't know {noun} {spoken_list(missing)}{known}")
        return names

    def _targets(self, cmd: Command, views: Mapping[str, RobotView]) -> tuple[list[str], str]:
        """The live robots a command goes to, and a note on lost ones left out."""
        if cmd.robots:
            names = self._named(cmd, views)
            lost = self._lost(names, views)
            if lost:
                raise Refusal(f"{lost[0].upper()}{lost[1:]}: nothing sent")
            return names, ""
        if cmd.everyone:
            names = self._named(cmd, views)
        else:
            if not self.targets:
                raise Refusal("Which robots? Say robot 1, robots 1 and 2, or everyone")
            names = [n for n in self.targets if n in views]
            if not names:
                raise Refusal(f"I don't know {self.who(self.targets, False, views)} any more; name the robots")
        live = [n for n in names if views[n].up]
        lost = self._lost(names, views)
        if not live:
            raise Refusal(f"{lost[0].upper()}{lost[1:]}: nothing sent")
        return live, f"{lost}, left out" if lost else ""

    def _relay_ends(self, cmd: Command, views: Mapping[str, RobotView], targets: list[str]) -> dict[str, str]:
        numbers = {k: cmd.params[k] for k in ("source", "destination")}
        names = {k: self.control if n == 0 else self.naming.name(n) for k, n in numbers.items()}
        missing = [numbers[k] for k, name in names.items() if name != self.control and name not in views]
        if missing:
            noun = "robot" if len(missing) == 1 else "robots"
            raise Refusal(f"I don't know {noun} {spoken_list(missing)}")
        if names["source"] == names["destination"]:
            raise Refusal("A relay needs two different ends; say relay between robot 1 and robot 3")
        mine = [t for t in targets if t in names.values()]
        if mine:
            raise Refusal(f"{self.who(mine, False, views).capitalize()} can't relay for "
                          f"{'itself' if len(mine) == 1 else 'themselves'}; name two other ends")
        return names

    # -- stop, selection, questions ----------------------------------------------------------

    def _stop(self, cmd: Command, views: Mapping[str, RobotView], reply: Reply) -> Reply:
        """Stop the named robots (the known ones), the last targets, or everyone: in any state."""
        notes = [cmd.params["note"]] if "note" in cmd.params else []
        if cmd.robots:
            names = [self.naming.name(n) for n in cmd.robots]
            unknown = [n for n, name in zip(cmd.robots, names) if name not in views]
            names = [n for n in names if n in views]
            if unknown:
                notes.append(f"I don't know {'robot' if len(unknown) == 1 else 'robots'} {spoken_list(unknown)}")
        elif cmd.everyone or not self.targets:
            names = list(views)
        else:
            names = [n for n in self.targets if n in views] or list(views)
        reply.stop = True
        if not names:
            reply.say = notes[0] if notes else "I don't know any robots to stop"
            return reply
        lost = self._lost(names, views)
        if lost:
            notes.append(f"{lost}: it gets the stop when heard again" if " is " in lost
                         else f"{lost}: they get the stop when heard again")
        reply.tasks = tasks_for("stop", {}, names, verb=self.verb, source=self.source)
        self.targets = names
        reply.targets, reply.action, reply.accepted = list(names), "stop", True
        everyone = cmd.everyone or (not cmd.robots and set(names) == set(views))
        reply.say = f"{ROGER}: {self.who(names, everyone, views)}, stop" + (f" ({'; '.join(notes)})" if notes else "")
        return reply

    def _select(self, cmd: Command, views: Mapping[str, RobotView], reply: Reply) -> Reply:
        names = self._named(cmd, views)
        self.targets = names
        reply.targets, reply.accepted = list(names), True
        lost = self._lost(names, views)
        reply.say = f"Selected {self.who(names, cmd.everyone, views)}" + (f" ({lost})" if lost else "")
        return reply

    def _query(self, cmd: Command, views: Mapping[str, RobotView], reply: Reply) -> Reply:
        if cmd.action == "count":
            up = [n for n in views if views[n].up]
            lost = self._lost(list(views), views)
            reply.say = (f"{len(views)} robot{'' if len(views) == 1 else 's'}, {len(up)} up"
                         + (f"; {lost}" if lost else "")) if views else "I don't know any robots yet"
            reply.accepted = True
            return reply
        if cmd.robots or cmd.everyone:
            names = self._named(cmd, views)
            self.targets = names
            reply.targets = list(names)
        else:
            names = [n for n in self.targets if n in views] or list(views)
        if not names:
            raise Refusal("I don't know any robots yet")
        reply.say = "; ".join(self._answer(cmd.action, views[n]) for n in names)
        reply.accepted = True
        return reply

    def _answer(self, question: str, v: RobotView) -> str:
        who = self._spoken(v.name).capitalize()
        where = (f"at x {v.x:.1f}, y {v.y:.1f}, heading {math.degrees(v.theta or 0.0):.0f} degrees"
                 if v.x is not None and v.y is not None else "position unknown")
        doing = v.doing or "idle"
        battery = f"battery {v.battery:.1f} volts" if v.battery is not None else "battery unknown"
        if v.up:
            link = "link up" + (f", best link quality {v.link:.2f}" if v.link is not None else "")
        else:
            link = "link lost" + (f", not heard for {v.silent:.0f} s" if v.silent is not None else "")
        if question == "where":
            return (f"{who} is {where}" if v.x is not None else f"{who}: {where}") + ("" if v.up else f" ({link})")
        if question == "doing":
            return f"{who} is {doing}" + ("" if v.up else f" ({link})")
        if question == "battery":
            return f"{who} {battery}"
        if question == "link":
            return f"{who} {link}"
        return f"{who}: {where}; {doing}; {battery}; {link}"


def _stop_in(text: str) -> Command | None:
    """A stop inside an utterance the grammar refuses ("robot 1 stop banana"): stop, never ignore it."""
    words = without_fillers(tokens(text))
    if not any(w in STOP_WORDS for w in words) or "avoiding" in words:
        return None
    r = _Reader(words)
    try:
        robots, everyone = _subject(r)
    except Refusal:  # "robot stop", "robot 1.5 stop": who is unclear, so everyone stops
        return Command("action", "stop", {"note": "I didn't catch which robot"}, everyone=True)
    return Command("action", "stop", robots=robots, everyone=everyone)
