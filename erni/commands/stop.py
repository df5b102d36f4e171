"""`erni stop [ROBOT ...]`: stop robots of a running team; without names, every robot it has.

Each robot gets the stop the console's "everyone stop" sends it: `RemoteBotMotion cancel` (its
remote tasks cancelled and the robot halted), or with `--verb BotMotion` a `BotMotion stop`
(every motion of the robot ends; obstacle avoidance stays). The tasks go as `erni task` sends
one (`deliver`, then `answers`), all at once through one agent; one line says which robots took
the stop and which did not.
"""

from __future__ import annotations

import argparse
import sys
import time
from typing import TYPE_CHECKING, Any

from erni.blackboard.errors import shown
from erni.commands._client import add_client_options, dumps, open_client
from erni.commands._text import say
from erni.commands.task import ANSWER_WAIT, DISCOVERY_WAIT, Answer, answers, deliver

if TYPE_CHECKING:
    from erni.blackboard import Task

# a stop in each tier of the task language, as the console's dialogue turns "stop" into tasks
# (erni.plugins.ui.dialogue.tasks_for; tests/core/test_cli_startup.py checks they stay the same)
STOP = {"RemoteBotMotion": "cancel", "BotMotion": "stop"}


def register(sub: Any) -> None:
    """Add the `stop` sub-command."""
    p = sub.add_parser("stop", help="stop robots of a running team (every robot without names)",
                       description="Stop each ROBOT, or without names every robot in the directory of the "
                       "agent reached through (--via, or one found by its beacons): RemoteBotMotion cancel "
                       "(its remote tasks cancelled and the robot halted), or with --verb BotMotion a "
                       "BotMotion stop. One line says which robots took the stop. Exit 0 when every robot "
                       "asked took it, 1 when one did not or no robot is known, 2 on bad arguments.")
    p.add_argument("robots", nargs="*", metavar="ROBOT", help="a robot to stop (default: every robot of the team)")
    p.add_argument("--verb", choices=sorted(STOP), default="RemoteBotMotion",
                   help="RemoteBotMotion (default) or BotMotion for teams without MissionControl")
    add_client_options(p)
    p.set_defaults(func=run, collect_later=True)  # the collector is on once the tasks went (`deliver`)


def stops(verb: str, robots: list[str], source: str) -> list[Task]:
    """One stop task per robot, in the tier of `verb` (TaskError: a name that is no agent's)."""
    from erni.blackboard import Task

    return [Task(verb=verb, preposition=STOP[verb], destination=robot, source=source) for robot in robots]


def run(args: argparse.Namespace) -> int:
    """Send the stops, all at once; say which robots took them."""
    from erni.blackboard import TaskError
    from erni.transport.client import ClientError

    named = list(dict.fromkeys(args.robots))
    for robot in named:
        try:
            stops(args.verb, [robot], "cli")
        except TaskError as err:  # the destination's problem: "cancel: destination: expected a name ..."
            say(f"erni stop: ROBOT {shown(robot)}: {str(err).rpartition('destination: ')[2]}", file=sys.stderr)
            return 2
    client = open_client(args, "stop")
    if client is None:
        return 2
    with client:
        try:
            addr = client.find(named[0] if len(named) == 1 else None)
            robots = named or _every_robot(client, addr)
            if not robots:
                return 1
            tasks = stops(args.verb, robots, client.endpoint.name)
            deliver(client, addr, tasks)
        except ClientError as err:
            say(f"erni stop: {err}", file=sys.stderr)
            return 1
        # named robots reached through another agent are looked up in its directory, after the stops went
        got = answers(client, addr, tasks, check_names=bool(named) and (bool(args.via) or len(named) > 1))
    return _report(args, addr, tasks, got)


def _every_robot(client: Any, addr: tuple[str, int]) -> list[str]:
    """The robots in the directory of the agent at `addr` (asked again for a while while it lists no
    agent: one that just started has heard nobody yet); [] said on stderr."""
    from erni.commands.peers import ask_directory

    end = time.monotonic() + DISCOVERY_WAIT
    while True:
        _, directory = ask_directory(client, addr)
        heard = [name for name, (_, beacon) in client.beacons.items() if beacon.role == "robot"]
        robots = sorted({p.name for p in directory.peers if p.role == "robot"} | set(heard))
        if robots or directory.peers or time.monotonic() > end:
            break
        time.sleep(0.5)
    if not robots:
        others = ", ".join(sorted(p.name for p in directory.peers)[:20]) or "no other agent"
        say(f"erni stop: no robot to stop: {directory.agent} at {addr[0]}:{addr[1]} knows {others} "
            "(`erni peers` lists them)", file=sys.stderr)
    return robots


def _said(answer: Answer) -> str:
    """What became of one robot's stop, in a few words."""
    if answer.state == "unknown":
        return "not in the team"
    if answer.state == "succeeded":
        return "stopped"
    if answer.state == "running":
        return "stopping"
    if answer.state == "sent":
        return f"no answer within {ANSWER_WAIT:g} s"
    if answer.state == "pending":
        return f"not taken within {ANSWER_WAIT:g} s (pending: not heard?)"
    reason = " ".join(answer.result.message.split()) if answer.result is not None else ""
    return f"{answer.state}: {reason or 'no reason given'}"


def _report(args: argparse.Namespace, addr: tuple[str, int], tasks: list[Task], got: dict[str, Answer]) -> int:
    """One line: which robots took the stop (stdout, exit 0 when every one did; else stderr, exit 1)."""
    taken = [t for t in tasks if got[t.uid].state in ("succeeded", "running")]
    ok = len(taken) == len(tasks)
    if args.json:
        say(dumps({"via": f"{addr[0]}:{addr[1]}", "verb": args.verb, "taken": len(taken), "asked": len(tasks),
                   "robots": {t.destination: {"uid": t.uid, "state": got[t.uid].state, "said": _said(got[t.uid])}
                              for t in tasks}}))
        return 0 if ok else 1
    line = (f"stop taken by {len(taken)} of {len(tasks)} robot{'s' if len(tasks) != 1 else ''} through "
            f"{addr[0]}:{addr[1]}: " + ", ".join(f"{t.destination} {_said(got[t.uid])}" for t in tasks))
    if ok:
        say(line)
        return 0
    say(f"erni stop: {line}", file=sys.stderr)
    return 1

