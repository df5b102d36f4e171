"""`erni task AGENT VERB PREPOSITION [KEY=VALUE ...]`: task an agent of a running team."""

from __future__ import annotations

import argparse
import json
import sys
import time
from typing import Any

from erni.blackboard import Task, TaskError
from erni.blackboard.errors import UsageError
from erni.blackboard.schemas import Cancel, ResultUpdate
from erni.commands._client import add_client_options, dumps, open_client, stamp


def register(sub: Any) -> None:
    """Add the `task` sub-command."""
    p = sub.add_parser("task", help="send a task to an agent and print its result",
                       description="Send a task to AGENT (through --via or a discovered agent). "
                       "Exit 0 on success, 1 on failure, 2 on bad arguments.")
    p.add_argument("agent", help="the agent that performs the task")
    p.add_argument("verb", help="NetWatch, BotMotion, RemoteBotMotion, ...")
    p.add_argument("preposition", help="the sub-task, e.g. goto")
    p.add_argument("params", nargs="*", metavar="KEY=VALUE", help="parameters (see `erni tasks`)")
    p.add_argument("--wait", action="store_true", help="print result updates until the task ends")
    p.add_argument("--timeout", type=float, default=None, help="with --wait: give up after S seconds")
    add_client_options(p)
    p.set_defaults(func=run)


def parse_params(items: list[str]) -> dict[str, Any]:
    """Turn KEY=VALUE words into a dict; values are JSON when they parse, else strings."""
    params: dict[str, Any] = {}
    for item in items:
        key, sep, value = item.partition("=")
        if not sep or not key:
            raise UsageError(f"parameter {item!r}: expected KEY=VALUE")
        try:
            params[key] = json.loads(value)
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
    """Send the task; with --wait follow it to its end."""
    try:
        task = Task(verb=args.verb, preposition=args.preposition, params=parse_params(args.params),
                    destination=args.agent, source="cli")
    except (TaskError, ValueError) as err:
        print(f"erni task: {err}", file=sys.stderr)
        return 2
    client = open_client(args, "task")
    if client is None:
        return 2
    from erni.transport.client import ClientError

    with client:
        task = task.evolve(source=client.endpoint.name)
        try:
            addr = client.find(args.agent)
            msg_id = client.send(addr, "task.add", task)
            deadline = time.monotonic() + 6.0
            while msg_id not in client.delivered:
                client.check_failed(msg_id)
                if time.monotonic() > deadline:
                    raise ClientError("could not reach the agent: no acknowledgement")
                time.sleep(0.01)
        except ClientError as err:
            print(f"erni task: {err}", file=sys.stderr)
            return 1
        if not args.wait:
            print(dumps({"uid": task.uid, "agent": args.agent, "state": "sent"}) if args.json
                  else f"{task.uid} sent to {args.agent}: {task.describe()}")
            return 0
        end = time.monotonic() + args.timeout if args.timeout else None
        try:
            while True:
                if end and time.monotonic() > end:
                    print(f"erni task: no final result within {args.timeout} s; cancelling",
                          file=sys.stderr)
                    client.send(addr, "task.cancel", Cancel(uid=task.uid))
                    time.sleep(0.2)
                    return 1
                msg = client.receive(0.2)
                if msg is None or msg.kind != "task.result" or not isinstance(msg.body, ResultUpdate):
                    continue
                if msg.body.uid != task.uid:
                    continue
                result = msg.body.result
                print(_line(args, task, result), flush=True)
                if result.state.done:
                    return 0 if result.state.value == "succeeded" else 1
        except KeyboardInterrupt:
            client.send(addr, "task.cancel", Cancel(uid=task.uid))
            time.sleep(0.2)
            print(f"erni task: cancelled {task.uid}", file=sys.stderr)
            return 130
