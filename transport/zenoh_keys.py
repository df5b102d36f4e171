"""What the Zenoh wire is configured with and where its frames go: settings, key expressions, addresses.

Kept apart from `zenoh_wire.py` so that reading a configuration never imports Zenoh itself: an
agent on ERNI's own wire loads nothing of it.

Every agent of a team receives under its own key expression, `erni/<team>/<name>`:

- `erni/<team>/<receiver>/d/<sender>`: datagrams (statuses, handshakes and their answers, hints,
  in-session beacons), best effort, newest wins, as ERNI's UDP;
- `erni/<team>/<receiver>/r/<sender>`: reliable messages as queries (tasks, results, cancels); the
  reply is the acknowledgement (or a hint that the session is unknown), as ERNI's TCP stream;
- `erni/<team>/<name>/alive/<role>/<instance>/<router>`: the agent's liveliness token (who is
  up, and the Zenoh id of the router it is connected through, `-` for none).

The sender's name in a key is only where to answer: every frame is still authenticated by its
session, so a key that lies gains nothing but a wasted answer. An agent's address on this wire
is `("zenoh/<name>", 0)`, shown as `zenoh/<name>:0`.
"""

from __future__ import annotations

import re
from typing import Any, Literal

from pydantic import ConfigDict, Field, field_validator, model_validator

from erni.blackboard import text
from erni.blackboard.errors import ConfigError
from erni.blackboard.objects import Model

Address = tuple[str, int]

ADDRESS_PREFIX = "zenoh/"
"""The host part of an agent's address on the Zenoh wire: `zenoh/<name>` (port 0)."""

NAME = text.NAME
"""An agent's name (`blackboard/text.py`) and a team's: each one chunk of a key."""

ENDPOINT = re.compile(r"^(tcp|udp|tls|quic|ws)/(\[[0-9A-Fa-f:.]+\]|[A-Za-z0-9_.-]+):([0-9]{1,5})(#.*)?$")
"""A Zenoh locator this wire accepts: `PROTOCOL/HOST:PORT`, e.g. `tcp/192.0.2.1:7447`."""

DATAGRAM, RELIABLE, ALIVE = "d", "r", "alive"


class ZenohSettings(Model):
    """How an agent joins a team over Zenoh (`[plugin.settings.zenoh]` of the transport)."""

    model_config = ConfigDict(extra="forbid")

    team: str = Field("team", description="the team's key chunk: agents of one team share it (erni/<team>/...)")
    mode: Literal["peer", "client"] = Field("peer", description="peer: agents meet each other directly (on a "
                                            "LAN by multicast scouting); client: only through the routers "
                                            "in `connect`")
    connect: list[str] = Field(default_factory=list, description="routers or peers to connect to, "
                               "PROTOCOL/HOST:PORT (tcp/192.0.2.1:7447)")
    listen: list[str] = Field(default_factory=list, description="endpoints a peer listens on for other "
                              "peers (default: Zenoh's, any free TCP port)")
    scouting: bool = Field(True, description="peer mode: find peers on the LAN by UDP multicast scouting")

    @field_validator("team")
    @classmethod
    def _team(cls, value: str) -> str:
        if not NAME.match(value):
            raise ValueError(f"team {value[:80]!r}: expected letters, digits, '_', '.', '-' (one key chunk)")
        return value

    @field_validator("connect", "listen")
    @classmethod
    def _endpoints(cls, values: list[str]) -> list[str]:
        return check_endpoints(values)

    @model_validator(mode="after")
    def _check(self) -> ZenohSettings:
        if self.mode == "client" and not self.connect:
            raise ValueError("mode = \"client\" needs connect = [\"tcp/ROUTER:7447\"]: a client reaches its "
                             "team only through a router")
        if self.mode == "client" and self.listen:
            raise ValueError("listen is for mode = \"peer\": a client listens on nothing")
        return self

    def config(self) -> dict[str, Any]:
        """The Zenoh configuration of these settings, as `zenoh.Config` keys and JSON values."""
        conf: dict[str, Any] = {"mode": self.mode, "scouting/multicast/enabled": self.mode == "peer" and self.scouting}
        if self.connect:
            conf["connect/endpoints"] = list(self.connect)
        if self.listen:
            conf["listen/endpoints"] = list(self.listen)
        return conf


def check_endpoint(value: str) -> str:
    """Return `value` if it is a locator this wire accepts; raise ConfigError (a ValueError) naming the
    expected form."""
    match = ENDPOINT.match(value.strip())
    if match is None or not 0 < int(match.group(3)) <= 65535:
        raise ConfigError(f"zenoh endpoint {value[:80]!r}: expected PROTOCOL/HOST:PORT with PROTOCOL one of "
                         "tcp, udp, tls, quic, ws and PORT in 1..65535, e.g. tcp/192.0.2.1:7447")
    return value


def check_endpoints(values: list[str]) -> list[str]:
    """`check_endpoint` of each (a settings validator of `connect` and `listen` lists)."""
    for value in values:
        check_endpoint(value)
    return values


def address_of(name: str) -> Address:
    """The address of agent `name` on the Zenoh wire."""
    return f"{ADDRESS_PREFIX}{name}", 0


def name_at(addr: Address) -> str | None:
    """The agent a Zenoh address names, or None for an address of another wire (or not a name)."""
    host = addr[0]
    if not host.startswith(ADDRESS_PREFIX):
        return None
    name = host[len(ADDRESS_PREFIX):]
    return name if NAME.match(name) else None


def wire_of(address: str) -> str:
    """The wire an address as a peer shows it (`HOST:PORT`) is on: 'zenoh' or 'udp'."""
    return "zenoh" if address.startswith(ADDRESS_PREFIX) else "udp" if address else ""


class Keys:
    """The key expressions of one team: to an agent, from an agent, and of its liveliness."""

    def __init__(self, team: str):
        self.root = f"erni/{team}"

    def inbox(self, receiver: str, lane: str, sender: str) -> str:
        """Where `sender` puts (lane `d`) or queries (lane `r`) frames for `receiver`."""
        return f"{self.root}/{receiver}/{lane}/{sender}"

    def listen(self, receiver: str, lane: str) -> str:
        """What `receiver` subscribes to (lane `d`) or answers (lane `r`)."""
        return f"{self.root}/{receiver}/{lane}/*"

    def token(self, name: str, role: str, inst: str, router: str = "") -> str:
        """The liveliness token of one instance of agent `name`, connected through `router` ('': none)."""
        return f"{self.root}/{name}/{ALIVE}/{role if NAME.match(role) else '-'}/{inst}/{router or '-'}"

    def tokens(self) -> str:
        """Every liveliness token of the team."""
        return f"{self.root}/*/{ALIVE}/*/*/*"

    def sender_of(self, key: str) -> str | None:
        """The sender a frame's key names (its last chunk), or None when it names no agent."""
        sender = key.rpartition("/")[2]
        return sender if NAME.match(sender) else None

    def parse_token(self, key: str) -> tuple[str, str, str, str] | None:
        """(name, role, instance, router) of a liveliness token's key, or None for another key."""
        parts = key.split("/")
        if len(parts) != 7 or "/".join(parts[:2]) != self.root or parts[3] != ALIVE or not NAME.match(parts[2]):
            return None
        role = "" if parts[4] == "-" else parts[4]
        return parts[2], role, parts[5], "" if parts[6] == "-" else parts[6]
