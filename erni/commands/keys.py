"""`erni keys`: a team authority and the identities of its agents (init, issue, revoke, list, show)."""

from __future__ import annotations

import argparse
import sys
from typing import Any

from erni.commands._text import say
from erni.transport.identity import AUTHORITY_CERT, REVOKED, Authority, IdentityError, load_identity

ROLES = """\
  robot    performs tasks; tasks another robot only for a mission (Deploy relay, spread,
           widep, patrol); publishes only its own Pose, NetInfo, Peer state and Territory,
           and results only of tasks it performs; may not watch the team
  control  the control node: tasks any agent, relays the tasks of cli and control clients
           (their originator kept), cancels any task, watches the team, publishes its own
           Pose and NetInfo
  cli      a command-line client (erni task, watch, peers): tasks any agent, directly or
           through the control node, cancels any task, watches the team; never a peer
  observer may watch, never task or cancel: a ROS 2 viewer's certificate (its topics through
           erni router --acl); ERNI's command-line tools take a cli certificate
A task is cancelled by the agent it came from or by control and cli (the one that gave it
is told who cancelled it)."""


def register(sub: Any) -> None:
    """Add the `keys` sub-command and its actions."""
    p = sub.add_parser("keys", help="make a team authority, issue and revoke agent identities",
                       description="Per-agent identities for the transport: a team authority (an Ed25519 "
                       "CA kept in DIR) signs one certificate per agent; a revocation list (DIR/revoked.crl) "
                       "withdraws them. Give each agent its NAME.pem (transport setting `identity`) and the "
                       "control node DIR/revoked.crl (setting `revocations`); agents pass newer lists on.")
    actions = p.add_subparsers(dest="action", metavar="ACTION", required=True)
    a = actions.add_parser("init", help="create a team authority in DIR")
    a.add_argument("dir")
    a.add_argument("--team", default="ERNI team", help="the team's name in certificates")
    a = actions.add_parser("issue", help="issue an identity for agent NAME (DIR/NAME.pem)",
                           formatter_class=argparse.RawDescriptionHelpFormatter,
                           description="What each role may do (transport/policy.py; the receiving agent "
                           "refuses everything else):\n" + ROLES)
    a.add_argument("dir")
    a.add_argument("name")
    a.add_argument("--role", default="robot", help="the agent's role, which says what it may do (see above): "
                   "robot, control, cli or observer (may only watch); another word is a role with no rights but its own status "
                   "(default robot)")
    a.add_argument("--out", help="where to write the bundle (default DIR/NAME.pem)")
    a = actions.add_parser("revoke", help="revoke every identity issued to NAME (or one serial, in hex)")
    a.add_argument("dir")
    a.add_argument("name")
    a = actions.add_parser("list", help="list the identities DIR issued, and which are revoked")
    a.add_argument("dir")
    a = actions.add_parser("show", help="say whose an identity bundle is (no secret printed)")
    a.add_argument("file")
    a.add_argument("--revocations", help="a revocation list to check it against")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    """Do the action; one line per result, one line per error (exit 2)."""
    try:
        if args.action == "init":
            authority = Authority.create(args.dir, args.team)
            say(f"team authority {args.team!r} in {authority.dir} ({AUTHORITY_CERT}, {REVOKED}); keep "
                  f"{authority.dir / 'authority.key'} off the robots")
        elif args.action == "issue":
            path = Authority(args.dir).issue(args.name, args.role, args.out)
            identity = load_identity(path)
            say(f"{path}: {identity.name} ({identity.role}), serial {identity.serial:x}; set "
                  f"identity = \"{path}\" in its transport settings")
        elif args.action == "revoke":
            authority = Authority(args.dir)
            serials = authority.revoke(args.name)
            number = authority.crl_number()
            if serials:
                say(f"revoked {len(serials)} certificate(s) of {args.name}: "
                      f"{', '.join(f'{s:x}' for s in serials)}; {authority.dir / REVOKED} is now list {number}: "
                      "give it to the control node (the agents pass it on)")
            else:
                say(f"{args.name}: already revoked (list {number})")
        elif args.action == "list":
            authority = Authority(args.dir)
            revoked = {r.serial_number for r in authority.crl()}
            for name, role, serial in authority.issued():
                say(f"{name:<16} {role:<8} {serial:x}{'  REVOKED' if serial in revoked else ''}")
        else:
            identity = load_identity(args.file, args.revocations)
            say(f"{args.file}: {identity.name} ({identity.role}), serial {identity.serial:x}, team authority "
                  f"{identity.trust.fingerprint}" + (f", revocation list {identity.trust.crl_number}"
                                                      if args.revocations else ""))
    except IdentityError as err:
        say(f"erni keys: {err}", file=sys.stderr)
        return 2
    return 0
