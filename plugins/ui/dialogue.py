"""The operator's side of a conversation with the team: listening state, sticky targets, tasks.

A `Dialogue` hears utterances (spoken or typed), keeps whether it is listening ("attention"
/ "go to sleep") and the last robots named, and turns each understood command into the
tasks to publish, with the sentence to say back: a "Roger" that restates what will be done
("Roger: robots 5 and 6, turn right 90 degrees"), a refusal that says what was expected, or
the answer to a question, read from the team's state (`RobotView`: pose, task, battery, link).
A stop ("stop", "everyone halt", "freeze") is never gated: it acts and is answered while
standing by too, and goes to lost robots as well. Other commands to a lost robot are refused
(named) or leave it out with a warning (everyone, last targets).
"Cancel that" withdraws the tasks of the last command carried out; "set speed 0.2", "faster" and
"slower" set each robot's cruise speed for later moves (and a running go-to or random walk);
"go to robot 2" drives to that robot, stopping short. A dialogue made with `read_back` (the
spoken one) restates a risky command and carries it out only on "yes", however sure the hearing: a
command to several robots, a clear, a teleport, a deployment, a held velocity, a move beyond
`read_back` metres or off the map; with `read_back_numbers` so is a spoken motion command that
carries a number ("turn 180 degrees": as on an air-traffic radio, numbers are read back, since a
recogniser mishears them without doubting); an unsure hearing of a command that would move robots
is read back too ("Did you say: robot 1, go forward 2 metres? Say yes or no"), any other unsure
hearing is asked again ("Say again?"); a stop never waits. A dialogue made with `confirm_beyond`
(the typed one) asks once before a move that leaves the map: its end off the floor plan's bounds
(`area`), a held velocity, or, where the bounds cannot tell, a move longer than `confirm_beyond`
metres. A dialogue made with `confirm_remembered` (the console's) carries out a command that names no
robot for the robots last named only when they were named, or answered about, in the exchange just
before ("Roger: robot 3, clear your behaviours"); older than that, it asks ("Robot 3: clear your
behaviours? No robot named; robot 3 was named 4 commands ago ..."). A stop never asks.
`Naming` maps robot numbers to agent names (`robot3`) and back; `tasks_for` maps an action
of the grammar onto the task language in either tier (RemoteBotMotion through each robot's
MissionControl, or BotMotion straight to its motion plugin).
"""

from __future__ import annotations

import math
import re
from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass, field
from typing import Any, overload

from erni.blackboard import Task
from erni.blackboard.clock import monotonic
from erni.blackboard.errors import ConfigError, TaskError
from erni.blackboard.tasks import PREPOSITIONS
from erni.plugins.ui.caution import Caution, Cautious, _num
from erni.plugins.ui.caution import quantities as quantities  # its home before the caution had one
from erni.plugins.ui.grammar import (
    ATTENTION,
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
CONFIRM_PROMPT = "say yes to confirm"
TYPED_PROMPT = "type yes to confirm"
SAY_AGAIN = "Say again?"
DID_YOU_SAY = "Did you say:"  # a doubted hearing read back: "Did you say: robot 1, go forward 2 metres? ..."
YES_OR_NO = "Say yes or no"
EXAMPLE = "say a command like robot 1 go forward 2 metres"

DEFAULT_SPEED = 0.3  # m/s: the task language's cruise speed of goto, forward, backward and random walk
SPEEDS = (0.05, 2.0)  # m/s: the cruise speeds "faster" and "slower" stay within
SPEED_STEP = 1.5  # "faster" multiplies the cruise speed by this, "slower" divides by it
CRUISING = ("goto", "forward", "backward", "randomwalk")  # moves with a cruise speed
RETUNED = ("goto", "randomwalk")  # running moves a new cruise speed re-sends
SHORT = 1.0  # m: "go to robot 2" stops this far from robot 2 (centre to centre)
APART = 0.8  # m: goals of several robots going to one robot are at least this far apart


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
    robot's remote tasks and stop it). With `verb = "BotMotion"`, `stop` is BotMotion `stop` (every
    motion of the robot ends; obstacle avoidance stays) and `cancel` becomes `clear` (empty the
    behaviour stack).
    """
    prep, args = action, dict(params)
    if (STRATEGY_VERB, prep) in PREPOSITIONS:
        verb = STRATEGY_VERB  # deployment strategies have a verb of their own, run by MissionControl
    elif verb == "BotMotion":
        if prep == "cancel":
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
    if action == "goto_robot":
        return f"go to robot {p['robot']}"
    if action == "speed":
        return p["change"] if "change" in p else f"cruise speed {_num(p['speed'])} metres per second"
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
    withdraw: list[str] = field(default_factory=list)  # uids of tasks to cancel ("cancel that", a new speed)
    asked: bool = False  # a read-back or "say again?": nothing sent, an answer awaited


@dataclass
class Sent:
    """A command carried out: who and what in words ("robot 1, go forward 2 metres"), and its tasks."""

    what: str
    tasks: list[Task]


@dataclass
class Memory:
    """What one operator's front ends share: the last command carried out and each robot's cruise speed."""

    last: Sent | None = None
    speeds: dict[str, float] = field(default_factory=dict)


@dataclass
class _Pending:
    reply: Reply
    what: str
    until: float
    redo: Callable[[set[str] | None], Reply] | None = None  # on "yes": the reply, made with the tasks running then


Team = Mapping[str, RobotView] | Iterable[str]


@dataclass
class Sticky:
    """The robots a command that names none goes to (the last named, or answered about) and when they were
    named; with `ask`, a command for robots named longer ago than the exchange just before waits for a yes."""

    ask: bool = False
    names: list[str] = field(default_factory=list)
    heard: int = 0  # utterances heard
    at: int = 0  # the utterance that last named them

    def age(self, named: bool) -> int:
        """How many utterances ago the robots were named, when a command that does not name them (`named`
        False) is to wait for a yes for it (older than the one just before, and `ask`); else 0."""
        age = self.heard - self.at
        return age if self.ask and not named and age > 1 else 0

    def question(self, who: str, doing: str, prompt: str) -> str:
        """`Robot 3: clear your behaviours? No robot named; robot 3 was named 4 commands ago \u2014 ...`"""
        were = "were" if len(self.names) > 1 else "was"
        return (f"{who[0].upper()}{who[1:]}: {doing}? No robot named; {who} {were} named {self.heard - self.at} "
                f"commands ago \u2014 {prompt}, or name the robots")


class _Targets:
    """`Dialogue.targets`: the sticky targets; setting them marks them named in the utterance heard now."""

    @overload
    def __get__(self, dialogue: None, owner: type[Any] | None = None) -> _Targets: ...

    @overload
    def __get__(self, dialogue: object, owner: type[Any] | None = None) -> list[str]: ...

    def __get__(self, dialogue: Any, owner: type[Any] | None = None) -> list[str] | _Targets:
        if dialogue is None:
            return self
        names: list[str] = dialogue.sticky.names
        return names

    def __set__(self, dialogue: Any, names: list[str]) -> None:
        dialogue.sticky.names, dialogue.sticky.at = names, dialogue.sticky.heard


class Dialogue:
    """Listening state and sticky targets of one operator; `hear()` answers each utterance."""

    read_back: Cautious[float | None] = Cautious()  # what waits for a yes: see `Caution`
    confirm_beyond: Cautious[float | None] = Cautious()
    read_back_numbers: Cautious[bool] = Cautious()
    area: Cautious[tuple[float, float, float, float] | None] = Cautious()
    targets = _Targets()  # the last robots named: `sticky`

    def __init__(self, naming: Naming | None = None, *, verb: str = "RemoteBotMotion", source: str = "control",
                 listening: bool = True, control: str = "control", memory: Memory | None = None,
                 read_back: float | None = None, area: tuple[float, float, float, float] | None = None,
                 read_back_timeout: float = 20.0, read_back_numbers: bool = False, echo: bool = False,
                 wake: tuple[str, ...] = ATTENTION, confirm_beyond: float | None = None,
                 confirm_remembered: bool = False, clock: Callable[[], float] = monotonic) -> None:
        self.naming = naming or Naming()
        self.wake = wake  # the phrases that wake a standing-by dialogue
        self.verb = verb
        self.source = source
        self.control = control  # agent name of the control node: "relay between robot 1 and control"
        self.listening = listening
        self.sticky = Sticky(ask=confirm_remembered)  # `targets`, and when they were named
        self.memory = memory or Memory()
        self.caution = Caution(read_back, confirm_beyond, read_back_numbers, area)  # what waits for a yes
        self.read_back_timeout = read_back_timeout
        self.clock = clock  # monotonic seconds: when a read-back expires
        self.echo = echo  # a refusal names what was heard (speech: the operator cannot see it)
        self.pending: _Pending | None = None

    def select(self, robots: Iterable[str]) -> None:
        """Make these robots the current targets (the GUI's selection)."""
        self.targets = list(dict.fromkeys(robots))

    def _order(self, names: Iterable[str]) -> list[str]:
        return sorted(set(names), key=lambda n: (self.naming.number(n) is None, self.naming.number(n) or 0, n))

    def _views(self, team: Team) -> dict[str, RobotView]:
        if isinstance(team, Mapping):
            return {name: team[name] for name in self._order(team)}
        return {name: RobotView(name) for name in self._order(team)}

    def hear(self, text: str, team: Team, running: Iterable[Task] | None = None, *, unsure: bool = False) -> Reply:
        """Answer one utterance given the robots the team has now (agent names, or their views).

        `running` are the unfinished tasks this operator's front ends sent (None: all it sent
        are taken as running); `unsure` marks a hearing the recogniser doubts: a command that would
        send tasks is read back when the dialogue reads back (`read_back`) and runs only on "yes";
        anything else is asked again ("Say again?"); a stop acts however it was heard.
        """
        views = self._views(team)
        live = None if running is None else {t.uid for t in running}
        reply = Reply(text)
        self.sticky.heard += 1
        pending, self.pending = self.pending, None
        try:
            cmd = parse(text, self.wake)
        except Refusal as why:
            rescued = _stop_in(text)
            if rescued is None:
                if self.listening:
                    reply.say = self._unsure(text, pending) if unsure else self._refused(text, str(why), pending)
                return reply
            cmd = rescued
        if cmd.is_stop:
            return self._stop(cmd, views, reply)  # never waits, never asked again; drops a read-back
        if unsure:
            return self._doubted(cmd, views, live, pending, reply)
        if cmd.kind == "attention":
            self.listening = True
            reply.say, reply.accepted = LISTENING, True
            return reply
        if not self.listening:
            return reply  # ignored until the next "attention"
        if cmd.kind == "confirm":
            return self._confirmed(pending, live, reply)
        dropped = f"Not sent: {pending.what}" if pending is not None else ""
        if dropped and (cmd.kind == "deny" or (cmd.action == "cancel" and "last" in cmd.params
                                               and not cmd.names_targets)):
            reply.say, reply.accepted = dropped, True
            return reply
        answered = self._understood(cmd, views, live, reply)
        if dropped and answered.say is not None:
            answered.say = f"{dropped}. {answered.say}"
        return answered

    def _doubted(self, cmd: Command, views: Mapping[str, RobotView], live: set[str] | None,
                 pending: _Pending | None, reply: Reply) -> Reply:
        """A command the recogniser doubts: read back when it would send tasks (and the dialogue reads back),
        else asked again."""
        if not (self.listening or cmd.kind == "attention"):
            return reply
        if self.read_back is not None and cmd.kind == "action" and cmd.action != "speed" and not (
                cmd.action == "cancel" and cmd.params.get("last") and not cmd.names_targets):
            asked = self._understood(cmd, views, live, Reply(reply.heard), doubt=True)
            if asked.asked:  # a doubted command is read back: it runs only on "yes"
                if pending is not None and asked.say is not None:
                    asked.say = f"Not sent: {pending.what}. {asked.say}"
                return asked
        reply.say, reply.asked = self._unsure(reply.heard, pending), True
        return reply

    def _confirmed(self, pending: _Pending | None, live: set[str] | None, reply: Reply) -> Reply:
        """A "yes": the command read back carried out (made again now when it says how), or why not."""
        text = reply.heard
        if pending is None:
            reply.say = self._refused(text, "Nothing to confirm; yes answers a read-back", None)
            return reply
        if self.clock() > pending.until:
            reply.say = self._refused(text, f"Too late: {pending.what} was not sent; say it again", None)
            return reply
        if pending.redo is not None:  # made now, with the tasks running now
            try:
                done = pending.redo(live)
            except Refusal as why:
                reply.say = self._refused(text, str(why), None)
                return reply
            done.heard = text
            return done
        pending.reply.heard = text
        self.targets = list(pending.reply.targets) or self.targets
        self._carried_out(pending.reply)
        return pending.reply

    def _understood(self, cmd: Command, views: Mapping[str, RobotView], live: set[str] | None, reply: Reply,
                    doubt: bool = False) -> Reply:
        """Answer a command heard while listening and with no read-back waiting; with `doubt` (the
        recogniser is unsure of it) a command that would send tasks is read back instead."""
        if cmd.kind == "sleep":
            self.listening = False
            reply.say, reply.accepted = STANDING_BY, True
            return reply
        try:
            if cmd.kind == "deny":
                raise Refusal("Nothing to say no to; " + EXAMPLE)
            if cmd.kind == "select":
                return self._select(cmd, views, reply)
            if cmd.kind == "query":
                return self._query(cmd, views, reply)
            if cmd.action == "cancel" and cmd.params.get("last") and not cmd.names_targets:
                return self._cancel_last(live, reply)
            targets, note = self._targets(cmd, views)
            if cmd.action == "speed":
                return self._speed_heard(cmd, targets, views, live, note, reply)
            params = {k: v for k, v in cmd.params.items() if k != "last"}
            ends = self._relay_ends(cmd, views, targets) if cmd.action == "relay" else None
            params = {**params, **ends} if ends else params
            if cmd.action == "goto_robot":
                goals, what = self._to_robot(cmd.params["robot"], targets, views)
                targets = list(goals)
                reply.tasks = [t for r, goal in goals.items() for t in self._tasks("goto", goal, [r])]
            else:
                reply.tasks = self._tasks(cmd.action, params, targets)
                spoken_ends = {k: self._spoken(v) for k, v in ends.items()} if ends else None
                what = restate(cmd.action, cmd.params, spoken_ends)
        except Refusal as why:
            reply.say = self._refused(reply.heard, str(why), None)
            return reply
        reply.targets, reply.action = list(targets), "goto" if cmd.action == "goto_robot" else cmd.action
        risk = self._risk(cmd, reply, views, doubt)
        if not doubt and risk != "remembered":  # a doubted hearing, or one for robots named long ago,
            self.targets = targets              # picks no robots until it is confirmed
        what += self._at_speed(reply.action, targets)
        who = self.who(targets, cmd.everyone, views)
        reply.accepted = True
        reply.say = f"{ROGER}: {who}, {what}" + (f" ({note})" if note else "")
        if risk:
            return self._ask(reply, who, what, risk)
        self._carried_out(reply)
        return reply

    def _speed_heard(self, cmd: Command, targets: list[str], views: Mapping[str, RobotView], live: set[str] | None,
                     note: str, reply: Reply) -> Reply:
        """A cruise speed: set at once, or read back (and made again on "yes") when risky."""
        self._cruise(cmd, targets)  # refused now rather than after a read-back
        probe = Reply(reply.heard, targets=list(targets), action="speed")
        remembered = self.sticky.age(cmd.names_targets)
        if not remembered and not self.caution.risk(probe, views):
            return self._speed(cmd, targets, views, live, note, reply)
        who = self.who(targets, cmd.everyone, views)
        what = f"{who}, {restate('speed', cmd.params)}"
        self.pending = _Pending(probe, what, self.clock() + self.read_back_timeout,
                                redo=lambda now: self._speed(cmd, targets, views, now, note, Reply(probe.heard)))
        say = (self.sticky.question(who, restate("speed", cmd.params), self._prompt()) if remembered
               else f"{what[0].upper()}{what[1:]} \u2014 {CONFIRM_PROMPT}")
        return Reply(reply.heard, say=say, targets=list(targets), accepted=True, asked=True)

    def _risk(self, cmd: Command, reply: Reply, views: Mapping[str, RobotView], doubt: bool) -> str:
        """Why an understood command waits for a "yes"; '' when it is carried out at once."""
        if doubt and reply.tasks:
            return "doubt"
        if not doubt and reply.tasks and self.sticky.age(cmd.names_targets):
            return "remembered"
        return self.caution.risk(reply, views)

    def _prompt(self) -> str:
        return CONFIRM_PROMPT if self.read_back is not None else TYPED_PROMPT

    def _ask(self, reply: Reply, who: str, doing: str, risk: str) -> Reply:
        """Hold a risky command until "yes", and say so as its risk asks."""
        what = f"{who}, {doing}"
        self.pending = _Pending(reply, what, self.clock() + self.read_back_timeout)
        if risk == "remembered":
            ask = self.sticky.question(who, doing, self._prompt())
        elif risk in ("doubt", "number"):
            ask = f"{DID_YOU_SAY} {what}? {YES_OR_NO}"
        elif self.read_back is None:  # typed: asked once, saying why
            ask = f"{what[0].upper()}{what[1:]} \u2014 {self.caution.why(risk)}; {TYPED_PROMPT}"
        else:
            ask = f"{what[0].upper()}{what[1:]} \u2014 {CONFIRM_PROMPT}"
        return Reply(reply.heard, say=ask, targets=list(reply.targets), accepted=True, asked=True)

    # -- what was heard, what is expected ----------------------------------------------------

    def _refused(self, heard: str, why: str, pending: _Pending | None) -> str:
        """The one line a refusal is answered with: with `echo`, what was heard and what is expected."""
        if not self.echo:
            return why
        low = why.lower()
        if not any(w in low for w in ("say", "ask", "name ", "like", "at most", "i know", "more than")):
            why = f"{why}; {EXAMPLE}"
        dropped = f" ({pending.what} not sent)" if pending is not None else ""
        return f"I heard \u201c{_plain(heard)}\u201d: {why}{dropped}"

    def _unsure(self, heard: str, pending: _Pending | None) -> str:
        words = _plain(heard)
        what = f"I heard \u201c{words}\u201d, but I am not sure" if words else "I did not catch that"
        dropped = f"; {pending.what} not sent" if pending is not None else ""
        return f"{SAY_AGAIN} {what}{dropped}"

    # -- the last command, cruise speeds, going to a robot, read-back -------------------------

    def _carried_out(self, reply: Reply) -> None:
        """Remember a command whose tasks go out now, for "cancel that"."""
        if reply.tasks and reply.action not in ("stop", "cancel", "clear"):
            what = reply.say.split(": ", 1)[1] if reply.say and reply.say.startswith(ROGER) else reply.action
            self.memory.last = Sent(what, list(reply.tasks))

    def _cancel_last(self, live: set[str] | None, reply: Reply) -> Reply:
        last = self.memory.last
        if last is None:
            raise Refusal("Nothing to cancel: no command carried out yet; to halt a robot say robot 1 stop")
        uids = [t.uid for t in last.tasks if live is None or t.uid in live]
        if not uids:
            raise Refusal(f"Nothing to cancel: {last.what} has ended")
        self.memory.last = None
        reply.withdraw = uids
        reply.targets = list(dict.fromkeys(t.destination for t in last.tasks if t.uid in uids and t.destination))
        self.targets = list(reply.targets)
        reply.action, reply.accepted = "cancel", True
        reply.say = f"{ROGER}: cancelled {last.what}"
        return reply

    def _tasks(self, action: str, params: Mapping[str, Any], robots: list[str]) -> list[Task]:
        """`tasks_for`, each robot's move at its cruise speed."""
        if action not in CRUISING or "speed" in params:
            return tasks_for(action, params, robots, verb=self.verb, source=self.source)
        out: list[Task] = []
        for r in robots:
            speed = self.memory.speeds.get(r)
            out += tasks_for(action, {**params, **({"speed": speed} if speed else {})}, [r], verb=self.verb,
                             source=self.source)
        return out

    def _at_speed(self, action: str, robots: list[str]) -> str:
        speeds = {self.memory.speeds.get(r) for r in robots}
        if action not in CRUISING or speeds == {None}:
            return ""
        if len(speeds) == 1:
            return f" at {_num(next(iter(speeds)) or DEFAULT_SPEED)} metres per second"
        return " at their cruise speeds"

    def _speed(self, cmd: Command, targets: list[str], views: Mapping[str, RobotView], live: set[str] | None,
               note: str, reply: Reply) -> Reply:
        """Set the targets' cruise speed; re-send a running go-to or random walk at it."""
        change = cmd.params.get("change")
        new = self._cruise(cmd, targets)
        self.memory.speeds.update(new)
        newest: dict[str, Task] = {}
        last = self.memory.last
        for t in sorted(last.tasks if last else [], key=lambda t: t.created):
            if t.destination in new and (live is None or t.uid in live):
                newest[t.destination] = t
        resent, kept = [], []
        for r, old in newest.items():
            if old.preposition in RETUNED:
                params = {**old.params.model_dump(exclude_defaults=True), "speed": new[r]}
                task = Task(verb=old.verb, preposition=old.preposition, params=params, source=self.source,
                            destination=r)
                reply.tasks.append(task)
                reply.withdraw.append(old.uid)
                resent.append((old, task))
            elif old.preposition in CRUISING:
                kept.append(old)
        if last is not None and resent:
            swap = {old.uid: task for old, task in resent}
            last.tasks = [swap.get(t.uid, t) for t in last.tasks]
        self.targets = targets
        reply.targets, reply.action, reply.accepted = list(targets), "speed", True
        values = sorted(set(new.values()))
        said = (f"{_num(values[0])} metres per second" if len(values) == 1
                else ", ".join(f"{self._spoken(r)} {_num(v)}" for r, v in new.items()) + " metres per second")
        notes = [note] if note else []
        if resent:
            notes.append(f"the running {self._moves(o for o, _ in resent)} too")
        if kept:
            notes.append(f"the running {self._moves(kept)} keeps its speed; the next move is at the new one")
        reply.say = (f"{ROGER}: {self.who(targets, cmd.everyone, views)}, "
                     f"{'' if change is None else change + ', '}cruise speed {said}"
                     + (f" ({'; '.join(notes)})" if notes else ""))
        return reply

    def _cruise(self, cmd: Command, targets: list[str]) -> dict[str, float]:
        """Each target's new cruise speed (nothing is set yet); refused when it would not change."""
        change = cmd.params.get("change")
        new: dict[str, float] = {}
        for r in targets:
            now = self.memory.speeds.get(r, DEFAULT_SPEED)
            v = cmd.params["speed"] if change is None else now * SPEED_STEP if change == "faster" else now / SPEED_STEP
            new[r] = round(min(max(v, SPEEDS[0]), SPEEDS[1]), 2)
        if change and all(new[r] == self.memory.speeds.get(r, DEFAULT_SPEED) for r in targets):
            edge = "fastest" if change == "faster" else "slowest"
            raise Refusal(f"Already at the {edge} cruise speed, {_num(new[targets[0]])} metres per second; "
                          f"say set speed to a number between {_num(SPEEDS[0])} and {_num(SPEEDS[1])}")
        return new

    def _moves(self, tasks: Iterable[Task]) -> str:
        return ", ".join(f"{restate(t.preposition, t.params.model_dump())} of {self._spoken(t.destination or '')}"
                         for t in tasks)

    def _to_robot(self, number: int, movers: list[str], views: Mapping[str, RobotView]
                  ) -> tuple[dict[str, dict[str, float]], str]:
        """Goals short of robot `number` for each mover (apart from each other), and the words for them."""
        name = self.naming.name(number)
        if name not in views:
            have = [self.naming.number(n) for n in views]
            known = f"; I know robots {spoken_list(have)}" if views and all(h is not None for h in have) else ""
            raise Refusal(f"I don't know robot {number}{known}")
        target = views[name]
        movers = [m for m in movers if m != name]
        if not movers:
            raise Refusal(f"Robot {number} is already there; name another robot to go to it")
        if not target.up or target.x is None or target.y is None:
            raise Refusal(f"I don't know where robot {number} is now; say go to and a point, like go to 3 4")
        tx, ty = target.x, target.y
        unknown = [m for m in movers if views[m].x is None or views[m].y is None]
        if unknown:
            raise Refusal(f"I don't know where {self.who(unknown, False, views)} "
                          f"{'is' if len(unknown) == 1 else 'are'}; say go to and a point, like go to 3 4")
        goals = goals_short_of(tx, ty, {m: (views[m].x or 0.0, views[m].y or 0.0) for m in movers})
        what = f"go to robot {number}"
        if len(goals) == 1:
            g = next(iter(goals.values()))
            what += f" (x {_num(g['x'])}, y {_num(g['y'])})"
        return {m: goals[m] for m in movers}, what

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
            names = [n for n in self.targets if n in views]
            if names:
                self.targets = names  # answered about: they are the ones just mentioned
            else:
                names = list(views)
        if not names:
            raise Refusal("I don't know any robots yet")
        reply.say = "; ".join(answer(cmd.action, views[n], self._spoken(n)) for n in names)
        reply.accepted = True
        return reply


def answer(question: str, v: RobotView, spoken: str) -> str:
    """The answer to a status question about one robot (`spoken`: its name as said, `robot 2`)."""
    who = spoken.capitalize()
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


def goals_short_of(tx: float, ty: float, movers: Mapping[str, tuple[float, float]]) -> dict[str, dict[str, float]]:
    """Goals short of (tx, ty) for robots at `movers`' positions: the nearest stops SHORT away (or where it
    is, when nearer), each on its side of the point, the others further out until at least APART from each other."""
    goals: dict[str, dict[str, float]] = {}
    for m in sorted(movers, key=lambda m: math.hypot(movers[m][0] - tx, movers[m][1] - ty)):
        mx, my = movers[m]
        away = math.atan2(my - ty, mx - tx)
        radius = min(SHORT, math.hypot(mx - tx, my - ty)) if not goals else SHORT
        while True:
            gx, gy = tx + radius * math.cos(away), ty + radius * math.sin(away)
            if all(math.hypot(gx - g["x"], gy - g["y"]) >= APART for g in goals.values()):
                break
            radius += APART
        goals[m] = {"x": round(gx, 2), "y": round(gy, 2)}
    return goals


def _plain(text: str) -> str:
    """An utterance as words, for saying back what was heard."""
    return " ".join(w for w in tokens(text) if w != "[unk]")


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
