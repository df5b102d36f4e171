"""Discovery at the endpoint: signed beacons to and from agents not in session yet.

An agent announces itself (`announce`) to the discovery port's broadcast address or to a peer it
knows only by address: a sessionless frame signed with its identity (`B`, in `session.py`), sent
by the sender pool (`_announce`). A beacon heard is a hint of presence only (signed, but
replayable): its signature is checked only when the owner wants the hint (`hint_wanted`: not for
a peer already in session) and at most `limits.beacons_total` a second. The peers' liveliness
(in-session beacons, silences, the numbered beacons of `liveness.py`) is the transport plugin's
(`bridge.py`).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import replace
from typing import TYPE_CHECKING, Any

from pydantic import BaseModel

from erni.transport.outbox import Dest, Outgoing
from erni.transport.session import cut_signed
from erni.transport.wire import BEACON, UDP_MAX_FRAME, FrameError, Message, body_of, parse_envelope

if TYPE_CHECKING:
    from erni.transport.limits import TokenBucket
    from erni.transport.session import Auth, Session
    from erni.transport.wires import Wire

Address = tuple[str, int]
Accepted = tuple[list[Message], "Session | None"] | None


class Beacons:
    """Signed beacons (a mixin of `Endpoint`; what it uses of the rest is declared below)."""

    if TYPE_CHECKING:
        carrier: Wire
        auth: Auth | None
        name: str
        inst: str
        max_frame: int
        hint_wanted: Callable[[str], bool] | None
        _beacon_bucket: TokenBucket

        def count(self, name: str, n: int = 1) -> None: ...
        def warn(self, reason: str, text: str) -> None: ...
        def _enqueue(self, addr: Address, kind: str, body: Any, lane: str, msg_id: str | None,
                     ttl: float | None, to: str | None) -> str: ...
        def _frame(self, out: Outgoing, session: Session | None, max_frame: int) -> bytes: ...
        def _envelope(self, out: Outgoing, to: str) -> bytes: ...
        def _filter(self, sender: str, role: str) -> None: ...

    def announce(self, addr: Address, kind: str, body: BaseModel | Any = None) -> str:
        """Queue a signed, sessionless datagram for receivers not known yet (beacons)."""
        return self._enqueue(addr, kind, body, "announce", None, None, None)

    def _announce(self, dest: Dest, out: Outgoing) -> None:
        try:
            frame = self._frame(replace(out, to=""), None, UDP_MAX_FRAME) if self.auth is None else \
                self.auth.sign(BEACON, self._envelope(out, ""))
            self.carrier.sendto(frame, dest.addr)
            self.count("sent.announce")
        except (OSError, FrameError) as err:
            self.count("dropped.fast_error")
            self.warn("udp", f"beacon to {dest.addr[0]}:{dest.addr[1]} failed: {err}")

    def _on_beacon(self, raw: bytes, channel: str, src: Address) -> Accepted:
        assert self.auth is not None
        signed = cut_signed(raw, self.max_frame)
        env = parse_envelope(signed.body)
        if env.sender == self.name and env.inst == self.inst:
            return None  # our own beacon, heard back
        if env.kind != "beacon":
            raise FrameError("parse", f"a signed broadcast frame of kind {env.kind[:64]!r}: beacons only")
        if self.hint_wanted is not None and not self.hint_wanted(env.sender):
            self.count("received.beacons.known")  # a peer in session already: its hint is not worth a signature check
            return None
        if not self._beacon_bucket.take():
            raise FrameError("rate", "too many beacons to check")
        self.auth.verify(signed, env.sender, env.role)
        self._filter(env.sender, env.role)
        body = body_of(env.type, env.body)
        self.count("received.beacons")
        return [Message(env.sender, env.role, (env.reply[0], env.reply[1]), 0, env.seq, env.id, env.kind,
                        body, hint=True, source=src[0])], None
