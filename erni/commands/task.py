"""`erni task AGENT VERB PREPOSITION [KEY=VALUE ...]`: task an agent of a running team.

Sending tasks and waiting for their performers to take them (`deliver`, `answers`) is shared with
`erni stop`. The task language and the transport are imported once the arguments are read, not to
build the parser: a stop typed in a hurry goes out in a fraction of a second.
"""

from __future__ import annotations

import argparse
import gc
import sys
import time
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

from erni.blackboard.errors import UsageError, shown
from erni.commands._client import add_client_options, check_seconds, dumps, open_client, stamp
from erni.commands._text import say

if TYPE_CHECKING:
    from erni.blackboard import Task
    from erni.blackboard.messages import PeerList

QUERY_PERIOD = 2.0  # with --wait, ask the agent for the task's state this often
ANSWER_WAIT = 5.0  # without --wait, how long to wait for the agent to take the task or refuse it
# through another agent (--via), a name missing from its directory fails at once; only while that
# directory is still empty (the agent reached through just started and heard nobody yet) it is asked
# again for this long, so `erni agent ... &` followed at once by `erni task` works
DISCOVERY_WAIT = 4.0


def register(sub: Any) -> None:
    """Add the `task` sub-command."""
    p = sub.add_parser("task", help="send a task to an agent and print its result",
                       description="Send a task to AGENT (through --via or a discovered agent). "
                       "Without --wait, wait only for AGENT to take the task or refuse it. "
                       "Exit 0 on success (taken, without --wait), 1 on failure or refusal, 2 on bad arguments.")
    p.add_argument("agent", help="the agent that performs the task")
    p.add_argument("verb", help="NetWatch, BotMotion, RemoteBotMotion, ...")
    p.add_argument("preposition", help="the sub-task, e.g. goto")
    p.add_argument("params", nargs="*", metavar="KEY=VALUE", help="parameters (see `erni tasks`)")
    p.add_argument("--wait", action="store_true", help="print result updates until the task ends")
    p.add_argument("--timeout", type=float, default=None, help="with --wait: give up (and cancel) after S seconds")
    p.add_argument("--link-deadline", type=float, default=30.0,
                   help="with --wait: give up when the agent reached through does not answer for S "
                   "seconds (default 30)")
    add_client_options(p)
    p.set_defaults(func=run, collect_later=True)  # the collector is on once the tasks went (`deliver`)


def parse_params(items: list[str]) -> dict[str, Any]:
    """Turn KEY=VALUE words into a dict; values are JSON when they parse, else strings."""
    from erni.transport.wire import loads

    params: dict[str, Any] = {}
    for item in items:
        key, sep, value = item.partition("=")
        if not sep or not key:
            raise UsageError(f"parameter {shown(item)}: expected KEY=VALUE")
        try:
            params[key] = loads(value)
        except UsageError as err:
            raise UsageError(f"parameter {shown(key, 40)}: {err}") from None
        except ValueError:
            params[key] = value
    return params


def _line(args: argparse.Namespace, task: Task, result: Any) -> str:
    if args.json:
        return dumps({"uid": task.uid, "agent": args.agent, **result.model_dump(mode="json")})
    values = " ".join(f"{k}={v}" for k, v in result.values.items())
    return (f"{stamp(result.stamp)} {args.agent} {task.uid} {result.state.value:<9} "
            f"{result.progress:4.0%} {result.message} {values}").rstrip()


def run(args: argparse.Namespace) -> int:
    """Send the task; with --wait follow it to its end (or until its link is lost)."""
    problem = check_seconds(args.timeout, "--timeout") or check_seconds(args.link_deadline, "--link-deadline")
    if problem:
        say(f"erni task: {problem}", file=sys.stderr)
        return 2
    from erni.blackboard import Task, TaskError
    from erni.blackboard.messages import Cancel
    from erni.transport.client import ClientError

    try:
        task = Task(verb=args.verb, preposition=args.preposition, params=parse_params(args.params),
                    destination=args.agent, source="cli")
    except (TaskError, UsageError) as err:
        say(f"erni task: {err}", file=sys.stderr)
        return 2
    client = open_client(args, "task")
    if client is None:
        return 2

    with client:
        task = task.evolve(source=client.endpoint.name)
        try:
            addr = client.find(args.agent)
            deliver(client, addr, [task])
        except ClientError as err:
            say(f"erni task: {err}", file=sys.stderr)
            return 1
        if not args.wait:
            return _answer(args, client, addr, task)
        try:
            return _follow(args, client, addr, task)
        except KeyboardInterrupt:
            client.send(addr, "task.cancel", Cancel(uid=task.uid))
            time.sleep(0.2)
            say(f"erni task: cancelled {task.uid}", file=sys.stderr)
            return 130


def deliver(client: Any, addr: tuple[str, int], tasks: list[Task]) -> None:
    """Send each task to the agent at `addr`, all at once; return when that agent acknowledged every
    one (ClientError: one could not be delivered, or no acknowledgement within 6 s).

    The garbage collector is turned on once the tasks are on their way: `erni task` and `erni stop`
    start with it off (erni.cli), so that importing what sends them is not slowed by it. What the
    start built is frozen first (it lives to the end): the collector, back on, does not walk it
    while the handshake that carries the tasks is made."""
    from erni.transport.client import ClientError

    ids = [client.send(addr, "task.add", task) for task in tasks]
    gc.freeze()
    gc.enable()
    deadline = time.monotonic() + 6.0
    while not all(msg_id in client.delivered for msg_id in ids):
        client.check_failed(*ids)
        if time.monotonic() > deadline:
            raise ClientError("could not reach the agent: no acknowledgement")
        time.sleep(0.01)


@dataclass
class Answer:
    """What became of a task sent, as far as its performer said within the wait."""

    state: str = "sent"  # sent, pending, a TaskState's value, or "unknown" (no such agent in the team)
    result: Any = None  # the performer's last TaskResult
    reason: str = ""  # unknown: why AGENT is no agent of the team

    @property
    def settled(self) -> bool:
        """Whether the performer has it (running, or done) or it cannot be (refused, unknown)."""
        return self.state not in ("sent", "pending")  # pending may be a relay's note


def answers(client: Any, addr: tuple[str, int], tasks: list[Task], *,
            check_names: bool) -> dict[str, Answer]:
    """Wait at most `ANSWER_WAIT` s for each task's performer to take it (running, or done) or refuse it;
    return the answer of each (by uid).

    With `check_names`, the directory of the agent reached through is asked for too: a destination it
    has never heard of is a typo, not a robot still starting, and its task is cancelled at once
    instead of waiting there for the agent to be discovered. (The tasks go first: a stop is never
    held up.)
    """
    from erni.blackboard.messages import ResultUpdate, TaskQuery

    start = time.monotonic()
    next_query = start + 1.0
    got = {task.uid: Answer() for task in tasks}
    known = _NameCheck(client, addr, sorted({t.destination or "" for t in tasks}), check=check_names)
    while (waiting := [t for t in tasks if not got[t.uid].settled]) \
            and (left := start + ANSWER_WAIT - time.monotonic()) > 0:
        known.ask()
        if time.monotonic() >= next_query:  # an update may be lost: the agent answers with the task's state
            for task in waiting:
                client.send(addr, "task.query", TaskQuery(uid=task.uid), reliable=False)
            next_query += 1.0
        msg = client.receive(min(left, 0.2))
        unknown = known.answered(msg)
        for task in waiting:
            if task.destination in unknown:
                got[task.uid] = Answer("unknown", reason=unknown[task.destination or ""])
                _cancel(client, addr, task)
        if msg is None or msg.kind != "task.result" or not isinstance(msg.body, ResultUpdate) \
                or msg.body.uid not in got or got[msg.body.uid].settled:
            continue
        got[msg.body.uid] = Answer(msg.body.result.state.value, msg.body.result)
    return got


def _answer(args: argparse.Namespace, client: Any, addr: tuple[str, int], task: Task) -> int:
    """Without --wait: wait for the agent to take the task (running, or done) or refuse it; 1 on refusal
    (or when it is no agent of the team the agent reached through, --via, knows)."""
    answer = answers(client, addr, [task], check_names=bool(args.via))[task.uid]
    if answer.state == "unknown":
        say(f"erni task: {answer.reason}", file=sys.stderr)
        return 1
    state, result = answer.state, answer.result
    if result is not None and result.state.done and state != "succeeded":
        if args.json:
            say(_line(args, task, result))
        reason = " ".join(result.message.split()) or "no reason given"
        say(f"erni task: {args.agent}: task {task.uid} {state}: {reason}", file=sys.stderr)
        return 1
    if args.json:
        say(dumps({"uid": task.uid, "agent": args.agent, "state": state}))
    else:
        note = f" (still {state} after {ANSWER_WAIT:g} s; `erni task --wait` follows a task)" \
            if state in ("sent", "pending") else f" ({state})"
        say(f"{task.uid} sent to {args.agent}: {task.describe()}{note}")
    return 0


class _NameCheck:
    """Through another agent (--via): whether each of `names` is in its directory. Asked at once (after
    the tasks went: a stop is never held up); a name missing from a directory that lists other agents
    is a typo, not a robot still starting. An empty directory is asked again for `DISCOVERY_WAIT` s."""

    def __init__(self, client: Any, addr: tuple[str, int], names: list[str], *, check: bool):
        from erni.transport.client import PeerListParts

        self.names, self.client, self.addr = names, client, addr
        self.pending = check
        self.parts = PeerListParts()  # a large directory comes in parts
        self.start = time.monotonic()
        self.next_ask = self.start

    def ask(self) -> None:
        """Ask for the directory when an answer is due and none settled the question."""
        if self.pending and time.monotonic() >= self.next_ask:
            self.client.send(self.addr, "peers.request", None)
            self.next_ask = time.monotonic() + 0.5

    def answered(self, msg: Any) -> dict[str, str]:
        """Name -> the one-line reason it is no agent of the team, for each of `names` that the directory
        `msg` says so of (empty unless `msg` is the directory, whole)."""
        from erni.blackboard.messages import PeerList

        if not self.pending or msg is None or msg.kind != "peers.reply" or not isinstance(msg.body, PeerList):
            return {}
        directory = self.parts.add(msg.body)
        if directory is None:
            return {}  # more parts to come
        unknown = {name: why for name in self.names if (why := _unknown(name, directory))}
        waited = time.monotonic() - self.start
        if unknown and not directory.peers and waited < DISCOVERY_WAIT:
            return {}  # nobody heard yet: ask again
        self.pending = False
        if unknown and not directory.peers:
            return {name: f"no agent {name} in the team: {directory.agent} has heard of no other agent within "
                    f"{waited:.0f} s (is {name} running, with the same discovery port?)" for name in unknown}
        return unknown


def _unknown(agent: str, peers: PeerList) -> str:
    """Why `agent` is no agent of the team the agent `peers` came from ('' if it is one)."""
    if agent == peers.agent or any(p.name == agent for p in peers.peers):
        return ""
    known = ", ".join(sorted(p.name for p in peers.peers)[:20]) or "no other agent"
    return f"no agent {agent} in the team: {peers.agent} knows {known} (`erni peers` lists them)"


def _cancel(client: Any, addr: tuple[str, int], task: Task, wait: float = 2.0) -> None:
    """Cancel `task` at the agent reached through; return once it acknowledged (or after `wait` s)."""
    from erni.blackboard.messages import Cancel

    msg_id = client.send(addr, "task.cancel", Cancel(uid=task.uid))
    deadline = time.monotonic() + wait
    while msg_id not in client.delivered and time.monotonic() < deadline:
        time.sleep(0.01)


def _given_up(args: argparse.Namespace, client: Any, addr: tuple[str, int], task: Task, now: float,
              end: float | None, heard: float) -> bool:
    """Whether to stop following at `now`: the timeout passed (the task is cancelled) or the agent
    reached through has been silent past the link deadline (each said on stderr)."""
    from erni.blackboard.messages import Cancel

    if end and now > end:
        say(f"erni task: no final result within {args.timeout:g} s; cancelling", file=sys.stderr)
        client.send(addr, "task.cancel", Cancel(uid=task.uid))
        time.sleep(0.2)
        return True
    if now - heard > args.link_deadline:
        say(f"erni task: link lost: no answer from {addr[0]}:{addr[1]} for {now - heard:.0f} s; "
              f"task {task.uid} may still run there", file=sys.stderr)
        return True
    return False


def _follow(args: argparse.Namespace, client: Any, addr: tuple[str, int], task: Task) -> int:
    """Print the task's updates until it is final, the timeout passes, or the agent goes silent."""
    from erni.blackboard.messages import ResultUpdate, TaskQuery, TaskUnknown

    start = time.monotonic()
    end = start + args.timeout if args.timeout else None
    heard = start  # anything from the agent we reach the team through
    next_query = start + QUERY_PERIOD
    shown_last: dict[str, Any] | None = None
    known = _NameCheck(client, addr, [args.agent], check=bool(args.via))
    while True:
        known.ask()
        now = time.monotonic()
        if _given_up(args, client, addr, task, now, end, heard):
            return 1
        if now >= next_query:  # the agent answers with the task's state: a heartbeat, and a lost update found
            client.send(addr, "task.query", TaskQuery(uid=task.uid), reliable=False)
            next_query = now + QUERY_PERIOD
        msg = client.receive(0.2)
        if msg is None:
            continue
        unknown = known.answered(msg)
        if unknown:
            _cancel(client, addr, task)
            say(f"erni task: {unknown[args.agent]}", file=sys.stderr)
            return 1
        if msg.reply == addr or msg.kind in ("task.result", "task.unknown"):
            heard = time.monotonic()
        if msg.kind == "task.unknown" and isinstance(msg.body, TaskUnknown) and msg.body.uid == task.uid:
            say(f"erni task: {args.agent} no longer knows task {task.uid} (restarted without its journal?)",
                  file=sys.stderr)
            return 1
        if msg.kind != "task.result" or not isinstance(msg.body, ResultUpdate) or msg.body.uid != task.uid:
            continue
        result = msg.body.result
        same = result.model_dump(exclude={"stamp"})
        if same == shown_last and not result.state.done:
            continue  # an answer to a query that says nothing new
        shown_last = same
        say(_line(args, task, result), flush=True)
        if result.state.done:
            return 0 if result.state.value == "succeeded" else 1
