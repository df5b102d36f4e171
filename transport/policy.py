"""Who may ask what of whom: the authorization policy, one rule per message kind, default deny.

An authenticated frame says who sent it (the name and role of its certificate); this module says
what that sender may do. The receiving agent asks it about every message before anything reaches
its blackboard (`TransportPlugin._handle`); a refusal is a `Refusal` naming the rule, logged once
per sender, kind and rule in a while, and counted. Roles come from the certificates `erni keys
issue --role` writes (in team-key and insecure mode from what the sender states).

| kind | body | who may send it | rule |
|---|---|---|---|
| `task.add` | `Task` | `control` and `cli` to any agent; `robot` to `robot` only the mission's tasks (`Deploy` relay, spread, widep, patrol); nobody else | `task` |
| `task.relay` | `Relayed` | a role that relays for the originator's role (`control` for `cli` and `control`); the originator must be allowed the task itself | `relay` |
| `task.cancel` | `Cancel` | the agent the task came from (its requester), and `control` and `cli`, which operate the team (the requester then gets `cancelled by NAME`) | `requester` |
| `task.rescind` | `TaskRescind` | the agent the task came from | `requester` |
| `task.result` | `ResultUpdate` | the agent the task was sent to (its performer) | `performer` |
| `task.query` | `TaskQuery` | `control` and `cli`; else the task's requester or performer | `query` |
| `status`, `status.fresh`, `status.remove` | the object, `Fresh`, `StatusRemoved` | an agent about its own objects only: a type of `STATUS`, from a role it names, the object naming its sender (and, where the type has one, under its uid); a uid is held by one sender until it removes it | `status` |
| `watch.request`, `peers.request` | `WatchRequest`, any | `control`, `cli` and `observer` (a robot does not watch the team) | `watch` |
| `beacon`, `status.resend` | `Beacon`, `StatusResend` | any agent of the team | — |
| anything else | | nobody | `kind` |

A message whose body is not its kind's type is not acted on (`TransportPlugin._kind_table`); the
answers an agent sends are `task.result` (`ResultUpdate`) and `task.unknown` (`TaskUnknown`).

Stamps are never compared across senders: a status orders only against its own sender's earlier
ones (the uid is held by that sender), a result only against its performer's.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

from erni.blackboard.errors import ErniError

OPERATORS = frozenset({"control", "cli"})
"""Roles that operate the team: they task any agent, cancel any agent's task, watch."""

ANY = "*"
"""In a rule: any verb, any preposition, or any role but `cli`."""

TASKS: Mapping[tuple[str, str], frozenset[tuple[str, str]]] = {
    # (sender's role, receiver's role): the (verb, preposition) pairs it may give
    ("control", "robot"): frozenset({(ANY, ANY)}),
    ("control", "control"): frozenset({(ANY, ANY)}),
    ("cli", "robot"): frozenset({(ANY, ANY)}),
    ("cli", "control"): frozenset({(ANY, ANY)}),
    # robots task each other only for a mission: placing relays, spreading, a patrol that takes
    # over a territory; never motion, never a cancel of the operator's tasks
    ("robot", "robot"): frozenset({("Deploy", "relay"), ("Deploy", "spread"), ("Deploy", "widep"),
                                   ("Deploy", "patrol")}),
}

RELAYS: Mapping[str, frozenset[str]] = {
    # a relay's role: the roles it may forward tasks for (the receiver checks both hops)
    "control": frozenset({"cli", "control"}),
}

WATCHERS = OPERATORS | {"observer"}
"""Roles that may watch the blackboard (`erni watch`) and list the peers (`erni peers`): the
operators, and `observer`, which may watch and never task (a ROS 2 viewer's certificate behind
`erni router --acl`; ERNI's command-line client always runs as `cli`)."""


@dataclass(frozen=True)
class StatusRule:
    """Who may publish objects of a type as status: `roles`, each only its own object (the field
    `owner` names the sender), under the uid `uid` (with `{owner}` filled in) if the type has one."""

    roles: frozenset[str]
    owner: str
    uid: str = ""


STATUS: dict[str, StatusRule] = {
    "Pose": StatusRule(frozenset({"robot", "control"}), "robot", "pose:{owner}"),
    "NetInfo": StatusRule(frozenset({"robot", "control"}), "node"),
    "Peer": StatusRule(frozenset({"robot", "control"}), "name", "peer:{owner}"),
    "Territory": StatusRule(frozenset({"robot"}), "robot", "territory:{owner}"),  # patrol heartbeats
    # the round-trip experiment (erni experiment roundtrip): readings out, acknowledgements back
    "SensorReading": StatusRule(frozenset({"robot"}), "robot", "reading:{owner}"),
    "SensorAck": StatusRule(frozenset({ANY}), "consumer", "ack:{owner}"),
}
"""Shared object types, by type name. A registered type not listed here travels as status only
as an agent's own object naming it in a field `robot` (`DEFAULT_OWNER`); a task, a receipt or
anything without an owner never does."""

DEFAULT_OWNER = "robot"


def allow_status(type_name: str, roles: set[str] | frozenset[str], owner: str, uid: str = "") -> None:
    """Let agents of `roles` publish their own objects of `type_name` (a plugin's shared type)."""
    STATUS[type_name] = StatusRule(frozenset(roles), owner, uid)


class Refusal(ErniError):
    """A message its sender may not send: `rule` names the rule, the message says why."""

    def __init__(self, rule: str, why: str):
        super().__init__(why)
        self.rule = rule


def _role_in(role: str, roles: frozenset[str]) -> bool:
    return role in roles or (ANY in roles and role != "cli")


def check_task(role: str, receiver_role: str, verb: str, preposition: str) -> None:
    """Refuse a task of (`verb`, `preposition`) from an agent of `role` to one of `receiver_role`."""
    allowed = TASKS.get((role, receiver_role or "robot"), frozenset())
    if (verb, preposition) in allowed or (verb, ANY) in allowed or (ANY, ANY) in allowed:
        return
    if not allowed:
        raise Refusal("task", f"role {role or '(none)'} may not task a {receiver_role or 'robot'}")
    raise Refusal("task", f"role {role} may give a {receiver_role or 'robot'} only "
                  f"{', '.join(sorted(f'{v} {p}' for v, p in allowed))}, not {verb} {preposition}")


def check_relay(relay_role: str, origin_role: str) -> None:
    """Refuse a task forwarded by an agent of `relay_role` for an originator of `origin_role`."""
    if origin_role not in RELAYS.get(relay_role, frozenset()):
        raise Refusal("relay", f"role {relay_role or '(none)'} may not relay tasks of role {origin_role or '(none)'}")


def check_status(sender: str, role: str, obj: Any) -> None:
    """Refuse a status object that is not `sender`'s own object of a shared type its role publishes."""
    name = type(obj).__name__
    rule = STATUS.get(name)
    if rule is None:
        if DEFAULT_OWNER not in type(obj).model_fields or name in ("Task", "Received"):
            raise Refusal("status", f"a {name} is no shared state")
        rule = StatusRule(frozenset({ANY}), DEFAULT_OWNER)
    if not _role_in(role, rule.roles):
        raise Refusal("status", f"role {role or '(none)'} does not publish {name}")
    owner = getattr(obj, rule.owner, None)
    if owner != sender:
        raise Refusal("status", f"{name} {str(obj.uid)[:64]} is {str(owner)[:64]}'s, not {sender}'s")
    if rule.uid and obj.uid != rule.uid.format(owner=sender):
        raise Refusal("status", f"{name} of {sender} under uid {str(obj.uid)[:64]}, not "
                      f"{rule.uid.format(owner=sender)}")


def check_watch(role: str) -> None:
    """Refuse a watch or a peer list to an agent of `role`."""
    if role not in WATCHERS:
        raise Refusal("watch", f"role {role or '(none)'} may not watch the team")


def table() -> str:
    """The task rules as a Markdown table (the site's role policy page, `erni keys issue --help`)."""
    rows = ["| sender | receiver | tasks |", "|---|---|---|"]
    for (sender, receiver), allowed in TASKS.items():
        what = "any" if (ANY, ANY) in allowed else ", ".join(sorted(f"{v} {p}" for v, p in allowed))
        rows.append(f"| {sender} | {receiver} | {what} |")
    return "\n".join(rows)
