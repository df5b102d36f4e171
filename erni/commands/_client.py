"""Options and helpers shared by the commands that talk to a running team.

Adding the options imports nothing of the transport: a command's parser is built before anything
is known to be sent (`erni stop --help`, a bad argument), and the transport is imported when the
client is made.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import sys
import time
from collections.abc import Iterator
from pathlib import Path
from typing import TYPE_CHECKING, Any

from erni.blackboard.errors import ErniError, UsageError
from erni.commands._text import say

if TYPE_CHECKING:
    from erni.transport.endpoint import Address

DISCOVERY_PORT = 47000  # the beacon port of a team that names no other


def add_client_options(p: argparse.ArgumentParser) -> None:
    """Add --via, --discovery-port, --zenoh, --team, --identity, --key-env, --insecure and --json."""
    p.add_argument("--via", metavar="HOST:PORT", help="an agent's transport address, or with --zenoh its name "
                   "(default: the control node of a running erni sim of this user's, else find one by its "
                   "beacons or liveliness token)")
    p.add_argument("--zenoh", metavar="ENDPOINT", action="append", help="reach a team that runs over Zenoh "
                   "through this router or peer, e.g. tcp/192.0.2.1:7447 (repeatable)")
    p.add_argument("--team", default="team", help="with --zenoh: the team's key chunk (default: team)")
    p.add_argument("--discovery-port", type=int, default=None,
                   help=f"beacon port (default {DISCOVERY_PORT})")
    p.add_argument("--identity", metavar="FILE", help="this client's identity bundle, role cli "
                   "(default: $ERNI_IDENTITY)")
    p.add_argument("--key-env", default="ERNI_TEAM_KEY", help="environment variable with a shared team key "
                   "(used without an identity)")
    p.add_argument("--insecure", action="store_true", help="send unauthenticated frames")
    p.add_argument("--json", action="store_true", help="one JSON object per line")


def check_seconds(value: float | None, option: str, *, zero: bool = False) -> str:
    """'' if `value` is a usable number of seconds (None: not given), else the one-line problem."""
    if value is None or (zero and value == 0):
        return ""
    if not math.isfinite(value) or value <= 0:
        return f"{option}: expected a finite number of seconds > 0{' (or 0)' if zero else ''}, got {value}"
    return ""


def via_address(args: argparse.Namespace) -> Address | None:
    """Return the --via address, or None (raises ValueError naming the problem)."""
    if not args.via:
        return None
    if getattr(args, "zenoh", None):
        from erni.transport.zenoh_keys import NAME, address_of

        if not NAME.match(args.via):
            raise UsageError(f"--via {args.via!r}: with --zenoh, expected an agent's name")
        return address_of(args.via)
    from erni.transport.endpoint import parse_address

    host, port = parse_address(args.via)
    if port == 0:
        raise UsageError(f"--via {args.via!r}: expected HOST:PORT")
    return host, port


def make_client(args: argparse.Namespace) -> Any:
    """Build a Client from the shared options (without --via, --zenoh and --discovery-port: to the control node
    of a running `erni sim` of this user's, if there is one and no other credentials were given)."""
    from erni.transport.client import Client

    zenoh = None
    if getattr(args, "zenoh", None):
        from erni.transport.zenoh_keys import ZenohSettings

        try:
            zenoh = ZenohSettings(team=args.team, mode="client", connect=args.zenoh)
        except ValueError as err:  # pydantic's: the first problem, on one line
            errors = getattr(err, "errors", None)
            raise UsageError(f"--zenoh/--team: {errors()[0]['msg'] if errors else err}") from None
    via, identity = via_address(args), args.identity
    if via is None and zenoh is None and args.discovery_port is None:
        via, identity = _sim_team(args) or (None, identity)
    return Client(via, discovery_port=args.discovery_port or DISCOVERY_PORT, identity=identity,
                  key_env=args.key_env, insecure=args.insecure, zenoh=zenoh)


def _sim_team(args: argparse.Namespace) -> tuple[Address, str] | None:
    """The control node's address and the identity of a running `erni sim` of this user's, when the command
    was given no credentials of its own or that run's identity; else None."""
    from erni.commands._team_file import running_sim
    from erni.transport.client import IDENTITY_ENV
    from erni.transport.endpoint import parse_address

    if args.insecure:
        return None
    given = args.identity or os.environ.get(IDENTITY_ENV) or ""
    if not given and os.environ.get(args.key_env):
        return None  # a shared team key: another team's
    team = running_sim()
    if team is None or (given and Path(given).resolve() != Path(team["identity"]).resolve()):
        return None
    host, port = parse_address(team["via"])
    return (host, port), team["identity"]


def open_client(args: argparse.Namespace, command: str) -> Any:
    """Build the client for `erni COMMAND`, or print the one-line reason and return None."""
    try:
        return make_client(args)
    except (ErniError, ValueError) as err:
        say(f"erni {command}: {str(err).splitlines()[0]}", file=sys.stderr)
        return None


def make_room_for_a_stream(client: Any) -> int:
    """Ask the kernel for a receive buffer that holds seconds of a team's watch stream
    (`STREAM_BUFFER`); return the size granted (beyond `net.core.rmem_max` only for a process
    allowed to: root, CAP_NET_ADMIN)."""
    from erni.transport.endpoint import STREAM_BUFFER

    return int(client.endpoint.receive_buffer(STREAM_BUFFER))


def watch_events(client: Any, addr: Address, end: float | None, lease: float = 10.0, *,
                 command: str) -> Iterator[Any]:
    """Lease a watch from the agent at `addr`, renewing it, and yield its events until `end`.

    Yields None about every 0.1 s without an event, so callers can show progress. A request that
    goes unacknowledged (nothing answers at `addr` within the client's delivery time, about 5 s) is
    sent again within a second, and `erni COMMAND` says so once on stderr, so a watch of nothing
    does not print nothing; an agent that starts later is still found.
    """
    from erni.blackboard.messages import WatchEvent, WatchRequest

    make_room_for_a_stream(client)
    renew = 0.0
    told = False
    asked: set[str] = set()
    while not (end and time.monotonic() > end):
        if time.monotonic() >= renew:
            asked.add(client.send(addr, "watch.request", WatchRequest(lease=lease)))
            renew = time.monotonic() + lease / 2
        if client.take_failed(asked):
            renew = min(renew, time.monotonic() + 1.0)
            if not told:
                say(f"erni {command}: nothing answers at {addr[0]}:{addr[1]} (no acknowledgement within 5 s: is an "
                    "agent running there, and does it trust this identity?); still asking, Ctrl-C stops",
                    file=sys.stderr, flush=True)
            told = True
        msg = client.receive(0.1)
        if msg is not None and msg.kind == "watch.event" and isinstance(msg.body, WatchEvent):
            yield msg.body
        else:
            yield None


def stamp(t: float | None = None) -> str:
    """Return HH:MM:SS.mmm for a wall-clock time; a time no clock shows (a peer's result stamped 1e300,
    before the epoch by centuries) as its number, `t=1e+300`."""
    t = time.time() if t is None else t
    try:
        return time.strftime("%H:%M:%S", time.localtime(t)) + f".{int(t % 1 * 1000):03d}"
    except (OverflowError, OSError, ValueError):
        return f"t={t:g}"


def dumps(obj: Any) -> str:
    """Return compact JSON, all ASCII: a string's control characters are JSON escapes (DEL too, which
    `json` leaves as it is), so a line of it prints as it reads."""
    return json.dumps(obj, separators=(",", ":"), default=str).replace("\x7f", "\\u007f")
