"""The sessions an endpoint holds with its peers, and the handshakes and hints that make and end them.

`session.py` is one session's cryptography (handshake frames, keys, AEAD, replay window); this
module keeps the table of them: which session a frame's id names, which one to send on to an
address, which instance of a peer is current (its epoch), the handshakes this endpoint started
and the answers it gave, and the revocation list that ends a revoked peer's sessions. It knows
nothing of sockets, queues or message kinds: what it needs from the endpoint that carries its
frames is `SessionHost`, so another wire can carry the same sessions.

Everything here is guarded by one lock, and bounded before authentication (`limits.py`):
handshakes per host and in total, answers waiting for their first frame, hints per host.
"""

from __future__ import annotations

import hashlib
import json
import logging
import threading
from collections import OrderedDict
from collections.abc import Callable
from pathlib import Path
from typing import Protocol

from erni.transport.identity import Identity, IdentityError, read_crl, write_public
from erni.transport.limits import HostBuckets, Limits, TokenBucket
from erni.transport.session import (
    PATIENCE_GROWTH,
    Auth,
    Initiation,
    Session,
    complete,
    cut_signed,
    initiate,
    parse_hello,
    respond,
)
from erni.transport.wire import HINT, KIND, REFUSAL, FrameError

Address = tuple[str, int]


class SessionHost(Protocol):
    """What the sessions need from the endpoint that carries their frames."""

    address: Address  # this endpoint's reply address, as its handshakes state it

    def clock(self) -> float:
        """Seconds on the endpoint's monotonic clock (a test's own, or the agent's)."""

    def pace(self) -> float:
        """Seconds on the real monotonic clock: rate limits hold a flood off, not a protocol step."""

    def count(self, name: str, n: int = 1) -> None: ...

    def warn(self, reason: str, text: str) -> None:
        """Log a warning, rate-limited per reason."""

    def send_datagram(self, frame: bytes, addr: Address) -> None:
        """Send a frame without a session (a handshake, its answer, a hint); raise OSError."""

    def admit(self, sender: str, role: str) -> None:
        """Raise FrameError('unreachable') when frames from `sender` may not be delivered now."""

    def session_up(self, session: Session) -> None:
        """A session is confirmed: what waited for one to its address may go."""

    def session_lost(self, addr: Address) -> None:
        """The peer at `addr` does not know our session: what waits for it needs a new handshake."""

    def handshake_done(self, init: Initiation) -> None:
        """A handshake this endpoint started is answered (or abandoned): it is no longer pending."""

    def send_crl(self, session: Session, der: bytes) -> None:
        """Send our revocation list to a peer whose list is older."""


class SessionTable:
    """The session table of one endpoint instance (`inst`) of agent `name`."""

    def __init__(self, host: SessionHost, auth: Auth | None, name: str, inst: str, limits: Limits, max_frame: int,
                 handshake_timeout: float, identity: Identity | None, revocations: Path | None,
                 log: logging.Logger):
        self.host, self.auth, self.name, self.inst = host, auth, name, inst
        self.limits, self.max_frame, self.handshake_timeout = limits, max_frame, handshake_timeout
        self.identity, self.revocations, self.log = identity, revocations, log
        self.lock = threading.RLock()
        self.by_sid: OrderedDict[bytes, Session] = OrderedDict()
        self.by_addr: dict[Address, Session] = {}
        self.answers: dict[str, tuple[bytes, Session, float]] = {}  # digest of an 'H' -> our 'R'
        self.initiations: dict[str, Initiation] = {}  # digest of our 'H' -> the handshake
        self._completed: OrderedDict[str, None] = OrderedDict()
        self._instances: OrderedDict[tuple[str, str], int] = OrderedDict()
        self._last_epoch: dict[str, int] = {}
        self._hs_hosts = HostBuckets(limits.handshakes_per_host, clock=host.pace)
        self._hs_total = TokenBucket(limits.handshakes_total, clock=host.pace)
        self._hint_hosts = HostBuckets(2.0, clock=host.pace)
        self._refusal_hosts = HostBuckets(2.0, clock=host.pace)
        self.refusals: dict[Address, str] = {}  # address -> why the agent there refused our certificate
        self._crl_mtime = 0.0

    # -- the table ------------------------------------------------------------------------

    def current(self, addr: Address) -> Session | None:
        """The confirmed session used to send to `addr` now (None: the next send starts one)."""
        with self.lock:
            return self.usable(addr)

    def usable(self, addr: Address) -> Session | None:
        """`current` without the lock, for the caller's hot path: each read is atomic, and a
        session dropped meanwhile is one the peer hints about, as if the message had left earlier."""
        session = self.by_addr.get(addr)
        if session is None or session.stale or session.sid not in self.by_sid:
            return None
        return session

    def epoch(self, name: str, inst: str) -> int:
        """This receiver's count of `name`'s instances: 1, 2 ... in the order they were confirmed."""
        key = (name, inst)
        epoch = self._instances.get(key)
        if epoch is None:
            epoch = self._instances[key] = self._last_epoch.get(name, 0) + 1
            self._last_epoch[name] = epoch
            if len(self._instances) > 8192:
                self._instances.popitem(last=False)
        return epoch

    def confirm(self, session: Session) -> None:
        """A session is trusted: send on it from now on; forget older instances of that peer there."""
        with self.lock:
            session.confirmed = True
            session.epoch = self.epoch(session.peer, session.inst)
            self.by_sid[session.sid] = session
            for sid, other in list(self.by_sid.items()):
                if other is not session and other.addr == session.addr and other.inst != session.inst:
                    del self.by_sid[sid]
            self.by_addr[session.addr] = session
            if len(self.by_sid) > self.limits.max_sessions:  # the least recently used go first
                idle = sorted(self.by_sid.values(), key=lambda s: max(s.last_rx, s.last_tx))
                for old in idle[:len(self.by_sid) - self.limits.max_sessions]:
                    del self.by_sid[old.sid]
        if self.identity is not None and session.crl < self.identity.trust.crl_number:
            self._push_crl(session)
        self.host.session_up(session)

    def forget(self, keep: Callable[[Session], bool]) -> int:
        """Drop the sessions `keep` refuses; return how many."""
        with self.lock:
            gone = [sid for sid, s in self.by_sid.items() if not keep(s)]
            for sid in gone:
                session = self.by_sid.pop(sid)
                if self.by_addr.get(session.addr) is session:
                    del self.by_addr[session.addr]
        return len(gone)

    def sweep(self, now: float) -> None:
        """Forget answers never followed by a frame, handshakes never answered, idle sessions; and
        take a revocation list that changed on disk."""
        with self.lock:
            for digest, (_, session, made) in list(self.answers.items()):
                if session.confirmed or now - made > 5 * self.handshake_timeout:
                    del self.answers[digest]
                    if not session.confirmed:
                        self.by_sid.pop(session.sid, None)
            for digest, init in list(self.initiations.items()):
                if now - init.started > (PATIENCE_GROWTH + 1) * self.handshake_timeout:  # none waits as long
                    del self.initiations[digest]
        self.forget(lambda s: now - max(s.last_rx, s.last_tx) < self.limits.session_idle)
        self._reload_crl()

    # -- handshakes -----------------------------------------------------------------------

    def initiate(self, addr: Address, expect: str) -> Initiation:
        """Start a handshake with `addr` (expecting agent `expect`, '' when unknown): its 'H' frame."""
        assert self.auth is not None
        init = initiate(self.auth, self.inst, self.host.address, addr, expect, self.host.clock)
        with self.lock:
            self.initiations[init.digest] = init
        return init

    def abandon(self, init: Initiation) -> None:
        """Give up a handshake that was never answered."""
        with self.lock:
            self.initiations.pop(init.digest, None)

    def on_hello(self, raw: bytes, src: Address) -> None:
        """Answer a peer's handshake ('H'); raise FrameError for one refused."""
        assert self.auth is not None
        digest = hashlib.sha256(raw).hexdigest()
        with self.lock:
            known = self.answers.get(digest)
        if known is not None:  # a retransmission: the same answer again, no new keys
            self._answer(known[0], src)
            return
        now = self.host.pace()  # rate limits keep real time: they hold a flood off, not a protocol step
        if not self._hs_hosts.take(src[0], now) or not self._hs_total.take(now):
            raise FrameError("rate", f"too many handshakes from {src[0]}")
        if len(self.answers) >= 4 * self.limits.max_connections:
            raise FrameError("rate", "too many handshakes waiting for their first frame")
        signed = cut_signed(raw, self.max_frame)
        hello = parse_hello(signed.body)
        if hello.sender == self.name and hello.inst == self.inst:
            return
        if hello.to and hello.to != self.name:
            raise FrameError("receiver", f"handshake for {hello.to} arrived at {self.name}")
        serial = self.auth.verify(signed, hello.sender, hello.role)
        self.host.admit(hello.sender, hello.role)
        frame, session = respond(self.auth, hello, raw, serial, self.inst, self.host.address, self.host.clock)
        with self.lock:
            self.answers[digest] = (frame, session, self.host.clock())
            self.by_sid[session.sid] = session
        self.host.count("handshakes.answered")
        self._answer(frame, src)

    def refuse(self, hello: bytes, src: Address, err: FrameError) -> None:
        """Tell the sender of a handshake why its certificate is not trusted here (at most twice a
        second per host). Unsigned, but it names the handshake's digest: only who saw the handshake
        can forge it, and the sender takes it only as the reason its handshake goes unanswered."""
        trusted = getattr(self.auth, "trusted", None)
        if not callable(trusted) or not self._refusal_hosts.take(src[0]):
            return
        note = {"answers": hashlib.sha256(hello).hexdigest(), "agent": self.name,
                "reason": f"{str(err).partition(': ')[2]}; {self.name} trusts {trusted()}"[:400]}
        body = json.dumps(note).encode()
        try:
            self.host.send_datagram(KIND.pack(1 + len(body), REFUSAL) + body, src)
            self.host.count("refusals.sent")
        except OSError:
            pass

    def on_refusal(self, raw: bytes, src: Address) -> str:
        """A refusal of our handshake: record its reason for the address (logged once) and return
        it; raise FrameError for a refusal of no handshake of ours."""
        if len(raw) > KIND.size + 1024:
            raise FrameError("size", f"a refusal of {len(raw)} bytes (at most {KIND.size + 1024})")
        try:
            note = json.loads(raw[KIND.size:])
            answers, agent, reason = str(note["answers"]), str(note["agent"]), str(note["reason"])
        except (ValueError, TypeError, KeyError):
            raise FrameError("parse", "a refusal that is not the expected JSON object") from None
        with self.lock:
            found = self.initiations.get(answers)
        if found is None or found.addr != src:
            raise FrameError("session", "a refusal of no handshake of ours")
        why = f"{agent[:64]} at {src[0]}:{src[1]} refused this agent's certificate: {' '.join(reason[:400].split())}"
        self.host.count("refusals.received")
        if self.refusals.get(src) != why:
            self.refusals[src] = why
            self.log.warning("%s", why)
        return why

    def _answer(self, frame: bytes, src: Address) -> None:
        """Answer a handshake from the receive thread: a send error (no route to the sender yet, as
        on a mesh whose routes are still forming) is counted and reported, never raised, so the
        receive thread goes on; the sender retransmits its handshake."""
        try:
            self.host.send_datagram(frame, src)
        except OSError as err:
            self.host.count("dropped.answer")
            self.host.warn("udp", f"handshake answer to {src[0]}:{src[1]} failed: {err}")

    def on_reply(self, raw: bytes) -> None:
        """Finish a handshake of ours with the peer's answer ('R'); raise FrameError for one refused."""
        assert self.auth is not None
        signed = cut_signed(raw, self.max_frame)
        answer = parse_hello(signed.body)
        with self.lock:
            init = self.initiations.get(answer.answers)
            if init is None and answer.answers in self._completed:
                return  # a second answer to a retransmitted handshake: the first one made the session
        if init is None:
            raise FrameError("session", "an answer to no handshake of ours")
        if answer.to != self.name:
            raise FrameError("receiver", f"handshake answer for {answer.to} arrived at {self.name}")
        serial = self.auth.verify(signed, answer.sender, answer.role)
        if init.expect and answer.sender != init.expect:
            raise FrameError("wrong_peer", f"{init.addr[0]}:{init.addr[1]} answered as {answer.sender}, "
                             f"expected {init.expect}")
        self.host.admit(answer.sender, answer.role)
        session = complete(self.auth, init, answer, raw, serial, self.host.clock)
        with self.lock:
            if self.initiations.pop(answer.answers, None) is None:
                return  # answered twice: the first answer made the session
            self._completed[answer.answers] = None
            if len(self._completed) > 256:
                self._completed.popitem(last=False)
            if init.addr != session.addr:
                self.by_addr[init.addr] = session
        self.host.handshake_done(init)
        self.host.count("handshakes.completed")
        self.confirm(session)

    # -- hints: "I do not know this session" ----------------------------------------------

    def hint(self, sid: bytes, src: Address, send: Callable[[bytes], object] | None = None) -> None:
        """Tell a sender we do not know its session (at most twice a second per host), on the
        stream it used (`send`) or else as a datagram."""
        if not self._hint_hosts.take(src[0]):
            return
        frame = KIND.pack(1 + 8, HINT) + sid
        try:
            if send is not None:
                send(frame)
            else:
                self.host.send_datagram(frame, src)
            self.host.count("hints.sent")
        except OSError:
            pass

    def on_hint(self, raw: bytes, src: Address) -> None:
        """A peer does not know our session: mark it stale, so that the next send starts a new one."""
        if len(raw) != KIND.size + 8:
            raise FrameError("size", "a hint frame is 13 bytes")
        with self.lock:
            session = self.by_sid.get(raw[KIND.size:])
            if session is None or session.addr[0] != src[0]:
                return
            now = self.host.pace()
            if now - session.stale < 1.0:
                return  # at most one new handshake a second for hints, which anyone can forge
            session.stale = now
            if self.by_addr.get(session.addr) is session:
                del self.by_addr[session.addr]
        self.host.count("hints.received")
        self.host.session_lost(session.addr)

    # -- revocation -----------------------------------------------------------------------

    def _push_crl(self, session: Session) -> None:
        assert self.identity is not None
        der = self.identity.trust.crl_der
        if der:
            self.host.send_crl(session, der)

    def adopt_crl(self, der: bytes, source: str) -> None:
        """Take a newer revocation list: drop revoked peers, keep it, pass it on."""
        if self.identity is None or not self.identity.trust.adopt(der):
            return
        trust = self.identity.trust
        self.log.warning("revocation list %d from %s: %d certificate(s) revoked", trust.crl_number, source,
                         len(trust.revoked))
        if self.revocations is not None and source != str(self.revocations):
            try:  # kept before it is acted on: a restart never forgets a revocation it applied
                write_public(self.revocations, der)
                self._crl_mtime = self.revocations.stat().st_mtime
            except OSError as err:
                self.log.warning("cannot keep the revocation list in %s: %s", self.revocations, err)
        dropped = self.forget(lambda s: s.serial is None or s.serial not in trust.revoked)
        if dropped:
            self.host.count("sessions.revoked", dropped)
        with self.lock:
            behind = [s for s in self.by_sid.values() if s.confirmed and s.crl < trust.crl_number]
        for session in behind:
            session.crl = trust.crl_number
            self._push_crl(session)

    def _reload_crl(self) -> None:
        if self.revocations is None or self.identity is None:
            return
        try:
            mtime = self.revocations.stat().st_mtime
        except OSError:
            return
        if mtime == self._crl_mtime:
            return
        self._crl_mtime = mtime
        try:
            from cryptography.hazmat.primitives.serialization import Encoding

            der = read_crl(self.revocations).public_bytes(Encoding.DER)
        except IdentityError as err:
            self.log.warning("%s", err)
            return
        self.adopt_crl(der, str(self.revocations))
