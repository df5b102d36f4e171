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
"""

from __future__ import annotations

from typing import Any

from erni.blackboard.errors import ConfigError
from erni.transport.zenoh_keys import ALIVE, DATAGRAM, NAME, RELIABLE, Keys


def access_control(team: str, names: list[str], routers: list[str] | None = None) -> dict[str, Any]:
    """The `access_control` section of a router's Zenoh configuration for agents `names` of `team`,
    and other routers (`routers`: their certificates' names) that may carry anything of the team
    (ConfigError for a name that is no agent's)."""
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
        rules.append({"id": "routers carry the team", "permission": "allow", "flows": ["ingress", "egress"],
                      "messages": ["put", "delete", "query", "reply", "declare_subscriber", "declare_queryable",
                                   "liveliness_token", "declare_liveliness_subscriber", "liveliness_query"],
                      "key_exprs": [f"{root}/**"]})
        subjects.append({"id": "routers", "cert_common_names": sorted(set(routers))})
        policies.append({"id": "routers carry the team", "rules": ["routers carry the team"], "subjects": ["routers"]})
    return {"enabled": True, "default_permission": "deny", "rules": rules, "subjects": subjects,
            "policies": policies}


def team_names(keys: str) -> tuple[list[str], list[str]]:
    """The agents and the routers (role `router`) of the team authority in directory `keys` that
    hold a certificate not revoked (IdentityError naming the directory when it holds no authority)."""
    from erni.transport.identity import Authority

    authority = Authority(keys)
    revoked = {entry.serial_number for entry in authority.crl()}
    agents: set[str] = set()
    routers: set[str] = set()
    for name, role, serial in authority.issued():
        if serial not in revoked and NAME.match(name):
            (routers if role == "router" else agents).add(name)
    return sorted(agents), sorted(routers)
