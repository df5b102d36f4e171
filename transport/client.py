"""A short-lived client of a running team (the `erni task`, `erni peers`, `erni watch` commands).

The client is an endpoint of its own in role `cli` (agents never list it as a peer). It proves
who it is with an identity of role `cli` (`--identity FILE` or `ERNI_IDENTITY`, made by
`erni keys issue DIR NAME --role cli`), or with the shared team key (`ERNI_TEAM_KEY`, named
`cli-<pid>` then). It reaches the team through one agent: the one given with `--via HOST:PORT`,
or, without it, one found by listening for beacons on the discovery port. On a team that runs
over Zenoh (`--zenoh ENDPOINT`) it is a Zenoh client of that router or peer, `--via` names the
agent, and agents are found by their liveliness tokens instead of beacons.
"""

from __future__ import annotations

import logging
import os
import queue
import socket
import sys
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING, Any

from erni.blackboard.clock import SYSTEM
from erni.blackboard.errors import ErniError
from erni.blackboard.messages import Beacon, PeerList, ResultUpdate
from erni.transport.endpoint import CLIENT_ROLE, Address, Endpoint, team_key
from erni.transport.identity import load_identity
from erni.transport.wire import Message

if TYPE_CHECKING:
    from erni.transport.zenoh_keys import ZenohSettings

IDENTITY_ENV = "ERNI_IDENTITY"


INBOX_LIMIT = 10_000  # messages a client holds for its reader (about 25 s of a 40-robot watch)


class ClientError(ErniError):
    """The team could not be reached or answered unexpectedly."""


class PeerListParts:
    """Puts a directory sent in parts (`peers.reply`: one part per half frame) back together."""

    KEEP = 16  # answers being put together at once (a client asks again and again: the oldest go)

    def __init__(self) -> None:
        self._parts: dict[tuple[str, str, int], dict[int, PeerList]] = {}

    def add(self, body: PeerList) -> PeerList | None:
        """Take one part; return the whole directory once every part of its answer arrived."""
        if body.parts <= 1:
            return body
        key = (body.agent, body.request, body.parts)
        got = self._parts.pop(key, {})
        got[body.part] = body
        if len(got) < body.parts:
            self._parts[key] = got  # the newest last
            while len(self._parts) > self.KEEP:
                del self._parts[next(iter(self._parts))]
            return None
        whole = [got[i] for i in range(body.parts)]
        return PeerList(agent=body.agent, request=body.request, peers=[p for part in whole for p in part.peers],
                        beacons={k: v for part in whole for k, v in part.beacons.items()},
                        down_after={k: v for part in whole for k, v in part.down_after.items()})


class Client:
    """Send requests to one agent of the team and receive what it sends back.

    A final result of a task is delivered once, however many copies arrive.
    """

    def __init__(self, via: Address | None, *, discovery_port: int = 47000, identity: str | Path | None = None,
                 key_env: str = "ERNI_TEAM_KEY", insecure: bool = False, discover_seconds: float = 3.0,
                 zenoh: ZenohSettings | None = None, clock: Callable[[], float] = SYSTEM):
        self.clock = clock
        path = identity or os.environ.get(IDENTITY_ENV) or None
        ident = load_identity(path) if path and not insecure else None
        key = None if ident is not None or insecure else team_key(None, key_env)
        if ident is None and key is None and not insecure:
            print(f"erni: neither {IDENTITY_ENV} nor {key_env} is set: sending unauthenticated frames "
                  "(only agents with insecure = true will listen)", file=sys.stderr)
            insecure = True
        self.via = via
        self.discovery_port = discovery_port
        self.discover_seconds = discover_seconds
        # bounded: a program that sent tasks and stopped reading (a benchmark, a script) would
        # otherwise keep every result update its tasks bring, forever; the oldest go first
        self.inbox: queue.Queue[Message] = queue.Queue(INBOX_LIMIT)
        self.overflowed = 0  # messages dropped from a full inbox
        self.failed: queue.Queue[str] = queue.Queue()
        self.delivered: set[str] = set()
        self.finals: set[str] = set()
        self.duplicates = 0
        name = ident.name if ident is not None else f"cli-{os.getpid()}"
        self.zenoh = zenoh
        if zenoh is not None:
            try:
                from erni.transport.zenoh_wire import ZenohEndpoint
            except ImportError:
                raise ClientError("--zenoh needs the eclipse-zenoh package: pip install 'erni[zenoh]'") from None
            self.endpoint: Endpoint = ZenohEndpoint(name, zenoh_settings=zenoh, identity=ident, key=key,
                                                    insecure=insecure, senders=1, role=CLIENT_ROLE)
        else:
            local = _local_ip_towards(via[0]) if via else "127.0.0.1"
            self.endpoint = Endpoint(name, listen=(local, 0), identity=ident, key=key, insecure=insecure,
                                     senders=1, discovery_port=None if via else discovery_port, role=CLIENT_ROLE)
        self.endpoint.log.propagate = False  # a client prints its own errors
        self.endpoint.log.addHandler(logging.NullHandler())
        self.endpoint.on_message = self._received
        self.endpoint.on_undeliverable = lambda addr, mid, kind, body: self.failed.put(mid)
        self.endpoint.on_delivered = lambda addr, mid: self.delivered.add(mid)
        self.refused = ""  # why an agent refused this client's certificate (another authority's, revoked)
        self.endpoint.on_refused = self._refused
        self.beacons: dict[str, tuple[Address, Beacon]] = {}

    def _refused(self, addr: Address, reason: str) -> None:
        self.refused = reason

    def check_refused(self) -> None:
        """Raise ClientError at once if the agent refused this client's certificate, naming why."""
        if self.refused:
            hint = ""
            if "authority" in self.refused:
                hint = (f" (an identity of another team or an earlier run? {IDENTITY_ENV} or --identity must "
                        "name one issued by this team's authority, e.g. RUN/keys/cli.pem of this `erni sim`)")
            raise ClientError(f"{self.refused}{hint}")

    def _received(self, msg: Message) -> None:
        if msg.kind == "task.result" and isinstance(msg.body, ResultUpdate) and msg.body.result.state.done:
            if msg.body.uid in self.finals:
                self.duplicates += 1
                return
            self.finals.add(msg.body.uid)
        while True:  # only this thread puts: after one get a put fits, unless a reader raced it
            try:
                self.inbox.put_nowait(msg)
                return
            except queue.Full:
                try:
                    self.inbox.get_nowait()
                    self.overflowed += 1
                except queue.Empty:
                    pass

    def __enter__(self) -> Client:
        self.endpoint.start()
        return self

    def __exit__(self, *exc: Any) -> None:
        self.endpoint.stop()

    def find(self, agent: str | None) -> Address:
        """Return the address to talk to: `--via`, or the agent heard in beacons (any, if None)."""
        if self.via:
            return self.via
        deadline = self.clock() + self.discover_seconds
        while self.clock() < deadline:
            try:
                msg = self.inbox.get(timeout=0.1)
            except queue.Empty:
                continue
            if msg.kind == "beacon" and isinstance(msg.body, Beacon):
                self.beacons[msg.sender] = (msg.reply, msg.body)
            if agent is None and self.beacons:
                return next(iter(self.beacons.values()))[0]
            if agent in self.beacons:
                return self.beacons[agent][0]
        heard = ", ".join(sorted(self.beacons)) or "no agent"
        if self.zenoh is not None:
            raise ClientError(f"no liveliness token of {agent or 'any agent'} of team {self.zenoh.team} through "
                              f"{' '.join(self.zenoh.connect)} within {self.discover_seconds:.0f} s (heard: {heard})")
        raise ClientError(f"no beacon from {agent or 'any agent'} on port {self.discovery_port} within "
                          f"{self.discover_seconds:.0f} s (heard: {heard}); give --via HOST:PORT")

    def send(self, addr: Address, kind: str, body: Any, reliable: bool = True) -> str:
        """Send a message; return its id."""
        return self.endpoint.send(addr, kind, body, reliable=reliable, ttl=5.0)

    def receive(self, timeout: float) -> Message | None:
        """Return the next message, or None after `timeout` seconds."""
        try:
            return self.inbox.get(timeout=timeout)
        except queue.Empty:
            return None

    def take_failed(self, msg_ids: set[str]) -> bool:
        """Take the ids of undeliverable messages reported so far; True if one of them is in `msg_ids`."""
        hit = False
        while True:
            try:
                hit = self.failed.get_nowait() in msg_ids or hit
            except queue.Empty:
                return hit

    def check_failed(self, *msg_ids: str) -> None:
        """Raise ClientError if a message with one of these ids could not be delivered, or at once if the
        agent refused this client's certificate."""
        self.check_refused()
        if self.take_failed(set(msg_ids)):
            raise ClientError("could not reach the agent: no acknowledgement within 5 s (is it running, "
                                  "and does it trust this identity?)")


def _local_ip_towards(host: str) -> str:
    """Return the local address that routes to `host` (so replies can reach us)."""
    try:
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
            s.connect((host, 9))
            return str(s.getsockname()[0])
    except OSError:
        return "127.0.0.1"
