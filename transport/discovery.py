"""Discovery at the endpoint: signed beacons to and from agents not in session yet.

An agent announces itself (`announce`) to the discovery port's broadcast address or to a peer it
knows only by address: a sessionless frame signed with its identity (`B`, in `session.py`), sent
by the sender pool (`Beacons.send_beacon`). A beacon heard is a hint of presence only (signed, but
replayable): its signature is checked only when the owner wants the hint (`hint_wanted`: not for
a peer already in session) and at most `limits.beacons_total` a second. The peers' liveliness
(in-session beacons, silences, the numbered beacons of `liveness.py`) is the transport plugin's
(`presence.py`).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import replace
from typing import TYPE_CHECKING, Protocol

from erni.transport.outbox import Counters, Dest, Outgoing
from erni.transport.session import cut_signed
from erni.transport.wire import BEACON, UDP_MAX_FRAME, FrameError, Message, body_of, parse_envelope

if TYPE_CHECKING:
    from erni.transport.limits import TokenBucket
    from erni.transport.session import Auth, Session
    from erni.transport.wires import Wire

Address = tuple[str, int]
Accepted = tuple[list[Message], "Session | None"] | None


class BeaconHost(Counters, Protocol):
    """What discovery needs of its endpoint: its frames, whether a hint is wanted (`hint_wanted`,
    set by the owner) and its inbound filter (`admit`), besides its counters."""

    hint_wanted: Callable[[str], bool] | None

    def frame(self, out: Outgoing, session: Session | None, max_frame: int) -> bytes: ...
    def envelope(self, out: Outgoing, to: str) -> bytes: ...
    def admit(self, sender: str, role: str) -> None: ...


class Beacons:
    """Signed beacons: sent for the sender pool (`send_beacon`), checked as they arrive (`on_beacon`)."""

    def __init__(self, carrier: Wire, host: BeaconHost, auth: Auth | None, bucket: TokenBucket, *, name: str,
                 inst: str, max_frame: int) -> None:
        self.carrier, self.host, self.auth, self.bucket = carrier, host, auth, bucket
        self.name, self.inst, self.max_frame = name, inst, max_frame

    def send_beacon(self, dest: Dest, out: Outgoing) -> None:
        try:
            frame = self.host.frame(replace(out, to=""), None, UDP_MAX_FRAME) if self.auth is None else \
                self.auth.sign(BEACON, self.host.envelope(out, ""))
            self.carrier.sendto(frame, dest.addr)
            self.host.count("sent.announce")
        except (OSError, FrameError) as err:
            self.host.count("dropped.fast_error")
            self.host.warn("udp", f"beacon to {dest.addr[0]}:{dest.addr[1]} failed: {err}")

    def on_beacon(self, raw: bytes, channel: str, src: Address) -> Accepted:
        assert self.auth is not None
        signed = cut_signed(raw, self.max_frame)
        env = parse_envelope(signed.body)
        if env.sender == self.name and env.inst == self.inst:
            return None  # our own beacon, heard back
        if env.kind != "beacon":
            raise FrameError("parse", f"a signed broadcast frame of kind {env.kind[:64]!r}: beacons only")
        hint_wanted = self.host.hint_wanted
        if hint_wanted is not None and not hint_wanted(env.sender):
            self.host.count("received.beacons.known")  # a peer in session already: its hint is not worth a signature check
            return None
        if not self.bucket.take():
            raise FrameError("rate", "too many beacons to check")
        self.auth.verify(signed, env.sender, env.role)
        self.host.admit(env.sender, env.role)
        body = body_of(env.type, env.body)
        self.host.count("received.beacons")
        return [Message(env.sender, env.role, (env.reply[0], env.reply[1]), 0, env.seq, env.id, env.kind,
                        body, hint=True, source=src[0])], None
