"""The frame path of an endpoint: a frame that arrives (a UDP datagram, a frame of a TCP stream or of
the Zenoh wire) is checked, opened in its session and decoded into messages, one handler per kind of
frame (data, hint, handshake, its answer, a refusal, a beacon, a plain frame); what fails a check is
counted and dropped, and a fault of the path itself never ends the thread that received the frame.

It keeps no state of its own but the moment it last logged a fault: the sessions, the counters and
the delivery of what it accepts are its endpoint's (`FrameHost`).
"""

from __future__ import annotations

import base64
import logging
from collections.abc import Callable
from typing import Any, Protocol

from erni.transport.codec import DecodedHead, decode_data, decode_status
from erni.transport.session import Auth, CertificateRefused, Session
from erni.transport.session_table import SessionTable
from erni.transport.wire import (
    BEACON,
    DATA,
    HEADER,
    HELLO,
    HINT,
    KIND,
    KINDS,
    PLAIN,
    REFUSAL,
    REPLY,
    EnvelopeHead,
    FrameError,
    Message,
    body_of,
    check_frame,
    parse_batch,
    parse_envelope,
    parse_item,
    parse_typed,
)

Address = tuple[str, int]
Accepted = tuple[list[Message], Session | None] | None
"""What a frame brings: its messages (several in a batch of statuses) and their session, or nothing."""
Handler = Callable[[bytes, str, Address], Accepted]

INTERNAL = ("ack", "crl")  # kinds the endpoint handles itself


class FrameHost(Protocol):
    """What the frame path needs of its endpoint."""

    name: str
    inst: str
    auth: Auth | None
    max_frame: int
    sessions: SessionTable
    log: logging.Logger

    @property
    def inbound_filter(self) -> Callable[[str, str], bool] | None: ...

    @property
    def on_refused(self) -> Callable[[Address, str], None]: ...

    def pace(self) -> float: ...

    def count(self, name: str, n: int = 1) -> None: ...

    def warn(self, reason: str, text: str) -> None: ...

    def admit(self, sender: str, role: str) -> None:
        """Raise FrameError when `sender` of `role` may not reach this endpoint now (the inbound filter)."""

    def deliver(self, msg: Message) -> None:
        """Hand a message on (its kind not the endpoint's own)."""

    def dispatch(self, msg: Message) -> None:
        """Hand a message to the endpoint's owner."""


class FramePath:
    """Frames in, messages out, for one endpoint."""

    def __init__(self, host: FrameHost, on_beacon: Handler) -> None:
        self.host = host
        self._on_beacon = on_beacon  # discovery.py (`Beacons.on_beacon`): a signed beacon of an agent not in session
        self._last_fault = -1e9  # when a fault of the frame path was last logged (monotonic)
        self._by_kind = self._handlers()

    def dropped(self, channel: str, err: FrameError) -> None:
        self.host.count(f"dropped.{err.reason}")
        self.host.warn(err.reason, f"dropped a {channel} frame: {err}")

    def accept_frame(self, raw: bytes, channel: str, src: Address) -> Accepted:
        """Check a frame; count and log what fails; return its messages (several in a batch of
        statuses) and their session, or None. A fault of the frame path itself (any exception
        other than a FrameError) drops the frame and is logged with its traceback, rate-limited:
        one frame must never end the receive thread."""
        try:
            return self._accept_frame(raw, channel, src)
        except Exception:
            self._fault(channel, raw, src)
            return None

    def _fault(self, channel: str, raw: bytes, src: Address | None) -> None:
        """Count a frame dropped by a fault of the frame path; log it with its traceback, rate-limited."""
        self.host.count("dropped.fault")
        now = self.host.pace()
        if now - self._last_fault >= 5.0:
            self._last_fault = now
            self.host.log.exception("dropped a %s frame of %d bytes from %s: the frame path failed on it",
                               channel, len(raw), src[0] if src else "?")

    def _accept_frame(self, raw: bytes, channel: str, src: Address) -> Accepted:
        try:
            kind = check_frame(raw, self.host.max_frame)
            if self.host.auth is None:
                if kind != PLAIN:
                    raise FrameError("auth", f"a {KINDS[kind]} frame at an agent running insecure")
                return self._plain(raw, channel, src)
            if channel == "tcp" and kind not in (DATA, HINT):  # a hint: on the stream a sender awaits its ack on
                raise FrameError("parse", f"a {KINDS[kind]} frame on a TCP stream")
            return self._by_kind[kind](raw, channel, src)
        except FrameError as err:
            self.dropped(channel, err)
        return None

    def _handlers(self) -> dict[int, Callable[[bytes, str, Address], Accepted]]:
        """The handler of each kind of frame, in a session (`wire.py` lists the kinds)."""
        def hint(raw: bytes, channel: str, src: Address) -> Accepted:
            self.host.sessions.on_hint(raw, src)
            return None

        def hello(raw: bytes, channel: str, src: Address) -> Accepted:
            try:
                self.host.sessions.on_hello(raw, src)
            except CertificateRefused as err:
                self.host.sessions.refuse(raw, src, err)
                raise
            return None

        def refusal(raw: bytes, channel: str, src: Address) -> Accepted:
            self.host.on_refused(src, self.host.sessions.on_refusal(raw, src))
            return None

        def reply(raw: bytes, channel: str, src: Address) -> Accepted:
            self.host.sessions.on_reply(raw)
            return None

        def plain(raw: bytes, channel: str, src: Address) -> Accepted:
            raise FrameError("auth", "an unauthenticated frame (is the sender running insecure?)")

        return {DATA: self._data, HINT: hint, HELLO: hello, REFUSAL: refusal, REPLY: reply, BEACON: self._on_beacon,
                PLAIN: plain}

    def _plain(self, raw: bytes, channel: str, src: Address) -> Accepted:
        env = parse_envelope(raw[KIND.size:])
        if env.sender == self.host.name and env.inst == self.host.inst:
            return None  # our own beacon, heard back
        if env.to and env.to != self.host.name:
            raise FrameError("receiver", f"frame for {env.to} arrived at {self.host.name}")
        self.host.admit(env.sender, env.role)
        body = body_of(env.type, env.body)
        self.host.count("received")
        # no hint: without authentication a beacon is as good a sign of life as any other frame
        return [Message(env.sender, env.role, (env.reply[0], env.reply[1]), self.host.sessions.epoch(env.sender, env.inst),
                        env.seq, env.id, env.kind, body)], None

    def _data(self, raw: bytes, channel: str, src: Address) -> tuple[list[Message], Session | None]:
        """Open a data frame of a session: one envelope, or a batch of statuses (`[head, [message,
        ...]]`), and decode its messages (`_messages`)."""
        sid = raw[KIND.size:KIND.size + 8]
        session = self.host.sessions.by_sid.get(sid)
        if session is None:
            self.host.sessions.hint(sid, src)
            raise FrameError("session", f"unknown session {sid.hex()} (its sender or this agent restarted)")
        return self._messages(session.open(raw), session, channel), session

    def _messages(self, plain: bytes, session: Session, channel: str) -> list[Message]:
        """The messages of an opened data frame. A batch's message or body that does not validate
        is dropped alone; a head or an envelope that does not validate, or that names another
        sender or receiver, drops the whole frame."""
        fast = decode_data(plain)  # msgspec: head, messages and typed bodies from the bytes, or None
        head: DecodedHead | EnvelopeHead
        pairs: list[tuple[Any, Any]]  # each message (its seq, id, kind, type) and its body
        if fast is not None:
            head, pairs = fast
            checked = True
        else:
            head, pairs, checked = self._parse_data(plain, channel)
        if head.sender != session.peer or head.role != session.role or head.inst != session.inst:
            raise FrameError("auth", f"envelope names {head.sender[:64]} but the session is with {session.peer}")
        if head.to != self.host.name:
            raise FrameError("receiver", f"frame for {head.to} arrived at {self.host.name}")
        if not session.confirmed:
            self.host.sessions.confirm(session)
        if self.host.inbound_filter is not None:
            self.host.admit(session.peer, session.role)
        peer, role, addr, epoch = session.peer, session.role, session.addr, session.epoch
        msgs = []
        for item, body in pairs:
            kind = item.kind
            if kind == "crl" or not checked:
                try:
                    if kind == "crl" and isinstance(body, str):
                        try:
                            self.host.sessions.adopt_crl(base64.b64decode(body, validate=True), session.peer)
                        except ValueError:
                            raise FrameError("parse", "revocation list is not base64") from None
                    if not checked:
                        body = body_of(item.type, body)
                except FrameError as err:
                    if plain[:1] != b"[":  # one envelope: the frame is dropped
                        raise
                    self.dropped(channel, err)
                    continue
            msgs.append(Message(peer, role, addr, epoch, item.seq, item.id, kind, body))
        self.host.count("received", len(msgs))
        return msgs

    def _parse_data(self, plain: bytes, channel: str) -> tuple[EnvelopeHead, list[tuple[Any, Any]], bool]:
        """The pydantic parse of a data frame the codec did not take: its head, its messages with
        their bodies, and whether the bodies are typed already (one step) or still to be (two)."""
        typed = parse_typed(plain)  # pydantic in one step, or None: two steps
        if typed is not None:
            return typed[0], [(item, item.body) for item in typed[1]], True
        if plain[:1] == b"[":  # a message of the batch that does not validate is dropped alone
            head, values = parse_batch(plain)
            pairs: list[tuple[Any, Any]] = []
            for value in values:
                try:
                    parsed = parse_item(value)
                    pairs.append((parsed, parsed.body))
                except FrameError as err:
                    self.dropped(channel, err)
            return head, pairs, False
        envelope = parse_envelope(plain)
        return envelope, [(envelope, envelope.body)], False

    def receive_datagram(self, raw: bytes, src: Address) -> None:
        """The UDP receive thread's whole path for one datagram: a data frame of a confirmed
        session is opened, decoded and handed to `on_message` here, in one call with the checks
        of `accept_frame` written out; any other frame goes through `accept_frame`. What fails is
        counted and logged the same way: a frame that fails a check is dropped, and a fault of
        the frame path never ends the receive thread."""
        try:
            session = self.host.sessions.by_sid.get(raw[5:13]) if raw[4:5] == b"D" and self.host.auth is not None else None
            if session is None or not session.confirmed or len(raw) > self.host.max_frame \
                    or HEADER.unpack_from(raw)[0] != len(raw) - 4:
                got = self.accept_frame(raw, "udp", src)
                if got is not None:
                    for msg in got[0]:
                        self.host.deliver(msg)
                return
            plain = session.open(raw)
            status = decode_status(plain)  # the common frame: one Pose, decoded in one pass (or None)
            if status is not None:
                env, pose = status
                if env.sender == session.peer and env.role == session.role and env.inst == session.inst \
                        and env.to == self.host.name and env.kind not in INTERNAL:
                    if self.host.inbound_filter is not None:
                        self.host.admit(session.peer, session.role)
                    self.host.count("received")
                    self.host.dispatch(Message(session.peer, session.role, session.addr, session.epoch, env.seq,
                                           env.id, env.kind, pose))
                    return
            msgs = self._messages(plain, session, "udp")  # anything else (and what fails a check above)
        except FrameError as err:
            self.dropped("udp", err)
            return
        except Exception:
            self._fault("udp", raw, src)
            return
        for msg in msgs:
            self.host.deliver(msg)
