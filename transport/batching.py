"""Fast messages (statuses): sent from the caller's thread when nothing waits before them, and
gathered into one datagram when they come in a burst.

A status on its own, in a confirmed session, with nothing queued for its destination, is sealed
and handed to the UDP socket by the caller (`_send_status`): the socket never blocks, and what it
does not take goes to the sender pool. A status that follows the caller's previous one to the same
destination within `COALESCE` joins that destination's batch (`_gather`): the caller seals and sends
each `BATCH_BYTES` of them as one datagram `[head, [item, ...]]`, the head stated once, and the
sender pool sends the last partly filled one after `FLUSH_AFTER`; a batch the pool sends with one
status, from a caller that filled none lately, turns gathering off for that destination for
`outbox.SOLO_FOR` (the caller waits between its statuses: it was no burst). The pool sends queued statuses
the same way (`_send_fast`); what the socket refuses goes back in front of the queue, which is
bounded and drops the oldest.

A status for several peers (`send_fanout`) is encoded once, as one message (one id, one number):
the caller seals it in each peer's session, then hands the datagrams to the socket back to back;
a peer it cannot go to at once gets it through `send`.
"""

from __future__ import annotations

import itertools
import math
import threading
from collections.abc import Callable, Sequence
from typing import TYPE_CHECKING, Any

from pydantic_core import to_json

from erni.transport.outbox import Batch, Dest, Outgoing
from erni.transport.wire import (
    FrameError,
    batch_payload,
    encode_body,
    head_bytes,
    item_bytes,
    join_envelope,
    kind_and_type,
)

if TYPE_CHECKING:
    from erni.transport.session import Auth, Session
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


class FastMessages:
    """Statuses and their batching (a mixin of `Endpoint`; what it uses of the rest is declared below)."""

    if TYPE_CHECKING:
        carrier: Wire
        _cond: threading.Condition
        auth: Auth | None
        _dests: dict[Address, Dest]
        clock: Callable[[], float]
        pace: Callable[[], float]
        _fast_at: dict[Address, float]
        _heads: dict[str, bytes]
        _head_opens: dict[str, bytes]
        _id_prefix: str
        _seq: itertools.count[int]
        _stopping: bool
        _threads: list[threading.Thread]
        _udp_frame: int
        address: Address
        inst: str
        name: str
        queue_limit: int
        ttl: float
        role: str
        sessions: SessionTable
        def send(self, addr: Address, kind: str, body: Any = None, *, reliable: bool, msg_id: str | None = None,
                 ttl: float | None = None, to: str | None = None) -> str: ...
        def _dest_for(self, addr: Address) -> Dest: ...
        def _frame(self, out: Outgoing, session: Session | None, max_frame: int) -> bytes: ...
        def _outgoing(self, msg_id: str, kind: str, type_name: str | None, body: Any, data: bytes, seq: int,
                      ttl: float | None, to: str | None) -> Outgoing: ...
        def _queue(self, addr: Address, out: Outgoing, lane: str) -> None: ...
        def _make_ready(self, dest: Dest) -> None: ...
        def _schedule(self, dest: Dest, when: float) -> None: ...
        def count(self, name: str, n: int = 1) -> None: ...
        def warn(self, reason: str, text: str) -> None: ...

    def _send_status(self, addr: Address, kind: str, body: Any, msg_id: str | None, ttl: float | None,
                     to: str | None) -> str:
        """`send` of a fast message (a status): sealed and handed to the socket from the caller's
        thread when that cannot wait, else queued for the sender pool; return its id.

        The common case, a status on its own in a confirmed session with the intended peer and
        nothing queued before it for that destination, is written here in one piece: the body's
        JSON, the message's around it (`_head_open`), sealed, handed to the UDP socket, which never
        blocks (MSG_DONTWAIT). Anything else (no session yet, a burst to gather, a queue to keep
        the order of, a full send buffer) takes the general way, `_send_now` and then the queue.
        """
        seq = next(self._seq)
        msg_id = msg_id or f"{self._id_prefix}{seq:x}"
        type_name, data = encode_body(body)
        sessions = self.sessions
        session = sessions.by_addr.get(addr) if self.auth is not None else None
        if session is not None and self._threads and not self._stopping and not session.stale \
                and session.sid in sessions.by_sid and not (to and to != session.peer):
            dest = self._dests.get(addr)
            fast_at = self._fast_at
            if (dest is None or not (dest.fast or dest.announce)) and not self._gathers(addr, dest, self.pace()):
                head = self._head_opens.get(session.peer) or self._head_open(session.peer)
                try:
                    self.carrier.sendto(session.seal(b'%b"seq":%d,"id":%b,%b,"body":%b}' % (
                        head, seq, to_json(msg_id), kind_and_type(kind, type_name), data), self._udp_frame), addr)
                except (OSError, FrameError) as err:
                    dropped = self._unsent(addr, err)  # True: too big, or an error; False: the buffer is full
                    fast_at[addr] = self.pace()
                    if dropped:
                        return msg_id
                    self.count("sent.deferred")  # the pool sends it when the buffer drains
                    self._queue(addr, self._outgoing(msg_id, kind, type_name, body, data, seq, ttl, to), "fast")
                    return msg_id
                self.count("sent.fast")
                fast_at[addr] = self.pace()  # a burst is told by the time until the next
                return msg_id
        out = self._outgoing(msg_id, kind, type_name, body, data, seq, ttl, to)
        if not self._send_now(addr, out):
            self._queue(addr, out, "fast")
        return msg_id

    def _send_now(self, addr: Address, out: Outgoing) -> bool:
        """Send a fast message from the caller's thread when that cannot wait: True when it is done.
        Note when the caller's send to `addr` was handled, sent or not (`_fast_at`).

        Only in a confirmed session (no handshake to drive) with the intended peer, with nothing
        queued before it for that destination, and only what the socket takes at once: the UDP
        socket never blocks (a full send buffer raises at once), and then the message is queued
        for the sender pool. A status of a burst (`COALESCE`) is gathered into the destination's
        batch instead.
        """
        sent = False
        try:
            if not self._threads or self._stopping:
                return False
            dest = self._dests.get(addr)
            if dest is not None and (dest.fast or dest.announce):
                return False  # keep the order of what is queued already
            if self.auth is None:
                single = self._batch(None)
                single.add(out, b"")
                sent = self._send_datagram(addr, single)
            else:
                session = self.sessions.usable(addr)
                if session is None or out.to and out.to != session.peer:
                    return False  # a handshake to drive, or a wrong peer to report: the sender pool's work
                if self._gathers(addr, dest, self.pace()):
                    return self._gather(addr, out, session)  # a burst: several statuses to a datagram
                single = self._batch(session)
                single.add(out, self._item(out))
                sent = self._send_datagram(addr, single)
            if not sent:
                self.count("sent.deferred")  # the socket's buffer is full: the pool sends it when it drains
            return sent
        finally:
            self._fast_at[addr] = self.pace()

    def _gathers(self, addr: Address, dest: Dest | None, now: float) -> bool:
        """Whether a status to `addr` now joins a batch: one is being gathered there, or it follows
        the caller's previous status there within `COALESCE` (a burst) while gathering is on there
        (not within `SOLO_FOR` of a batch of one)."""
        if dest is not None and dest.batch is not None:
            return True
        return now - self._fast_at.get(addr, -math.inf) < COALESCE and (dest is None or now >= dest.solo_until)

    def send_fanout(self, targets: Sequence[tuple[Address, str]], kind: str, body: Any) -> str:
        """Send one fast message (a status) to each `(address, agent)` of `targets`; return its id.

        The body is encoded once and the message is one message, with one id and one number, for
        every peer (each receives it once). To each peer in a confirmed session with nothing queued
        before it, the caller seals it in that session; once all are sealed, the datagrams go to
        the socket back to back (no Python between two `sendto`, so the peers it wakes all have
        theirs when the caller leaves the CPU). Any other peer (no session yet, messages queued
        for it, a burst being gathered, a full socket buffer) gets it through `send`, as before.
        """
        seq = next(self._seq)
        msg_id = f"{self._id_prefix}{seq:x}"
        later: list[tuple[Address, str]] = []
        frames: list[tuple[bytes, Address, str]] = []
        if not self._threads or self._stopping:
            later = list(targets)
        else:
            type_name, data = encode_body(body)
            item = item_bytes(seq, msg_id, kind, type_name, data)
            recent = self.pace() - COALESCE
            dests = self._dests
            fast_at = self._fast_at
            for addr, to in targets:
                session = self.sessions.usable(addr) if self.auth is not None else None
                dest = dests.get(addr)
                if session is None or session.peer != to or fast_at.get(addr, -math.inf) > recent \
                        or dest is not None and (dest.fast or dest.announce or dest.batch is not None):
                    later.append((addr, to))  # the general path: a handshake, an order to keep, a burst
                    continue
                try:
                    frames.append((session.seal(join_envelope(self._head(to), item), self._udp_frame), addr, to))
                except FrameError as err:
                    self._unsent(addr, err)
        sent = 0
        sendto = self.carrier.sendto
        for frame, addr, to in frames:
            try:
                sendto(frame, addr)
                sent += 1
            except OSError as err:
                if not self._unsent(addr, err):  # the socket's buffer is full: the pool sends it
                    later.append((addr, to))
        if frames:
            now = self.pace()
            for _, addr, _ in frames:
                self._fast_at[addr] = now  # a burst is told by the time until the next
        if sent:
            self.count("sent.fast", sent)
        for addr, to in later:
            self.send(addr, kind, body, reliable=False, msg_id=msg_id, to=to)
        return msg_id

    def _unsent(self, addr: Address, err: OSError | FrameError) -> bool:
        """Count and report a datagram of fast messages that did not leave; False when only the
        socket's buffer was full (the sender pool sends it when it drains), True when it is dropped."""
        if isinstance(err, BlockingIOError | InterruptedError):
            return False
        if isinstance(err, FrameError):
            self.count("dropped.too_big")
            self.warn("too_big", f"not sent to {addr}: {err}")
        else:
            self.count("dropped.fast_error")
            self.warn("udp", f"UDP send to {addr[0]}:{addr[1]} failed: {err}")
        return True

    def _gather(self, addr: Address, out: Outgoing, session: Session) -> bool:
        """Add a status of a burst to its destination's open batch; send the batch from the
        caller's thread once the next would not fit, and leave what is left at the burst's end
        to the sender pool (`FLUSH_AFTER`)."""
        item = self._item(out)
        full: Batch | None = None
        with self._cond:
            if self._stopping:
                return True
            dest = self._dest_for(addr)
            if dest.fast or dest.announce:
                return False  # queued meanwhile: it goes after them, in order
            batch = dest.batch
            if batch is not None and (batch.session is not session or not batch.fits(item)):
                full, batch = batch, None
                dest.full_at = self.pace()  # a real burst: it filled a datagram
            if batch is None:
                batch = dest.batch = self._batch(session)
                self._schedule(dest, self.pace() + FLUSH_AFTER)
            batch.add(out, item)
        if full is not None and not self._send_datagram(addr, full):
            self._requeue(dest, full.outs)
            with self._cond:
                self._make_ready(dest)
        return True

    def _send_datagram(self, addr: Address, batch: Batch) -> bool:
        """Send a batch of fast messages as one datagram. False when the socket's buffer is full
        (nothing was sent)."""
        max_frame = self._udp_frame
        outs = batch.outs
        try:
            if batch.session is None:
                frame = self._frame(outs[0], None, max_frame)
            else:
                frame = batch.session.seal(batch_payload(batch.head, batch.items), max_frame)
            self.carrier.sendto(frame, addr)
        except (OSError, FrameError) as err:
            return self._unsent(addr, err)
        self.count("sent.fast", len(outs))
        if len(outs) > 1:
            self.count("sent.batched", len(outs))
        return True

    def _send_fast(self, dest: Dest, session: Session | None, outs: list[Outgoing]) -> float | None:
        """Send queued fast messages, in a session as many to a datagram as fit in `BATCH_BYTES`;
        return when to try again if the socket's buffer is full (what is left goes back in front)."""
        batch = self._batch(session)
        for k, out in enumerate(outs):
            if session is not None and out.to and out.to != session.peer:
                self.count("dropped.wrong_peer")
                self.warn("wrong_peer", f"not sent: {dest.addr[0]}:{dest.addr[1]} is "
                                    f"{session.peer}, not {out.to}")
                continue
            item = self._item(out) if session is not None else b""
            if not batch.fits(item):
                if not self._send_datagram(dest.addr, batch):
                    self._requeue(dest, batch.outs + outs[k:])
                    return self.pace() + 0.005
                batch = self._batch(session)
            batch.add(out, item)
        if batch.outs and not self._send_datagram(dest.addr, batch):
            self._requeue(dest, batch.outs)
            return self.pace() + 0.005
        return None

    def _requeue(self, dest: Dest, outs: list[Outgoing]) -> None:
        """Put fast messages the socket did not take back in front of the queue, in their order."""
        with self._cond:
            room = max(0, self.queue_limit - len(dest.fast))
            dest.fast.extendleft(reversed(outs[:room]))
            if len(outs) > room:
                self.count("dropped.fast_oldest", len(outs) - room)
        self.count("sent.deferred")

    def _head_open(self, peer: str) -> bytes:
        """`_head` without its closing brace, and a comma: the start of one message's envelope."""
        head = self._head_opens.get(peer)
        if head is None:
            if len(self._head_opens) >= 4096:
                self._head_opens.clear()
            head = self._head_opens[peer] = self._head(peer)[:-1] + b","
        return head

    def _head(self, peer: str) -> bytes:
        """The envelope head of every message to `peer` (our own fields, made once per peer)."""
        head = self._heads.get(peer)
        if head is None:
            if len(self._heads) >= 4096:
                self._heads.clear()
            head = self._heads[peer] = head_bytes(self.name, self.role, peer, self.inst, self.address)
        return head

    def _batch(self, session: Session | None) -> Batch:
        """An empty datagram for messages to `session`'s peer, with the head they will share."""
        batch = Batch(None) if session is None else Batch(session, self._head(session.peer))
        if self.carrier.batch_limit is not None:
            batch.limit = self.carrier.batch_limit
        return batch

    def _item(self, out: Outgoing) -> bytes:
        return item_bytes(out.seq, out.id, out.kind, out.type, out.data)
