"""`erni watch`: stream poses, task results and peer events of a running team as lines."""

from __future__ import annotations

import argparse
import sys
import time
from typing import Any

from erni.blackboard.schemas import WatchEvent
from erni.commands._client import add_client_options, check_seconds, dumps, open_client, stamp, watch_events
from erni.commands._text import say

LEASE = 10.0


def register(sub: Any) -> None:
    """Add the `watch` sub-command."""
    p = sub.add_parser("watch", help="stream poses, results and peer events as lines",
                       description="Stream what one agent's blackboard sees (Ctrl-C stops).")
    p.add_argument("--count", type=int, default=0, help="stop after N events (0 = never)")
    p.add_argument("--seconds", type=float, default=0, help="stop after S seconds (0 = never)")
    add_client_options(p)
    p.set_defaults(func=run)


def describe(event: WatchEvent) -> str:
    """One human line for an event."""
    d = event.data
    if event.type == "Pose":
        text = (f"{d['robot']} x={d['x']:.2f} y={d['y']:.2f} th={d['theta']:.2f} v={d['v']:.2f}"
                + (f" bat={d['battery']:.1f}V" if d.get("battery") is not None else ""))
    elif event.type == "Task":
        r = d.get("result") or {}
        text = (f"{d['uid']} {d['verb']} {d['preposition']} -> {d.get('destination') or event.agent} "
                f"{r.get('state', 'pending')} {r.get('progress', 0):.0%} {r.get('message', '')}")
    elif event.type == "Peer":
        text = f"{d['name']} {'up' if d['up'] else 'down'} {d['address']}"
    else:
        text = f"{d.get('node', '')} {d.get('kind', '')}" + (" degraded" if d.get("degraded") else "")
    return f"{stamp()} {event.agent} {event.op:<6} {event.type:<7} {text.rstrip()}"


def run(args: argparse.Namespace) -> int:
    """Lease a watch from one agent and print its events until stopped."""
    from erni.transport.client import ClientError

    problem = check_seconds(args.seconds, "--seconds", zero=True)
    if problem:
        say(f"erni watch: {problem}", file=sys.stderr)
        return 2
    client = open_client(args, "watch")
    if client is None:
        return 2
    seen = 0
    end = time.monotonic() + args.seconds if args.seconds else None
    with client:
        try:
            addr = client.find(None)
        except ClientError as err:
            say(f"erni watch: {err}", file=sys.stderr)
            return 1
        try:
            for ev in watch_events(client, addr, end, LEASE, command="watch"):
                if ev is None:
                    client.check_refused()
                    continue
                say(dumps(ev.model_dump(mode="json")) if args.json else describe(ev), flush=True)
                seen += 1
                if args.count and seen >= args.count:
                    break
        except ClientError as err:
            say(f"erni watch: {err}", file=sys.stderr)
            return 1
        except KeyboardInterrupt:
            pass
        if not seen and not client.delivered:  # events may come before the request's acknowledgement
            say(f"erni watch: nothing answered at {addr[0]}:{addr[1]}", file=sys.stderr)
            return 1
    return 0

