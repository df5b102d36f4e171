"""`erni peers`: list the agents a team member knows, with liveness."""

from __future__ import annotations

import argparse
import sys
import time
from typing import TYPE_CHECKING, Any

from erni.blackboard.messages import PeerList
from erni.commands._client import add_client_options, dumps, open_client
from erni.commands._text import say

if TYPE_CHECKING:
    from erni.transport.endpoint import Address


def register(sub: Any) -> None:
    """Add the `peers` sub-command."""
    p = sub.add_parser("peers", help="list known agents and whether they are heard",
                       description="Ask one agent (--via, or one found by its beacons) for its directory.")
    add_client_options(p)
    p.set_defaults(func=run)


ROUTES_WAIT = 2.0
"""On Zenoh, how long `erni peers` waits for the liveliness tokens of the agents that are up (s)."""


def run(args: argparse.Namespace) -> int:
    """Print the directory as a table or JSON lines."""
    from erni.transport.client import ClientError

    client = open_client(args, "peers")
    if client is None:
        return 2
    with client:
        try:
            addr, directory = ask_directory(client)
        except ClientError as err:
            say(f"erni peers: {err}", file=sys.stderr)
            return 1
        routes = _routes(client, directory)
    if args.json:
        _print_json(directory, routes)
    else:
        _print_table(directory, routes, addr)
    return 0


def ask_directory(client: Any, addr: Address | None = None) -> tuple[Address, PeerList]:
    """Ask one agent (the one at `addr`, or any found) for its directory: its address and the whole
    directory (ClientError: no answer in 5 s)."""
    from erni.transport.client import ClientError, PeerListParts

    addr = addr or client.find(None)
    client.send(addr, "peers.request", None)
    deadline = time.monotonic() + 5.0
    parts = PeerListParts()  # a large directory comes in parts
    directory: PeerList | None = None
    while directory is None and time.monotonic() < deadline:
        client.check_refused()
        msg = client.receive(0.2)
        if msg is not None and msg.kind == "peers.reply" and isinstance(msg.body, PeerList):
            directory = parts.add(msg.body)
    if directory is None:
        raise ClientError(f"no answer from {addr[0]}:{addr[1]} within 5 s")
    return addr, directory


def _routes(client: Any, directory: PeerList) -> dict[str, str | None]:
    """On Zenoh: the router each agent is connected through, as its liveliness token says (empty elsewhere).

    The tokens reach this client's own session on their own time, so wait a little for those of the
    agents that are up (a '-' then means no token, not one still on its way)."""
    route_of = getattr(client.endpoint, "route_of", None)
    if route_of is None:
        return {}
    deadline = time.monotonic() + ROUTES_WAIT
    while any(route_of(p.name) is None for p in directory.peers if p.up) and time.monotonic() < deadline:
        time.sleep(0.05)
    return {p.name: route_of(p.name) for p in directory.peers}


def _print_json(directory: PeerList, routes: dict[str, str | None]) -> None:
    from erni.transport.zenoh_keys import wire_of

    beacons, down_after = directory.beacons, directory.down_after
    for p in sorted(directory.peers, key=lambda p: p.name):
        say(dumps({"via": directory.agent, **p.model_dump(mode="json"), "wire": wire_of(p.address),
                     **({"router": routes.get(p.name)} if routes else {}),
                     "beacons": beacons.get(p.name), "down_after": down_after.get(p.name)}))


def _print_table(directory: PeerList, routes: dict[str, str | None], addr: Address) -> None:
    from erni.transport.zenoh_keys import wire_of

    now = time.time()
    beacons, down_after = directory.beacons, directory.down_after
    say(f"agents known to {directory.agent} ({addr[0]}:{addr[1]}):")
    say(f"{'name':<16} {'state':<5} {'wire':<5} {'address':<22}" + (f" {'router':<12}" if routes else "")
          + f" {'role':<10} {'heard':>8} {'down after':>10} {'beacons':>8}  capabilities")
    for p in sorted(directory.peers, key=lambda p: p.name):
        route = routes.get(p.name)
        router = f" {'-' if route is None else route[:12] or 'direct':<12}" if routes else ""
        heard = f"{now - p.last_heard:.1f}s" if p.last_heard else "never"
        limit = f"{down_after[p.name]:.1f}s" if p.name in down_after else "-"
        share = f"{100 * beacons[p.name]:.0f}%" if p.name in beacons else "-"
        say(f"{p.name:<16} {'up' if p.up else 'down':<5} {wire_of(p.address) or '-':<5} {p.address:<22}{router} "
              f"{p.role:<10} {heard:>8} {limit:>10} "
              f"{share:>8}  {','.join(p.capabilities)}" + (f"  DEGRADED: {p.degraded}" if p.degraded else ""))
