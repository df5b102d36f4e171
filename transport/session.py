"""Sessions between two agent instances: a signed handshake with fresh ephemeral keys, then AEAD frames.

Handshake, over UDP, retransmitted by the initiator I until the responder R answers:

    I -> R  'H' {sender, role, to, inst, reply, eph, nonce, crl}            + proof of I
    R -> I  'R' {sender, role, to, inst, reply, eph, nonce, crl, answers}   + proof of R

`eph` is a fresh X25519 public key, `nonce` 16 fresh random bytes, `to` the name the sender
expects at the other end, `answers` the SHA-256 of the 'H' frame answered, `crl` the number of
the sender's revocation list. The proof is, with identities, the sender's certificate and its
Ed25519 signature over the frame; with a shared team key, an HMAC-SHA256 under a key derived
from it. Both sides then derive

    HKDF-SHA256(ikm = X25519(eph_I, eph_R) [|| team key], salt = nonce_I || nonce_R,
                info = "erni/2 session" || SHA-256(H || R))  ->  key I->R | key R->I | session id (8)

and every data frame is `LEN | 'D' | session id | counter | ChaCha20-Poly1305(envelope)` with
the header as associated data, the counter as nonce (one key per direction), and a sliding
replay window per session. I trusts the session on a valid 'R' (signed by the peer over its own
fresh nonce); R trusts it on the first data frame (proof that I holds the ephemeral key of this
handshake: a replayed 'H' never gets that far). A session lives in memory only: a frame
captured under it is useless at any other agent, in any other session and after either side
restarts, and no wall clock is involved anywhere.
"""

from __future__ import annotations

import hashlib
import hmac
import itertools
import os
import struct
import threading
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Protocol

from cryptography.exceptions import InvalidSignature, InvalidTag
from cryptography.hazmat.primitives import hashes
from cryptography.hazmat.primitives.asymmetric.x25519 import X25519PrivateKey, X25519PublicKey
from cryptography.hazmat.primitives.ciphers.aead import ChaCha20Poly1305
from cryptography.hazmat.primitives.kdf.hkdf import HKDF
from cryptography.x509.oid import NameOID
from pydantic import ConfigDict, Field, ValidationError

from erni.blackboard.clock import SYSTEM, monotonic
from erni.blackboard.objects import Model
from erni.blackboard.text import Name, NameOrEmpty
from erni.transport.identity import Identity, IdentityError
from erni.transport.wire import (
    BEACON,
    DATA,
    DATA_HEADER,
    HEADER,
    HELLO,
    KIND,
    KINDS,
    REPLY,
    TAG_SIZE,
    FrameError,
    ReplayWindow,
    check_frame,
)

Address = tuple[str, int]
U16 = struct.Struct(">H")
DOMAIN = b"erni/2 signed frame\x00"
_HEX32 = r"^[0-9a-f]{32}$"
_HEX64 = r"^[0-9a-f]{64}$"


class Hello(Model):
    """The body of a handshake frame ('H' from the initiator, 'R' from the responder)."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    sender: Name
    role: str = Field("", max_length=32)
    to: NameOrEmpty = ""
    inst: str = Field(pattern=_HEX32)
    reply: tuple[str, int]
    eph: str = Field(pattern=_HEX64)
    nonce: str = Field(pattern=_HEX32)
    crl: int = Field(0, ge=0, le=2**63)
    answers: str = Field("", pattern=r"^([0-9a-f]{64})?$")


@dataclass(frozen=True)
class Signed:
    """A signed frame cut into its parts."""

    kind: int
    body: bytes
    cert: bytes
    signed: bytes
    proof: bytes


def cut_signed(frame: bytes, max_frame: int) -> Signed:
    """Cut an 'H', 'R' or 'B' frame; raise FrameError('size'|'parse') if it does not hold together."""
    kind = check_frame(frame, max_frame)
    if kind not in (HELLO, REPLY, BEACON):
        raise FrameError("parse", f"expected a signed frame, got a {KINDS[kind]} frame")
    at = KIND.size
    if len(frame) < at + 2:
        raise FrameError("size", "signed frame cut short before its body")
    (blen,) = U16.unpack_from(frame, at)
    body = frame[at + 2:at + 2 + blen]
    at += 2 + blen
    if len(body) != blen or len(frame) < at + 2:
        raise FrameError("size", "signed frame cut short in its body")
    (clen,) = U16.unpack_from(frame, at)
    cert = frame[at + 2:at + 2 + clen]
    at += 2 + clen
    if len(cert) != clen:
        raise FrameError("size", "signed frame cut short in its certificate")
    return Signed(kind, body, cert, frame[:at], frame[at:])


class Auth(Protocol):
    """How this endpoint proves who it is in handshakes and beacons, and checks others."""

    name: str
    role: str
    secret: bytes  # mixed into session keys (the team key; empty with identities)

    @property
    def crl_number(self) -> int: ...

    def sign(self, kind: int, body: bytes) -> bytes: ...

    def verify(self, signed: Signed, sender: str, role: str) -> int | None: ...


class CertificateRefused(FrameError):
    """A signed frame whose certificate this endpoint does not trust: its sender may be told why."""


class IdentityAuth:
    """Proof by certificate: each agent signs with its own key; the team authority vouches for it."""

    def __init__(self, identity: Identity):
        self.identity = identity
        self.name, self.role, self.secret = identity.name, identity.role, b""

    @property
    def crl_number(self) -> int:
        return self.identity.trust.crl_number

    def sign(self, kind: int, body: bytes) -> bytes:
        cert = self.identity.cert_der
        length = 1 + 2 + len(body) + 2 + len(cert) + 64
        head = KIND.pack(length, kind) + U16.pack(len(body)) + body + U16.pack(len(cert)) + cert
        return head + self.identity.sign(DOMAIN + head)

    def trusted(self) -> str:
        """The authority this endpoint trusts, as a refusal names it."""
        trust = self.identity.trust
        names = trust.authority.subject.get_attributes_for_oid(NameOID.COMMON_NAME)
        name = str(names[0].value) if names else "?"
        return f"the authority {name!r} (fingerprint {trust.fingerprint})"

    def verify(self, signed: Signed, sender: str, role: str) -> int | None:
        """Return the certificate's serial; raise FrameError('auth'|'revoked'), or CertificateRefused
        when the certificate itself is not trusted (another authority's, revoked, malformed)."""
        try:
            who = self.identity.trust.check(signed.cert)
        except IdentityError as err:
            raise CertificateRefused("revoked" if "revoked" in str(err) else "auth", str(err)) from None
        if who.name != sender or who.role != role:
            raise FrameError("auth", f"certificate of {who.name} ({who.role}) but the frame claims "
                             f"{sender[:64]} ({role[:32]})")
        try:
            who.key.verify(signed.proof, DOMAIN + signed.signed)
        except InvalidSignature:
            raise FrameError("auth", f"signature of {who.name} does not verify") from None
        return who.serial


class TeamKeyAuth:
    """Proof by a shared team key: any holder of the key can claim any name (see docs/explanation/reliability.md)."""

    def __init__(self, name: str, role: str, key: bytes):
        self.name, self.role = name, role
        self.secret = key
        self._mac_key = HKDF(hashes.SHA256(), 32, salt=None, info=b"erni/2 team key proof").derive(key)

    @property
    def crl_number(self) -> int:
        return 0

    def sign(self, kind: int, body: bytes) -> bytes:
        length = 1 + 2 + len(body) + 2 + 32
        head = KIND.pack(length, kind) + U16.pack(len(body)) + body + U16.pack(0)
        return head + hmac.new(self._mac_key, DOMAIN + head, hashlib.sha256).digest()

    def verify(self, signed: Signed, sender: str, role: str) -> int | None:
        expect = hmac.new(self._mac_key, DOMAIN + signed.signed, hashlib.sha256).digest()
        if signed.cert or not hmac.compare_digest(expect, signed.proof):
            raise FrameError("auth", "frame not signed with the team key")
        return None


def parse_hello(body: bytes) -> Hello:
    """Validate a handshake body; raise FrameError('parse', ...)."""
    try:
        return Hello.model_validate_json(body)
    except ValidationError as err:
        first = err.errors()[0]
        where = ".".join(str(p) for p in first["loc"]) or "hello"
        raise FrameError("parse", f"handshake field {where}: {first['msg']}") from None


_NONCE = struct.Struct(">4xQ")  # a frame's counter as its 12-byte nonce
_nonce = _NONCE.pack
_COUNTER = struct.Struct(">Q")
_COUNTER_AT = DATA_HEADER.size - _COUNTER.size  # where a data frame's counter is
_counter_of = _COUNTER.unpack_from
_HEAD = DATA_HEADER.size  # a data frame's header: the associated data; the ciphertext follows
_pack_head = DATA_HEADER.pack
_SHORTEST = _HEAD + TAG_SIZE  # a data frame with nothing sealed in it
_PREFIX = HEADER.size  # the length prefix, not counted in a frame's declared length
_GROWTH = _HEAD - _PREFIX + TAG_SIZE  # what sealing adds to a payload's declared length


class Session:
    """Keys, counters and the replay window of one session with one peer instance."""

    def __init__(self, sid: bytes, send_key: bytes, recv_key: bytes, hello: Hello, serial: int | None,
                 initiator: bool, clock: Callable[[], float] = SYSTEM):
        self.sid = sid
        self._clock = clock  # the endpoint's: when the session was last used, for the idle sweep
        self._send = ChaCha20Poly1305(send_key)
        self._recv = ChaCha20Poly1305(recv_key)
        self._counter = itertools.count(1)
        self._window = ReplayWindow()
        self._lock = threading.Lock()
        self.peer, self.role, self.inst = hello.sender, hello.role, hello.inst
        self.addr: Address = (hello.reply[0], hello.reply[1])
        self.crl = hello.crl
        self.serial = serial
        self.initiator = initiator
        self.confirmed = initiator
        self.epoch = 0  # the receiver's count of this peer's instances, set when confirmed
        self.created = self.last_rx = self.last_tx = clock()
        self.stale = 0.0  # when the peer said it does not know this session (0: never)

    def seal(self, payload: bytes, max_frame: int) -> bytes:
        """Encrypt an envelope into a data frame (FrameError('size') when too big)."""
        length = _GROWTH + len(payload)
        if length + _PREFIX > max_frame:
            raise FrameError("size", f"frame of {length + _PREFIX} bytes exceeds the limit of {max_frame}")
        counter = next(self._counter)
        head = _pack_head(length, DATA, self.sid, counter)
        self.last_tx = self._clock()
        return head + self._send.encrypt(_nonce(counter), payload, head)

    def open(self, frame: bytes) -> bytes:
        """Authenticate and decrypt a data frame of this session; raise FrameError('short'|'auth'|'replay')."""
        if len(frame) < _SHORTEST:
            raise FrameError("short", f"data frame of {len(frame)} bytes is shorter than a header and its tag "
                             f"({_SHORTEST} bytes; from {self.peer})")
        (counter,) = _counter_of(frame, _COUNTER_AT)
        window = self._window
        if counter <= window.top:
            window.fresh(counter)  # a cheap early refusal of a replay; checked again under the lock below
        try:
            plain = self._recv.decrypt(_nonce(counter), frame[_HEAD:], frame[:_HEAD])
        except InvalidTag:
            raise FrameError("auth", f"data frame does not authenticate in its session (from {self.peer})") from None
        with self._lock:
            window.check(counter)  # again: another thread may have taken it meanwhile
        self.last_rx = self._clock()
        return plain


def _derive(shared: bytes, secret: bytes, nonce_i: bytes, nonce_r: bytes, transcript: bytes) -> tuple[bytes, bytes, bytes]:
    okm = HKDF(hashes.SHA256(), 72, salt=nonce_i + nonce_r,
               info=b"erni/2 session" + transcript).derive(shared + secret)
    return okm[:32], okm[32:64], okm[64:]


def _exchange(private: X25519PrivateKey, public_hex: str) -> bytes:
    try:
        return private.exchange(X25519PublicKey.from_public_bytes(bytes.fromhex(public_hex)))
    except ValueError:  # a low-order point gives an all-zero secret: refused
        raise FrameError("auth", "handshake key is not usable") from None


PATIENCE_GROWTH = 8
"""A handshake with a destination whose last ones went unanswered waits up to this many times the
endpoint's `handshake_timeout` (doubling with each one given up in a row): on a machine so busy
that an answer takes longer than the timeout, a fixed timeout gives up every handshake just
before its answer arrives, and each new one costs both sides its keys and signatures again."""


def patience(timeout: float, failures: int) -> float:
    """How long a handshake waits for its answer after `failures` given up in a row."""
    return timeout * min(PATIENCE_GROWTH, 1 << failures)


@dataclass
class Initiation:
    """A handshake this endpoint started: what it sent, and what it needs to finish it."""

    addr: Address
    expect: str
    frame: bytes
    digest: str
    private: X25519PrivateKey
    nonce: bytes
    started: float = field(default_factory=monotonic)
    attempts: int = 0
    next_try: float = 0.0


def initiate(auth: Auth, inst: str, reply: Address, addr: Address, expect: str,
             clock: Callable[[], float] = SYSTEM) -> Initiation:
    """Build an 'H' frame to `addr` (expecting agent `expect`, '' when unknown)."""
    private = X25519PrivateKey.generate()
    nonce = os.urandom(16)
    hello = Hello(sender=auth.name, role=auth.role, to=expect, inst=inst, reply=reply,
                  eph=private.public_key().public_bytes_raw().hex(), nonce=nonce.hex(), crl=auth.crl_number)
    frame = auth.sign(HELLO, hello.model_dump_json().encode())
    return Initiation(addr, expect, frame, hashlib.sha256(frame).hexdigest(), private, nonce, clock())


def respond(auth: Auth, hello: Hello, hello_frame: bytes, serial: int | None, inst: str,
            reply: Address, clock: Callable[[], float] = SYSTEM) -> tuple[bytes, Session]:
    """Answer a verified 'H': return the 'R' frame and the (not yet confirmed) session."""
    private = X25519PrivateKey.generate()
    shared = _exchange(private, hello.eph)
    nonce = os.urandom(16)
    answer = Hello(sender=auth.name, role=auth.role, to=hello.sender, inst=inst, reply=reply,
                   eph=private.public_key().public_bytes_raw().hex(), nonce=nonce.hex(), crl=auth.crl_number,
                   answers=hashlib.sha256(hello_frame).hexdigest())
    frame = auth.sign(REPLY, answer.model_dump_json().encode())
    transcript = hashlib.sha256(hello_frame + frame).digest()
    to_r, to_i, sid = _derive(shared, auth.secret, bytes.fromhex(hello.nonce), nonce, transcript)
    return frame, Session(sid, to_i, to_r, hello, serial, initiator=False, clock=clock)


def complete(auth: Auth, init: Initiation, answer: Hello, answer_frame: bytes, serial: int | None,
             clock: Callable[[], float] = SYSTEM) -> Session:
    """Finish a handshake with a verified 'R': return the confirmed session."""
    shared = _exchange(init.private, answer.eph)
    transcript = hashlib.sha256(init.frame + answer_frame).digest()
    to_r, to_i, sid = _derive(shared, auth.secret, init.nonce, bytes.fromhex(answer.nonce), transcript)
    return Session(sid, to_r, to_i, answer, serial, initiator=True, clock=clock)
