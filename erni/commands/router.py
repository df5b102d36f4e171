"""`erni router`: a Zenoh router in this process, between the sites of a team on `wire = "zenoh"`."""

from __future__ import annotations

import argparse
import json
import sys
import threading
import time
from typing import TYPE_CHECKING, Any, TextIO

from erni.blackboard.errors import ErniError
from erni.commands._text import say, say_lines

if TYPE_CHECKING:
    from erni.transport.identity import Identity

DEFAULT_LISTEN = "tcp/0.0.0.0:7447"


def register(sub: Any) -> None:
    """Add the `router` sub-command."""
    p = sub.add_parser("router", help="run a Zenoh router for a team on wire = \"zenoh\"",
                       description="Run a Zenoh router in this process until Ctrl-C. Agents in client mode "
                       "connect to it (zenoh.connect); it forwards their frames, which ERNI's sessions keep "
                       "encrypted end to end, so it reads none of them. See docs/tutorials/two-sites-zenoh.md.")
    p.add_argument("--listen", metavar="ENDPOINT", action="append",
                   help=f"where agents and other routers connect, PROTOCOL/HOST:PORT (repeatable; default "
                   f"{DEFAULT_LISTEN})")
    p.add_argument("--connect", metavar="ENDPOINT", action="append", default=[],
                   help="another router to link with, e.g. the other site's (repeatable)")
    p.add_argument("--scouting", action="store_true", help="answer multicast scouting on this LAN, so that "
                   "peers there find this router without being told")
    p.add_argument("--identity", metavar="FILE", help="the router's identity bundle (`erni keys issue DIR NAME "
                   "--role router`): needed for tls/ endpoints, whose links then admit only holders of a "
                   "certificate of the same team authority (mutual TLS)")
    p.add_argument("--acl", metavar="KEYS_DIR", help="access control from the team authority in KEYS_DIR (erni "
                   "keys init): each agent's certificate may put, query and hold a token only as itself, and "
                   "receives only what is addressed to it; certificates of role router may carry anything; "
                   "ROS 2 traffic is admitted by role (--ros2-domain) (needs --identity, --team and tls/ endpoints)")
    p.add_argument("--ros2-domain", type=int, default=0, metavar="ID",
                   help="with --acl, the ROS 2 domain (ROS_DOMAIN_ID, default 0) whose rmw_zenoh traffic is "
                   "admitted by role: the control node's ros2 plugin publishes and serves; certificates of a "
                   "role that may watch subscribe to the topics; of one that may also task publish cmd_vel and "
                   "goal_pose and call the services; others get none of it")
    p.add_argument("--no-ros2", action="store_true", help="with --acl, admit no ROS 2 traffic")
    p.add_argument("--team", help="the team's key chunk, as the agents' zenoh.team: needed by --acl; with it "
                   "the router also holds a token in its name, so `erni peers` names the router each peer "
                   "is reached through")
    p.add_argument("--name", help="the router's name in the team's tokens (default: its identity's name)")
    p.add_argument("--print-acl", action="store_true", help="print the access control as Zenoh configuration "
                   "JSON (its access_control section, for zenohd) and exit")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    """Serve until interrupted; exit 2 on a bad endpoint, 1 when Zenoh cannot listen."""
    from erni.transport.zenoh_keys import check_endpoint

    listen = args.listen or [DEFAULT_LISTEN]
    try:
        for endpoint in listen + args.connect:
            check_endpoint(endpoint)
    except ValueError as err:
        say(f"erni router: {err}", file=sys.stderr)
        return 2
    problem = _acl_problem(args, listen + args.connect)
    if problem:
        say(f"erni router: {problem}", file=sys.stderr)
        return 2
    try:
        access = None
        if args.acl:
            from erni.transport.zenoh_acl import access_control, team_roles

            agents, routers = team_roles(args.acl)
            access = access_control(args.team, sorted(agents), routers, roles=agents,
                                    ros2_domain=None if args.no_ros2 else args.ros2_domain)
            if args.print_acl:
                say_lines(json.dumps({"access_control": access}, indent=2))
                return 0
        from erni.transport.identity import load_identity

        identity = load_identity(args.identity) if args.identity else None
        serve(listen, args.connect, args.scouting, threading.Event(), identity=identity, access=access,
              team=args.team, name=args.name)
    except ErniError as err:
        say(f"erni router: {err}", file=sys.stderr)
        return 1
    except ImportError:
        say("erni router: needs the eclipse-zenoh package: pip install 'erni[zenoh]'", file=sys.stderr)
        return 1
    return 0


def _acl_problem(args: argparse.Namespace, endpoints: list[str]) -> str:
    """What is wrong with the access-control options, in one line ('' when nothing)."""
    from erni.transport.zenoh_keys import NAME

    for option, value in (("--team", args.team), ("--name", args.name)):
        if value is not None and not NAME.match(value):
            return f"{option}: expected letters, digits, '_', '.', '-', got {value!r}"
    if args.print_acl and not args.acl:
        return "--print-acl needs --acl KEYS_DIR"
    if not 0 <= args.ros2_domain <= 232:
        return f"--ros2-domain: expected a ROS_DOMAIN_ID in 0-232, got {args.ros2_domain}"
    if not args.acl:
        return ""
    if not args.team or not NAME.match(args.team):
        return f"--acl needs --team TEAM, the agents' zenoh.team (letters, digits, '_', '.', '-'), got {args.team!r}"
    if args.print_acl:
        return ""
    if not args.identity or any(not e.startswith("tls/") for e in endpoints):
        return ("--acl needs --identity FILE and tls/ endpoints only: the router tells agents apart by the "
                "certificates of their TLS links")
    return ""


def serve(listen: list[str], connect: list[str], scouting: bool, stop: threading.Event,
          out: TextIO | None = None, identity: Identity | None = None, access: dict[str, Any] | None = None,
          team: str | None = None, name: str | None = None) -> None:
    """Run the router until `stop` is set (or Ctrl-C), telling `out` (stdout) when routers link or part."""
    from erni.transport.zenoh_wire import open_router

    out = out or sys.stdout
    session = open_router(listen, connect=connect, scouting=scouting, identity=identity, access=access,
                          team=team, name=name)
    try:
        say(f"erni router {session.zid()}: listening on {' '.join(listen)}"
              + (f", linked to {' '.join(connect)}" if connect else "")
              + (f"; access control for {len({n for s in access['subjects'] for n in s['cert_common_names']})} "
                 "certificate name(s)" if access else ""),
              file=out, flush=True)
        routers: set[str] = set()
        while not stop.wait(1.0):
            now = {str(z) for z in session.info.routers_zid()}
            for zid in sorted(now - routers):
                say(f"{time.strftime('%H:%M:%S')} router {zid} linked", file=out, flush=True)
            for zid in sorted(routers - now):
                say(f"{time.strftime('%H:%M:%S')} router {zid} parted", file=out, flush=True)
            routers = now
    except KeyboardInterrupt:
        pass
    finally:
        session.close()  # type: ignore[no-untyped-call]  # untyped in Zenoh's stubs
