"""Fast messages (statuses): sent from the caller's thread when nothing waits before them, and
gathered into one datagram when they come in a burst.

A status on its own, in a confirmed session, with nothing queued for its destination, is sealed
and handed to the UDP socket by the caller (`send_status`): the socket never blocks, and what it
does not take goes to the sender pool. A status that follows the caller's previous one to the same
destination within `COALESCE` joins that destination's batch (`gather`): the caller seals and sends
each `BATCH_BYTES` of them as one datagram `[head, [item, ...]]`, the head stated once, and the
sender pool sends the last partly filled one after `FLUSH_AFTER`; a batch the pool sends with one
status, from a caller that filled none lately, turns gathering off for that destination for
`outbox.SOLO_FOR` (the caller waits between its statuses: it was no burst). The pool sends queued statuses
the same way (`send_fast`); what the socket refuses goes back in front of the queue, which is
bounded and drops the oldest.

A status for several peers (`fanout`) is encoded once, as one message (one id, one number):
the caller seals it in each peer's session, then hands the datagrams to the socket back to back;
a peer it cannot go to at once gets it through `send`.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from typing import TYPE_CHECKING, Any, Protocol

from pydantic_core import to_json

from erni.transport.outbox import Batch, Counters, Dest, MessageIds, Outgoing, SendQueues
from erni.transport.wire import (
    FrameError,
    batch_payload,
    encode_body,
    item_bytes,
    join_envelope,
    kind_and_type,
)

if TYPE_CHECKING:
    from erni.transport.session import Session
    from erni.transport.session_table import SessionTable
    from erni.transport.wires import Wire

Address = tuple[str, int]

COALESCE = 20e-6
"""A status sent to a destination less than this (s) after the caller's previous send to it
returned is taken for part of a burst: it is gathered with the burst's next ones, and the caller
seals and sends each `BATCH_BYTES` of them as one datagram. A robot's statuses and a request
waiting for a remote reply are far slower than this and go out one to a datagram, at once. A
caller that waits for each status's delivery in its own process (a ping-pong on loopback) can
come back within this, often before its own `sendto` has returned; the first batch of one it
leaves to the sender pool then turns gathering off for that destination for
`outbox.SOLO_FOR`."""

FLUSH_AFTER = 200e-6
"""How long (s) the last, partly filled datagram of a burst waits for more before the sender
pool sends it."""


class FrameMaker(Counters, Protocol):
    """What the fast messages need of their endpoint: its messages and frames (the envelope heads
    name the endpoint), besides its counters."""

    def outgoing(self, msg_id: str, kind: str, type_name: str | None, body: Any, data: bytes, seq: int,
                 ttl: float | None, to: str | None) -> Outgoing: ...
    def frame(self, out: Outgoing, session: Session | None, max_frame: int) -> bytes: ...
    def head(self, peer: str) -> bytes: ...
    def head_open(self, peer: str) -> bytes: ...


def item_of(out: Outgoing) -> bytes:
    """A message's own part of an envelope (`[head, item]`): its number, id, kind, type and body."""
    return item_bytes(out.seq, out.id, out.kind, out.type, out.data)


class FastMessages:
    """Statuses and their batching: from the caller's thread (`send_status`, `fanout`), and
    for the sender pool (`send_datagram`, `send_fast`)."""

    def __init__(self, queues: SendQueues, ids: MessageIds, carrier: Wire, sessions: SessionTable,
                 frames: FrameMaker, *, secure: bool, udp_frame: int, pace: Callable[[], float]) -> None:
        self.queues, self.ids, self.carrier, self.sessions, self.frames = queues, ids, carrier, sessions, frames
        self.secure, self.udp_frame, self.pace = secure, udp_frame, pace
        self.fast_at: dict[Address, float] = {}  # destination -> when the caller's last status to it was handled

    def send_status(self, addr: Address, kind: str, body: Any, msg_id: str | None, ttl: float | None,
                    to: str | None) -> str:
        """`send` of a fast message (a status): sealed and handed to the socket from the caller's
        thread when that cannot wait, else queued for the sender pool; return its id.

        The common case, a status on its own in a confirmed session with the intended peer and
        nothing queued before it for that destination, is written here in one piece: the body's
        JSON, the message's around it (`head_open`), sealed, handed to the UDP socket, which never
        blocks (MSG_DONTWAIT). Anything else (no session yet, a burst to gather, a queue to keep
        the order of, a full send buffer) takes the general way, `send_now` and then the queue.
        """
        ids = self.ids
        seq = next(ids.seq)
        msg_id = msg_id or f"{ids.prefix}{seq:x}"
        type_name, data = encode_body(body)
        sessions, queues = self.sessions, self.queues
        session = sessions.by_addr.get(addr) if self.secure else None
        if session is not None and queues.started and not queues.stopping and not session.stale \
                and session.sid in sessions.by_sid and not (to and to != session.peer):
            dest = queues.dests.get(addr)
            fast_at = self.fast_at
            if (dest is None or not (dest.fast or dest.announce)) and not self.gathers(addr, dest, self.pace()):
                head = self.frames.head_open(session.peer)
                try:
                    self.carrier.sendto(session.seal(b'%b"seq":%d,"id":%b,%b,"body":%b}' % (
                        head, seq, to_json(msg_id), kind_and_type(kind, type_name), data), self.udp_frame), addr)
                except (OSError, FrameError) as err:
                    dropped = self.unsent(addr, err)  # True: too big, or an error; False: the buffer is full
                    fast_at[addr] = self.pace()
                    if dropped:
                        return msg_id
                    self.frames.count("sent.deferred")  # the pool sends it when the buffer drains
                    queues.queue(addr, self.frames.outgoing(msg_id, kind, type_name, body, data, seq, ttl, to), "fast")
                    return msg_id
                self.frames.count("sent.fast")
                fast_at[addr] = self.pace()  # a burst is told by the time until the next
                return msg_id
        out = self.frames.outgoing(msg_id, kind, type_name, body, data, seq, ttl, to)
        if not self.send_now(addr, out):
            queues.queue(addr, out, "fast")
        return msg_id

    def send_now(self, addr: Address, out: Outgoing) -> bool:
        """Send a fast message from the caller's thread when that cannot wait: True when it is done.
        Note when the caller's send to `addr` was handled, sent or not (`fast_at`).

        Only in a confirmed session (no handshake to drive) with the intended peer, with nothing
        queued before it for that destination, and only what the socket takes at once: the UDP
        socket never blocks (a full send buffer raises at once), and then the message is queued
        for the sender pool. A status of a burst (`COALESCE`) is gathered into the destination's
        batch instead.
        """
        sent = False
        queues = self.queues
        try:
            if not queues.started or queues.stopping:
                return False
            dest = queues.dests.get(addr)
            if dest is not None and (dest.fast or dest.announce):
                return False  # keep the order of what is queued already
            if not self.secure:
                single = self.batch(None)
                single.add(out, b"")
                sent = self.send_datagram(addr, single)
            else:
                session = self.sessions.usable(addr)
                if session is None or out.to and out.to != session.peer:
                    return False  # a handshake to drive, or a wrong peer to report: the sender pool's work
                if self.gathers(addr, dest, self.pace()):
                    return self.gather(addr, out, session)  # a burst: several statuses to a datagram
                single = self.batch(session)
                single.add(out, item_of(out))
                sent = self.send_datagram(addr, single)
            if not sent:
                self.frames.count("sent.deferred")  # the socket's buffer is full: the pool sends it when it drains
            return sent
        finally:
            self.fast_at[addr] = self.pace()

    def gathers(self, addr: Address, dest: Dest | None, now: float) -> bool:
        """Whether a status to `addr` now joins a batch: one is being gathered there, or it follows
        the caller's previous status there within `COALESCE` (a burst) while gathering is on there
        (not within `SOLO_FOR` of a batch of one)."""
        if dest is not None and dest.batch is not None:
            return True
        return now - self.fast_at.get(addr, -math.inf) < COALESCE and (dest is None or now >= dest.solo_until)

    def fanout(self, targets: Sequence[tuple[Address, str]], kind: str, body: Any) -> tuple[str, list[tuple[Address, str]]]:
        """Send one fast message (a status) to each `(address, agent)` of `targets` that it can go to
        at once; return its id and the targets left for `send` (`Endpoint.send_fanout`).

        The body is encoded once and the message is one message, with one id and one number, for
        every peer (each receives it once). To each peer in a confirmed session with nothing queued
        before it, the caller seals it in that session; once all are sealed, the datagrams go to
        the socket back to back (no Python between two `sendto`, so the peers it wakes all have
        theirs when the caller leaves the CPU). Any other peer (no session yet, messages queued
        for it, a burst being gathered, a full socket buffer) is left to the endpoint's `send`.
        """
        seq = next(self.ids.seq)
        msg_id = f"{self.ids.prefix}{seq:x}"
        later: list[tuple[Address, str]] = []
        frames: list[tuple[bytes, Address, str]] = []
        queues = self.queues
        if not queues.started or queues.stopping:
            later = list(targets)
        else:
            type_name, data = encode_body(body)
            item = item_bytes(seq, msg_id, kind, type_name, data)
            recent = self.pace() - COALESCE
            dests = queues.dests
            fast_at = self.fast_at
            head = self.frames.head
            for addr, to in targets:
                session = self.sessions.usable(addr) if self.secure else None
                dest = dests.get(addr)
                if session is None or session.peer != to or fast_at.get(addr, -math.inf) > recent \
                        or dest is not None and (dest.fast or dest.announce or dest.batch is not None):
                    later.append((addr, to))  # the general path: a handshake, an order to keep, a burst
                    continue
                try:
                    frames.append((session.seal(join_envelope(head(to), item), self.udp_frame), addr, to))
                except FrameError as err:
                    self.unsent(addr, err)
        sent = 0
        sendto = self.carrier.sendto
        for frame, addr, to in frames:
            try:
                sendto(frame, addr)
                sent += 1
            except OSError as err:
                if not self.unsent(addr, err):  # the socket's buffer is full: the pool sends it
                    later.append((addr, to))
        if frames:
            now = self.pace()
            for _, addr, _ in frames:
                self.fast_at[addr] = now  # a burst is told by the time until the next
        if sent:
            self.frames.count("sent.fast", sent)
        return msg_id, later

    def unsent(self, addr: Address, err: OSError | FrameError) -> bool:
        """Count and report a datagram of fast messages that did not leave; False when only the
        socket's buffer was full (the sender pool sends it when it drains), True when it is dropped."""
        if isinstance(err, BlockingIOError | InterruptedError):
            return False
        if isinstance(err, FrameError):
            self.frames.count("dropped.too_big")
            self.frames.warn("too_big", f"not sent to {addr}: {err}")
        else:
            self.frames.count("dropped.fast_error")
            self.frames.warn("udp", f"UDP send to {addr[0]}:{addr[1]} failed: {err}")
        return True

    def gather(self, addr: Address, out: Outgoing, session: Session) -> bool:
        """Add a status of a burst to its destination's open batch; send the batch from the
        caller's thread once the next would not fit, and leave what is left at the burst's end
        to the sender pool (`FLUSH_AFTER`)."""
        item = item_of(out)
        full: Batch | None = None
        queues = self.queues
        with queues.cond:
            if queues.stopping:
                return True
            dest = queues.dest_for(addr)
            if dest.fast or dest.announce:
                return False  # queued meanwhile: it goes after them, in order
            batch = dest.batch
            if batch is not None and (batch.session is not session or not batch.fits(item)):
                full, batch = batch, None
                dest.full_at = self.pace()  # a real burst: it filled a datagram
            if batch is None:
                batch = dest.batch = self.batch(session)
                queues.schedule(dest, self.pace() + FLUSH_AFTER)
            batch.add(out, item)
        if full is not None and not self.send_datagram(addr, full):
            queues.requeue(dest, full.outs)
            with queues.cond:
                queues.make_ready(dest)
        return True

    def send_datagram(self, addr: Address, batch: Batch) -> bool:
        """Send a batch of fast messages as one datagram. False when the socket's buffer is full
        (nothing was sent)."""
        max_frame = self.udp_frame
        outs = batch.outs
        try:
            if batch.session is None:
                frame = self.frames.frame(outs[0], None, max_frame)
            else:
                frame = batch.session.seal(batch_payload(batch.head, batch.items), max_frame)
            self.carrier.sendto(frame, addr)
        except (OSError, FrameError) as err:
            return self.unsent(addr, err)
        self.frames.count("sent.fast", len(outs))
        if len(outs) > 1:
            self.frames.count("sent.batched", len(outs))
        return True

    def send_fast(self, dest: Dest, session: Session | None, outs: list[Outgoing]) -> float | None:
        """Send queued fast messages, in a session as many to a datagram as fit in `BATCH_BYTES`;
        return when to try again if the socket's buffer is full (what is left goes back in front)."""
        batch = self.batch(session)
        for k, out in enumerate(outs):
            if session is not None and out.to and out.to != session.peer:
                self.frames.count("dropped.wrong_peer")
                self.frames.warn("wrong_peer", f"not sent: {dest.addr[0]}:{dest.addr[1]} is "
                                 f"{session.peer}, not {out.to}")
                continue
            item = item_of(out) if session is not None else b""
            if not batch.fits(item):
                if not self.send_datagram(dest.addr, batch):
                    self.queues.requeue(dest, batch.outs + outs[k:])
                    return self.pace() + 0.005
                batch = self.batch(session)
            batch.add(out, item)
        if batch.outs and not self.send_datagram(dest.addr, batch):
            self.queues.requeue(dest, batch.outs)
            return self.pace() + 0.005
        return None

    def batch(self, session: Session | None) -> Batch:
        """An empty datagram for messages to `session`'s peer, with the head they will share."""
        batch = Batch(None) if session is None else Batch(session, self.frames.head(session.peer))
        if self.carrier.batch_limit is not None:
            batch.limit = self.carrier.batch_limit
        return batch
