"""Presence, a collaborator of the transport plugin: who is in the team, where, and whether they are up.

Signed beacons go to the configured broadcast/unicast addresses and to addresses learned from
MobiNet's `NetInfo` where no peer is up: they only tell that an agent may be there. While every
known peer is up and nothing new is learned, these announcements back off (doubling up to
`announce_backoff` beacon periods); a newcomer still announces every period and is answered at
once. Known peers get beacons inside their session, but only the quiet ones (nothing else sent to
them for a beacon period: any session frame tells they are alive), and at most `beacon_fanout` of
them a period: with more, each gets one less often and the beacon says how often, so its receiver
waits as many periods longer. Only session traffic (fresh by construction) marks a peer up (a
peer not up shows when its signed beacon was last heard; an agent running insecure has no
sessions, so there any beacon marks its sender up), and a peer silent for `peer_timeout` (scaled
by its announced interval, and stretched by the share of its numbered beacons that arrive:
`liveness`) is down. A beacon that says nothing new (its peer up, at the same address and epoch)
costs no run: the receive thread marks the peer heard (`repeated`), the liveness pass updates
`last_heard`. With Zenoh, a peer whose liveliness token goes is down at once (`gone`).

Its state: the directory of peers (the `Peer` objects it puts on the blackboard), a record per peer
(when heard and sent to, its beacons and silence limit), the addresses learned and the reply
address of every sender.
"""

from __future__ import annotations

import ipaddress
import math
import random
import threading
from collections.abc import Callable, Iterable
from dataclasses import dataclass
from typing import Any

from erni.blackboard import NetInfo, Peer, Plugin
from erni.blackboard.errors import ConfigError
from erni.blackboard.schemas import Beacon, PeerList
from erni.transport.bounds import SenderBounds
from erni.transport.endpoint import CLIENT_ROLE, Address, Endpoint, parse_address
from erni.transport.liveness import BeaconCount, silence_stretch
from erni.transport.settings import TransportSettings
from erni.transport.wire import Message


class Presence:
    """The team as this agent knows it: beacons out, peers heard, liveness, the directory."""

    def __init__(self, plugin: Plugin[TransportSettings], endpoint: Endpoint, bounds: SenderBounds, *,
                 degraded: Callable[[], str], count: Callable[[str], None]) -> None:
        self.plugin, self.endpoint, self.bounds = plugin, endpoint, bounds
        self.settings, self.log, self.clock, self.me = plugin.settings, plugin.log, plugin.clock, plugin.agent_name
        self.degraded, self._count = degraded, count
        self.directory = Directory()
        self.peers: dict[str, PeerRecord] = {}  # peer -> when we heard it, beaconed it, its limit and counts
        self._peer_lock = threading.Lock()  # a record made on the receive thread and in a run at once: one
        self.learned: set[str] = set()
        self.addresses: dict[str, Address] = {}  # reply address of every sender, clients included
        self._next_beacon = 0.0
        self._next_silences = 0.0  # when the peers' silences are looked at next (monotonic)
        self._announce_every = self.settings.beacon_period  # backs off while the directory stands
        self._announce_seen: tuple[int, int] = (-1, -1)  # peers and learned addresses at the last announcement
        self._beacon_said: Beacon | None = None  # what the last in-session beacons said (but the interval)

    def add_static(self) -> None:
        """The configured peers (`peers`, NAME@HOST:PORT) into the directory and onto the blackboard."""
        for spec in self.settings.peers:
            name, _, addr = spec.partition("@")
            host, port = parse_address(addr)
            self.directory[name] = Peer(uid=f"peer:{name}", name=name, address=f"{host}:{port}")
            self.plugin.add(self.directory[name])

    # -- where each peer is ----------------------------------------------------------------

    def address_of(self, name: str) -> Address | None:
        """The address of peer `name` in the directory (None: not known there, or no address yet)."""
        peer = self.directory.get(name)
        return parse_address(peer.address) if peer is not None and peer.address else None

    def role_of(self, name: str) -> str:
        """The role peer `name` is known by ('' when unknown)."""
        peer = self.directory.get(name)
        return peer.role if peer is not None else ""

    def reply_address(self, name: str) -> Address | None:
        """The reply address `name` last sent from (a client's, or a peer's)."""
        return self.addresses.get(name)

    def replied_from(self, name: str, addr: Address) -> None:
        """`name` sent from `addr`: its replies go there."""
        self.addresses[name] = addr

    def reply_known(self, name: str, addr: Address) -> None:
        """`name` is known to reply at `addr` (a durable note): unless it has been heard since."""
        self.addresses.setdefault(name, addr)

    def sent_to(self, name: str, at: float) -> None:
        """A session frame other than a beacon went to peer `name` at `at` (monotonic): it needs no beacon."""
        self.peer(name).sent_peer_at = at

    def heard_at(self, name: str) -> float:
        """When a session frame of peer `name` last arrived (monotonic; 0.0: never)."""
        peer = self.peers.get(name)
        return peer.heard_at if peer is not None else 0.0

    def learn_from(self, infos: Iterable[NetInfo]) -> None:
        """Addresses named by the routing tables of `infos` (neighbours, and destinations several
        hops away): announced to from now on; somewhere new is announced to at once."""
        known = len(self.learned)
        for info in infos:
            for n in info.neighbors:
                if n.address and n.address not in self.learned:
                    self.learn(n.address, info.node)
            for route in info.routes:  # several hops away: a routing daemon's destination not yet named
                if route.destination not in self.learned and _is_ip(route.destination):
                    self.learn(route.destination, info.node)
        if len(self.learned) != known:  # somewhere new to announce to: at once
            self._next_beacon = 0.0

    def repeated(self, msg: Message) -> bool:
        """Whether `msg` is an in-session beacon that tells nothing new: then it only marks its peer
        heard (the liveness pass puts that on the board). Runs on the endpoint's receive thread."""
        if not self._repeats(msg):
            return False
        self.peer(msg.sender).heard_at = self.clock()
        self.count_beacon(msg.sender, msg.body)
        return True

    def learn(self, address: str, node: str) -> None:
        """Announce to `address` from now on (named by `node`'s routing table), within the bounds."""
        why = self.bounds.learned(address, node)
        if why:
            self.bounds.refuse("dropped.hint_bound", node, "learned", why)
        else:
            self.learned.add(address)

    def peer(self, name: str) -> PeerRecord:
        """The record of peer `name`, made when first written (in a run or on the receive thread)."""
        peer = self.peers.get(name)
        if peer is None:
            peer = self.peers.setdefault(name, PeerRecord())
        return peer

    def sent_peer_at(self, name: str) -> float:
        peer = self.peers.get(name)
        return peer.sent_peer_at if peer is not None else -math.inf

    def _repeats(self, msg: Message) -> bool:
        """Whether `msg` is an in-session beacon from a peer that is up, at the address, epoch and with
        the announced interval it had, saying what it said last: nothing for `_heard` to change."""
        body = msg.body
        if msg.hint or msg.kind != "beacon" or not isinstance(body, Beacon) or msg.role == CLIENT_ROLE:
            return False
        peer = self.directory.get(msg.sender)
        return (peer is not None and peer.up and peer.epoch == msg.epoch
                and peer.address == f"{msg.reply[0]}:{msg.reply[1]}"  # `addresses` is set with it
                and (peer.role, peer.capabilities, peer.degraded) == (body.role, body.capabilities, body.degraded)
                and (known := self.peers.get(msg.sender)) is not None
                and known.limit == self._silence_limit(body))

    def _silence_limit(self, beacon: Beacon) -> float:
        """How long a peer may be silent before it is down: `peer_timeout`, scaled by the interval
        its beacon announced (a peer with many quiet peers beacons each of them less often)."""
        s = self.settings
        return s.peer_timeout * max(1.0, beacon.interval / s.beacon_period)

    def count_beacon(self, name: str, beacon: Beacon) -> None:
        """Count a numbered beacon of `name` (runs on the receive thread or in a run)."""
        if beacon.seq:
            peer = self.peer(name)
            count = peer.beacon_count
            if count is None:
                with self._peer_lock:
                    if peer.beacon_count is None:
                        peer.beacon_count = BeaconCount()
                    count = peer.beacon_count
            count.heard(beacon.seq)

    def down_after(self, name: str) -> float:
        """The silence that marks peer `name` down: its limit on a link that loses nothing
        (`_silence_limit`), stretched by the share of its beacons that arrive (`liveness`)."""
        s = self.settings
        peer = self.peers.get(name)
        limit = peer.limit if peer is not None and peer.limit is not None else s.peer_timeout
        count = peer.beacon_count if peer is not None else None
        if count is None:
            return limit
        return limit * silence_stretch(count.delivery(), s.peer_timeout / s.beacon_period)

    def hint_wanted(self, name: str) -> bool:
        """Whether a broadcast beacon from `name` could change anything: not while its peer is up
        (`_hinted` acts on unknown and down peers only). Runs on the endpoint's receive thread."""
        peer = self.directory.get(name)
        return peer is None or not peer.up

    def hinted(self, msg: Message) -> None:
        """A signed beacon: learn where an unknown (or silent) agent may be; a session will tell."""
        name = msg.sender
        if not name or name == self.me:
            return
        old = self.directory.get(name)
        address = f"{msg.reply[0]}:{msg.reply[1]}"
        beacon = msg.body if isinstance(msg.body, Beacon) else Beacon(role=msg.role)
        now = self.clock.wall()  # a peer not up shows when its beacon was last heard (up needs a session)
        if old is None:
            source = msg.source or msg.reply[0]
            why = self.bounds.hint(name, source)
            if why:
                self.bounds.refuse("dropped.hint_bound", source, "hint", why)
                return
            peer = Peer(uid=f"peer:{name}", name=name, address=address, role=beacon.role,
                        capabilities=beacon.capabilities, last_heard=now)
            self.directory[name] = peer
            self.plugin.add(peer)
            self.log.info("agent %s announces itself at %s", name, address)
        elif not old.up and old.address != address:  # a replayed beacon never moves a peer that is up
            peer = old.evolve(address=address, last_heard=now)
            self.directory[name] = peer
            self.plugin.change(peer, reports=["moved"])
        else:
            if not old.up and now - old.last_heard > self.settings.peer_timeout / 4:
                self.directory[name] = old = old.evolve(last_heard=now)
                self.plugin.change(old, reports=["heard"])
            return
        self.endpoint.send(msg.reply, "beacon", self.beacon(), reliable=False, to=name)  # starts a session

    def gone(self, name: str) -> None:
        """The wire tells that agent `name` has left (its Zenoh liveliness token went): down at once,
        not after its silence limit. A session frame from it brings it up again. A peer known only
        from that hint (never heard in a session) is forgotten."""
        peer = self.directory.get(name)
        if peer is not None and not peer.up and self.bounds.is_hinted(name):
            self.bounds.hint_gone(name)
            del self.directory[name]
            self.peers.pop(name, None)
            if self.plugin.get(peer.uid) is not None:
                self.plugin.remove(peer.uid)
            self._count("forgot.hinted")
            return
        if peer is None or not peer.up:
            return
        self.directory[name] = peer = peer.evolve(up=False)
        self.log.warning("peer %s is down: it left (%s liveliness)", name, self.endpoint.wire)
        self.plugin.change(peer, reports=["down"])

    def heard(self, name: str, reply: tuple[str, int], epoch: int, beacon: Any, role: str = "") -> None:
        """A session frame from `name` (of `role`, from `reply`, in its instance `epoch`; a beacon's
        body, or None): it is up there, and its record says when it was heard."""
        if not name or name == self.me:
            return
        if self.bounds.is_hinted(name):  # heard in a session: a peer, no longer a hint
            self.bounds.hint_gone(name)
        now = self.clock.wall()
        self.peer(name).heard_at = self.clock()
        old = self.directory.get(name)
        address = f"{reply[0]}:{reply[1]}"
        if (beacon is None and old is not None and old.up and old.epoch == epoch and old.address == address
                and (old.role or not role) and now - old.last_heard <= self.settings.peer_timeout / 4):
            return  # a peer up, heard again: the common case (a control node hears ten Poses a second from each)
        fields: dict[str, Any] = {"address": address, "epoch": epoch, "last_heard": now, "up": True}
        if role and (old is None or not old.role):
            # a configured peer's role, from its session, before any beacon: two peers that talk
            # send each other no beacons, and its shared status must not wait for one
            fields["role"] = role
        if isinstance(beacon, Beacon):
            self.count_beacon(name, beacon)
            fields.update(role=beacon.role, capabilities=beacon.capabilities, degraded=beacon.degraded)
            self.peer(name).limit = self._silence_limit(beacon)
        if old is None:
            peer = Peer(uid=f"peer:{name}", name=name, **fields)
            self.directory[name] = peer
            self.plugin.add(peer)
            self.log.info("peer %s is up at %s", name, address)
            return
        changed = any(getattr(old, k) != v for k, v in fields.items() if k != "last_heard")
        if changed or now - old.last_heard > self.settings.peer_timeout / 4:
            self._heard_again(old, fields)

    def _heard_again(self, old: Peer, fields: dict[str, Any]) -> None:
        """A known peer heard with news (up again, restarted, moved, degraded ...) or not heard of on
        the board for a quarter peer timeout: its Peer changes, with reports saying what happened."""
        name, address = old.name, fields["address"]
        peer = old.evolve(**fields)
        self.directory[name] = peer
        report = "up" if not old.up else ("restarted" if old.epoch and old.epoch != fields["epoch"] else "heard")
        if report != "heard":
            self.log.info("peer %s is %s at %s", name, report, address)
        reports = [report]
        if peer.degraded != old.degraded:
            reports.append("degraded" if peer.degraded else "recovered")
            if peer.degraded:
                self.log.warning("peer %s is degraded: %s", name, peer.degraded)
            else:
                self.log.info("peer %s takes tasks again", name)
        self.plugin.change(peer, reports=reports)

    def beacon(self, interval: float = 0.0) -> Beacon:
        s = self.settings
        return Beacon(role=s.role, capabilities=s.capabilities, degraded=self.degraded(), interval=interval)

    def beacon_and_liveness(self) -> None:
        """The periodic pass (a few times a beacon period): announcements when due, in-session beacons
        to quiet peers, and the peers' silences when one may have reached its limit."""
        mono = self.clock()
        if mono >= self._next_beacon:
            self._announce(mono)
        self._beacon_quiet_peers(mono)
        if mono >= self._next_silences:
            self._look_at_silences(mono)

    def _announce(self, mono: float) -> None:
        """Signed beacons to the beacon addresses and the learned ones where no peer is up, backing
        off while the directory stands."""
        s = self.settings
        seen = (len(self.directory), len(self.learned))
        # a lone agent keeps announcing every period (it is heard by nobody yet, and costs nobody much)
        standing = (seen == self._announce_seen and bool(self.directory)
                    and all(p.up for p in self.directory.values()))
        self._announce_seen = seen
        self._announce_every = (min(self._announce_every * 2, s.beacon_period * s.announce_backoff)
                                if standing else s.beacon_period)
        self._next_beacon = mono + self._announce_every * 0.9
        announced: set[Address] = set()
        if s.discovery_port:
            announced |= {(host, s.discovery_port) for host in s.beacon_to}
            # a learned address whose agent is already up with us needs no announcement: its
            # session carries beacons (and on one host, as under `erni sim`, a unicast to the
            # shared beacon port lands on whichever agent bound it last, not on that agent)
            up = {p.address for p in self.directory.values() if p.up}
            up_hosts = {a.rpartition(":")[0] for a in up}
            for learned in self.learned:  # HOST (beacon port) or HOST:PORT (data port)
                if learned in up or learned in up_hosts:
                    continue
                try:
                    announced.add(parse_address(learned, s.discovery_port))
                except ConfigError:
                    continue
        if announced:
            beacon = self.beacon()
            for addr in announced:
                self.endpoint.announce(addr, "beacon", beacon)

    def _look_at_silences(self, mono: float) -> None:
        """Peers up but silent beyond their limit go down; the others' `last_heard` follows the
        beacons that said nothing new."""
        s = self.settings
        # O(peers), so every quarter peer timeout, earlier only when a peer's silence may reach its
        # limit then: hearing a peer moves that moment later, a peer that comes up has a limit of at
        # least one peer timeout, and a limit that shrinks (a shorter announced interval, fewer
        # beacons lost) is looked at within the quarter
        self._next_silences = mono + s.peer_timeout / 4
        wall = self.clock.wall()
        for name, peer in list(self.directory.items()):
            if not peer.up:
                continue  # a session frame will bring it up: nothing to look at
            heard = self.peers.get(name)
            silent = mono - (heard.heard_at if heard is not None else 0.0)
            limit = self.down_after(name)
            if silent <= limit:
                self._next_silences = min(self._next_silences, mono - silent + limit)
                if wall - silent - peer.last_heard > s.peer_timeout / 4:  # heard by beacons that said nothing new
                    self.directory[name] = peer = peer.evolve(last_heard=wall - silent)
                    self.plugin.change(peer, reports=["heard"])
                continue
            peer = peer.evolve(up=False)
            self.directory[name] = peer
            count = heard.beacon_count if heard is not None else None
            counted = f"; {100.0 * count.share():.0f} % of its beacons arrived" if count and count.sent else ""
            self.log.warning("peer %s is down: not heard for %.1f s (limit %.1f s%s)", name, silent, limit, counted)
            self.plugin.change(peer, reports=["down"])
            self._next_beacon = min(self._next_beacon, mono + s.beacon_period)  # announce often again

    def _beacon_quiet_peers(self, mono: float) -> None:
        """In-session beacons to the peers sent nothing else for a period, at most `beacon_fanout` a
        period: with more, each is beaconed less often, a newly quiet one at once, the others spread.
        What a beacon says (role, capabilities, degraded) going stale is news for every peer: when it
        changes, every peer gets a beacon at once, talking or not."""
        s = self.settings
        said = self.beacon()
        news = said != self._beacon_said
        self._beacon_said = said
        quiet = [(name, peer) for name, peer in self.directory.items()
                 if peer.address and mono - self.sent_peer_at(name) >= s.beacon_period]
        interval = s.beacon_period * max(1.0, len(quiet) / s.beacon_fanout)
        if news:
            quiet = [(name, peer) for name, peer in self.directory.items() if peer.address]
        beacon: Beacon | None = None
        for name, peer in quiet:
            due = None if news or (record := self.peers.get(name)) is None else record.beacon_due
            if due is not None and due > mono + interval:  # the interval shrank: no longer than the new one
                due = self.peer(name).beacon_due = mono + random.uniform(0.0, interval)
            if due is not None and mono < due:
                continue
            beacon = beacon or self.beacon(interval)
            record = self.peer(name)
            seq = record.beacons_sent = record.beacons_sent + 1  # the receiver counts what arrives
            self.endpoint.send(parse_address(peer.address), "beacon", beacon.model_copy(update={"seq": seq}),
                               reliable=False, to=name)
            # the next a little early (runs come every period); after a newly quiet peer's first
            # beacon (at once: its last frame is a period old), at a random phase, so that many
            # peers' beacons spread over the interval instead of leaving together
            early = 0.9 if due is not None or interval == s.beacon_period else random.uniform(0.3, 0.9)
            record.beacon_due = mono + early * interval
        for record in list(self.peers.values()):
            if record.beacon_due is not None and mono - record.sent_peer_at < s.beacon_period:
                record.beacon_due = None  # talking again: its frames tell it we are alive

    def on_peers_request(self, msg: Message, body: object) -> None:
        """The directory, in as many `peers.reply` parts as keep each within half a frame (room for
        the envelope and the seal): a directory of any size reaches the client whole."""
        counted = {name: peer.beacon_count.share() for name, peer in list(self.peers.items())
                   if peer.beacon_count is not None and peer.beacon_count.sent}
        budget = max(1024, self.settings.max_frame // 2)
        parts: list[list[Peer]] = [[]]
        used = 0
        for peer in self.directory.values():
            size = len(peer.model_dump_json()) + 2 * len(peer.name) + 64  # and its rows of beacons, down_after
            if parts[-1] and used + size > budget:
                parts.append([])
                used = 0
            parts[-1].append(peer)
            used += size
        for i, chunk in enumerate(parts):
            names = [p.name for p in chunk]
            reply = PeerList(agent=self.me, peers=chunk, request=msg.id[:128], part=i, parts=len(parts),
                             beacons={n: counted[n] for n in names if n in counted},
                             down_after={n: self.down_after(n) for n in names})
            self.endpoint.send(msg.reply, "peers.reply", reply, reliable=True, to=msg.sender)


def _is_ip(text: str) -> bool:
    try:
        ipaddress.ip_address(text)
    except ValueError:
        return False
    return True


class Directory(dict[str, Peer]):
    """The peers by name. `gen` moves when a peer is added or deleted, or stored with a change of
    what decides which of our statuses it is sent and where: up, address, role or epoch (not its
    `last_heard`). Peers are only stored (`d[name] = peer`) and deleted (`del d[name]`)."""

    gen = 0

    def __setitem__(self, name: str, peer: Peer) -> None:
        old = self.get(name)
        if old is None or (old.up, old.address, old.role, old.epoch) != (peer.up, peer.address, peer.role, peer.epoch):
            self.gen += 1
        super().__setitem__(name, peer)

    def __delitem__(self, name: str) -> None:
        self.gen += 1
        super().__delitem__(name)


@dataclass(slots=True)
class PeerRecord:
    """What the transport keeps of a peer: when it was heard and sent to, its beacons and limit."""

    heard_at: float = 0.0  # when a session frame of it last arrived (monotonic)
    sent_peer_at: float = -math.inf  # when a session frame other than a beacon went to it (monotonic)
    beacon_due: float | None = None  # while quiet: when its next in-session beacon is due (monotonic)
    limit: float | None = None  # silence that marks it down, from its announced interval
    beacon_count: BeaconCount | None = None  # how many of its numbered beacons arrive
    beacons_sent: int = 0  # in-session beacons sent it (their numbers)
