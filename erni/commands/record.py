"""`erni record [--via HOST:PORT] OUT`: record what one agent of a running team sees."""

from __future__ import annotations

import argparse
import sys
import time
from typing import Any

from erni.commands._client import add_client_options, check_seconds, open_client, watch_events
from erni.replay import LogError, Recorder

LEASE = 10.0


def register(sub: Any) -> None:
    """Add the `record` sub-command."""
    p = sub.add_parser("record", help="record a team's tasks, results, poses and peer events",
                       description="Record every blackboard change one agent (usually the control "
                       "node) sees, as JSON lines, until Ctrl-C. Replay it with `erni replay`.")
    p.add_argument("out", help="log file to write (JSON lines)")
    p.add_argument("--seconds", type=float, default=0, help="stop after S seconds (0 = at Ctrl-C)")
    add_client_options(p)
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    """Lease a watch and write every event to the log, with a progress line on stderr."""
    from erni.transport.client import ClientError

    problem = check_seconds(args.seconds, "--seconds", zero=True)
    if problem:
        print(f"erni record: {problem}", file=sys.stderr)
        return 2
    client = open_client(args, "record")
    if client is None:
        return 2
    end = time.monotonic() + args.seconds if args.seconds else None
    with client:
        try:
            addr = client.find(None)
            recorder = Recorder(args.out, f"{addr[0]}:{addr[1]}")
        except (ClientError, LogError) as err:
            print(f"erni record: {err}", file=sys.stderr)
            return 1 if isinstance(err, ClientError) else 2
        print(f"recording {addr[0]}:{addr[1]} into {args.out} (Ctrl-C stops)", file=sys.stderr)
        shown = 0.0
        try:
            for ev in watch_events(client, addr, end, LEASE):
                if ev is not None:
                    recorder.write(ev.agent, ev.op, ev.type, ev.data)
                if sys.stderr.isatty() and time.monotonic() >= shown:
                    print(f"\r{recorder.count} events", end="", file=sys.stderr, flush=True)
                    shown = time.monotonic() + 0.5
        except KeyboardInterrupt:
            pass
        finally:
            recorder.close()
    print(f"\nrecorded {recorder.count} events into {args.out}", file=sys.stderr)
    return 0
