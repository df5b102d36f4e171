"""A Zenoh router's access control for a team on `wire = "zenoh"`: each agent speaks only as itself.

A second layer under ERNI's own checks. ERNI's sessions already make a frame under another
agent's name worthless (it does not authenticate), but without this layer any holder of a team
certificate may put or query under any key: claim to be another agent in a key, fill another
agent's inbox with junk, declare a token in its name or listen to frames meant for others. With
it, the router (over `tls/` links, which give it each agent's certificate) lets the agent whose
certificate's common name is N

- put and query only as N: `erni/<team>/*/d/N`, `erni/<team>/*/r/N`;
- subscribe, answer queries and reply only for its own inbox: `erni/<team>/N/d/*`, `erni/<team>/N/r/*`;
- hold a liveliness token only as N (`erni/<team>/N/alive/**`), and see every agent's tokens;

and receive only what is addressed to it. Everything else is denied (`default_permission`).
Which agents: the names of the certificates issued (`erni keys list DIR`), or given.

Given the certificates' roles, it admits ROS 2 (rmw_zenoh) traffic of one domain by role too: data on
`<domain>/<topic>/<type>/<hash>`, discovery tokens under `@ros2_lv/<domain>/...` (`erni/ros2_rmw.py`):

- `control` (the control node runs the ros2 plugin): everything in the domain, as node and client;
- a role that may watch (`policy.WATCHERS`): subscribe to every topic and to the tokens, and hold
  tokens of nodes and subscriptions (`NN`, `MS`) only;
- a role that may also move a robot (`policy.check_task` of a velocity task): publish `cmd_vel` and
  `goal_pose` and call the services (`stop`, NavigateToPose's), with tokens of publishers and
  service clients (`MP`, `SC`);
- another site's router (role `router`) carries the domain's traffic as it carries the team's;
- any other role (`robot`, a role of no rights) nothing of ROS 2; a client without a certificate of
  the team's authority does not get a TLS link at all.

Zenoh tells the ros2 plugin nothing of who published a command: the plugin posts it as a task of
its own agent (`control`), which the robot's role policy checks as any task. What this layer adds
is that only a certificate of a role allowed to task gets a command to the plugin at all.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

from erni.blackboard.errors import ConfigError
from erni.transport.zenoh_keys import ALIVE, DATAGRAM, NAME, RELIABLE, Keys

ROS2_NODE_ROLE = "control"
"""The role of the agent whose ros2 plugin the access control lets publish and serve ROS 2 topics."""

ALL = ["put", "delete", "query", "reply", "declare_subscriber", "declare_queryable",
       "liveliness_token", "declare_liveliness_subscriber", "liveliness_query"]


def access_control(team: str, names: list[str], routers: list[str] | None = None, *,
                   roles: Mapping[str, str] | None = None, ros2_domain: int | None = 0) -> dict[str, Any]:
    """The `access_control` section of a router's Zenoh configuration for agents `names` of `team`,
    and other routers (`routers`: their certificates' names) that may carry anything of the team
    (ConfigError for a name that is no agent's). With `roles` (a certificate name -> its role) the
    ROS 2 traffic of domain `ros2_domain` (None: none) is admitted by role (`ros2_rules`)."""
    root = Keys(team).root
    rules: list[dict[str, Any]] = []
    subjects: list[dict[str, Any]] = []
    policies: list[dict[str, Any]] = []
    for name in sorted(set(names)):
        if not NAME.match(name):
            raise ConfigError(f"agent name {name[:80]!r}: expected letters, digits, '_', '.', '-'")
        mine = f"{root}/{name}"
        own_rules = [
            ("sends", "ingress", ["put"], [f"{root}/*/{DATAGRAM}/{name}"]),
            ("asks", "ingress", ["query"], [f"{root}/*/{RELIABLE}/{name}"]),
            ("listens", "ingress", ["declare_subscriber", "declare_queryable", "reply"],
             [f"{mine}/{DATAGRAM}/*", f"{mine}/{RELIABLE}/*"]),
            ("is alive", "ingress", ["liveliness_token"], [f"{mine}/{ALIVE}/**"]),
            ("watches", "ingress", ["declare_liveliness_subscriber", "liveliness_query"], [f"{root}/*/{ALIVE}/**"]),
            ("receives", "egress", ["put", "query"], [f"{mine}/{DATAGRAM}/*", f"{mine}/{RELIABLE}/*"]),
            ("is answered", "egress", ["reply"], [f"{root}/*/{RELIABLE}/{name}"]),
            ("sees who is alive", "egress", ["liveliness_token", "declare_liveliness_subscriber",
                                              "liveliness_query"], [f"{root}/*/{ALIVE}/**"]),
            ("is reached", "egress", ["declare_subscriber", "declare_queryable"],
             [f"{root}/*/{DATAGRAM}/*", f"{root}/*/{RELIABLE}/*"]),
        ]
        ids = []
        for what, flow, messages, keys in own_rules:
            rule_id = f"{name} {what}"
            ids.append(rule_id)
            rules.append({"id": rule_id, "permission": "allow", "flows": [flow], "messages": messages,
                          "key_exprs": keys})
        subjects.append({"id": name, "cert_common_names": [name]})
        policies.append({"id": f"{name} speaks as itself", "rules": ids, "subjects": [name]})
    if routers:
        for name in routers:
            if not NAME.match(name):
                raise ConfigError(f"router name {name[:80]!r}: expected letters, digits, '_', '.', '-'")
        carried = [f"{root}/**"]
        if roles is not None and ros2_domain is not None:  # and ROS 2 between the sites
            carried += [f"{ros2_domain}/**", f"@ros2_lv/{ros2_domain}/**"]
        rules.append({"id": "routers carry the team", "permission": "allow", "flows": ["ingress", "egress"],
                      "messages": ALL, "key_exprs": carried})
        subjects.append({"id": "routers", "cert_common_names": sorted(set(routers))})
        policies.append({"id": "routers carry the team", "rules": ["routers carry the team"], "subjects": ["routers"]})
    if roles is not None and ros2_domain is not None:
        more = ros2_rules(ros2_domain, roles)
        rules += more["rules"]
        subjects += more["subjects"]
        policies += more["policies"]
    return {"enabled": True, "default_permission": "deny", "rules": rules, "subjects": subjects,
            "policies": policies}


def ros2_rules(domain: int, roles: Mapping[str, str]) -> dict[str, list[dict[str, Any]]]:
    """The rules, subjects and policies that admit ROS 2 traffic of `domain` by the roles of the
    certificates `roles` names (see the module's description)."""
    from erni.transport.policy import WATCHERS, Refusal, check_task

    if not 0 <= domain <= 232:
        raise ConfigError(f"ROS 2 domain {domain}: expected 0-232 (ROS_DOMAIN_ID)")

    def may_drive(role: str) -> bool:
        try:
            check_task(role, "robot", "BotMotion", "velocity")
        except Refusal:
            return False
        return True

    data, tokens = f"{domain}/**", f"@ros2_lv/{domain}/**"

    def kinds(*names: str) -> list[str]:  # tokens of these kinds of entity: @ros2_lv/<d>/<zid>/<node>/<id>/<kind>/...
        return [f"@ros2_lv/{domain}/*/*/*/{kind}/**" for kind in names]

    commands = [f"{domain}/**/cmd_vel/**", f"{domain}/**/goal_pose/**"]
    services = [f"{domain}/**/stop/**", f"{domain}/**/_action/send_goal/**", f"{domain}/**/_action/get_result/**",
                f"{domain}/**/_action/cancel_goal/**"]
    watch = [
        ("ingress", ["declare_subscriber"], [data]),
        ("ingress", ["declare_liveliness_subscriber", "liveliness_query"], [tokens]),
        ("ingress", ["liveliness_token"], kinds("NN", "MS")),
        ("egress", ["put"], [data]),
        ("egress", ["liveliness_token", "declare_liveliness_subscriber", "liveliness_query", "reply"], [tokens]),
    ]
    drive = [
        ("ingress", ["put"], commands),
        ("ingress", ["query"], services),
        ("ingress", ["liveliness_token"], kinds("MP", "SC")),
        ("egress", ["declare_subscriber"], commands),
        ("egress", ["declare_queryable", "reply"], services),
    ]
    groups = [
        ("ROS 2 node", [("ingress", ALL, [data, tokens]), ("egress", ALL, [data, tokens])],
         {n for n, r in roles.items() if r == ROS2_NODE_ROLE}),
        ("ROS 2 watchers", watch, {n for n, r in roles.items() if r in WATCHERS and r != ROS2_NODE_ROLE}),
        ("ROS 2 drivers", drive,
         {n for n, r in roles.items() if r in WATCHERS and may_drive(r) and r != ROS2_NODE_ROLE}),
    ]
    out: dict[str, list[dict[str, Any]]] = {"rules": [], "subjects": [], "policies": []}
    for group, grants, members in groups:
        for name in members:
            if not NAME.match(name):
                raise ConfigError(f"agent name {name[:80]!r}: expected letters, digits, '_', '.', '-'")
        if not members:
            continue
        ids = []
        for i, (flow, messages, keys) in enumerate(grants):
            ids.append(f"{group} {i + 1}")
            out["rules"].append({"id": ids[-1], "permission": "allow", "flows": [flow], "messages": messages,
                                 "key_exprs": keys})
        out["subjects"].append({"id": group, "cert_common_names": sorted(members)})
        out["policies"].append({"id": group, "rules": ids, "subjects": [group]})
    return out


def team_names(keys: str) -> tuple[list[str], list[str]]:
    """The agents and the routers (role `router`) of the team authority in directory `keys` that
    hold a certificate not revoked (IdentityError naming the directory when it holds no authority)."""
    agents, routers = team_roles(keys)
    return sorted(agents), routers


def team_roles(keys: str) -> tuple[dict[str, str], list[str]]:
    """`team_names`, each agent with the role of its certificates not revoked ('' when they name
    different roles: the router tells certificates apart by their names only)."""
    from erni.transport.identity import Authority

    authority = Authority(keys)
    revoked = {entry.serial_number for entry in authority.crl()}
    agents: dict[str, str] = {}
    routers: set[str] = set()
    for name, role, serial in authority.issued():
        if serial not in revoked and NAME.match(name):
            if role == "router":
                routers.add(name)
            else:
                agents[name] = role if agents.get(name, role) == role else ""
    return agents, sorted(routers)
