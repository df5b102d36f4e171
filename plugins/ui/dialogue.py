"""The operator's side of a conversation with the team: listening state, sticky targets, tasks.

A `Dialogue` hears utterances (spoken or typed), keeps whether it is listening ("attention"
/ "go to sleep") and the last robots named, and turns each understood command into the
tasks to publish, with the sentence to say back ("Roger", "I don't know robot 9").
`Naming` maps robot numbers to agent names (`robot3`) and back; `tasks_for` maps an action
of the grammar onto the task language in either tier (RemoteBotMotion through each robot's
MissionControl, or BotMotion straight to its motion plugin).
"""

from __future__ import annotations

import re
from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field
from typing import Any

from erni.blackboard import Task
from erni.blackboard.errors import ConfigError, TaskError
from erni.blackboard.tasks import PREPOSITIONS
from erni.plugins.ui.grammar import STRATEGY_VERB, Command, Refusal, parse

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


def spoken_list(numbers: Iterable[int]) -> str:
    """Return `5`, `5 and 6`, `4, 5 and 6`."""
    items = [str(n) for n in numbers]
    return items[0] if len(items) == 1 else ", ".join(items[:-1]) + " and " + items[-1]


def tasks_for(action: str, params: Mapping[str, Any], robots: Iterable[str], *, verb: str,
              source: str) -> list[Task]:
    """Return one task per robot for a grammar action, in the configured tier.

    Deployment strategies are `Deploy` tasks in either tier. With `verb = "RemoteBotMotion"`, prepositions the team verb lacks go as BotMotion straight
    to the robot (turn, backward), and `stop` becomes RemoteBotMotion `cancel` (cancel the
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


@dataclass
class Reply:
    """What the dialogue answers to one utterance."""

    heard: str
    say: str | None = None
    tasks: list[Task] = field(default_factory=list)
    targets: list[str] = field(default_factory=list)
    accepted: bool = False
    action: str = ""


class Dialogue:
    """Listening state and sticky targets of one operator; `hear()` answers each utterance."""

    def __init__(self, naming: Naming | None = None, *, verb: str = "RemoteBotMotion", source: str = "control",
                 listening: bool = True) -> None:
        self.naming = naming or Naming()
        self.verb = verb
        self.source = source
        self.listening = listening
        self.targets: list[str] = []

    def select(self, robots: Iterable[str]) -> None:
        """Make these robots the current targets (the GUI's selection)."""
        self.targets = list(dict.fromkeys(robots))

    def hear(self, text: str, known: Iterable[str]) -> Reply:
        """Answer one utterance given the robots (agent names) the team has now."""
        known = sorted(set(known), key=lambda n: (self.naming.number(n) is None, self.naming.number(n) or 0, n))
        reply = Reply(text)
        try:
            cmd = parse(text)
        except Refusal as why:
            if self.listening:
                reply.say = str(why)
            return reply
        if cmd.kind == "attention":
            self.listening = True
            reply.say, reply.accepted = LISTENING, True
            return reply
        if not self.listening:
            return reply  # ignored until the next "attention"
        if cmd.kind == "sleep":
            self.listening = False
            reply.say, reply.accepted = STANDING_BY, True
            return reply
        try:
            targets = self._targets(cmd, known)
            params = self._relay_ends(cmd, known) if cmd.action == "relay" else cmd.params
            reply.tasks = tasks_for(cmd.action, params, targets, verb=self.verb, source=self.source)
        except Refusal as why:
            reply.say = str(why)
            return reply
        self.targets = targets
        reply.targets, reply.action = list(targets), cmd.action
        reply.say, reply.accepted = ROGER, True
        return reply

    def _relay_ends(self, cmd: Command, known: list[str]) -> dict[str, Any]:
        names = {k: self.naming.name(cmd.params[k]) for k in ("source", "destination")}
        missing = [cmd.params[k] for k, name in names.items() if name not in known]
        if missing:
            noun = "robot" if len(missing) == 1 else "robots"
            raise Refusal(f"I don't know {noun} {spoken_list(missing)}")
        return {**cmd.params, **names}

    def _targets(self, cmd: Command, known: list[str]) -> list[str]:
        if cmd.everyone:
            if not known:
                raise Refusal("I don't know any robots")
            return list(known)
        if cmd.robots:
            names = [self.naming.name(n) for n in cmd.robots]
            missing = [n for n, name in zip(cmd.robots, names) if name not in known]
            if missing:
                noun = "robot" if len(missing) == 1 else "robots"
                raise Refusal(f"I don't know {noun} {spoken_list(missing)}")
            return names
        if not self.targets:
            raise Refusal("Which robots?")
        return list(self.targets)
