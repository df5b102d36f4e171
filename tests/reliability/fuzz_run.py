"""Fuzzing at scale, on demand: every input surface, 100,000 generated inputs each.

    python -m tests.reliability.fuzz_run                          # 100,000 inputs per surface
    python -m tests.reliability.fuzz_run -n 2000 -s "spoken phrases" -s "replay logs"
    python -m tests.reliability.fuzz_run -n 2000 --coverage -s "frames after authentication"

Each surface is a generator (seeded `random.Random`: mutated valid inputs, which reach deep, and
noise) and a check that feeds one input to the same parsing and validation code the product runs
on it. An input may be accepted or refused with the surface's own error type; anything else
escaping, a traceback logged by the product (a handler that swallowed a bug), or an input taking
longer than `--hang` seconds counts as a crash. The run prints inputs, crashes and time per
surface, a reproducer for the first crashes of each, and writes the counts to
`artifacts/fuzz-counts.json` (key "scale"). Five surfaces (`fuzz_deep.py`) follow their input past
the parser onto a blackboard and into the page state, with invariants as oracles: a broken one is a
`Violation`, counted apart from crashes. `--coverage` adds, per surface, the statements of the handler
modules (`HANDLERS`) its inputs ran. The CI run of `test_fuzz_scale.py` drives every surface
with a few hundred inputs through the same code.

Surfaces behind sockets are driven in process, through the function the socket's reader calls:
`Endpoint.accept_frame` (UDP datagram or TCP frame), `ManetSnmpAgent.handle` (the node's datagram
handler), and `SnmpSource` with its UDP exchange replaced by a call to the simulated node and the
answer decoded by the client's own `ber.decode_response`.
"""

from __future__ import annotations

import argparse
import asyncio
import json
import logging
import os
import random
import signal
import string
import subprocess
import sys
import tempfile
import time
import traceback
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from erni.blackboard.testing import wait_until

ROOT = Path(__file__).resolve().parents[2]
Check = Callable[[Any], None]
Gen = Callable[[random.Random], Any]


def confirmed(a: Any, b: Any) -> bool:
    """Whether endpoint `a` holds a confirmed session to send to `b`."""
    s = a.session_with(b.address)
    return s is not None and bool(s.confirmed)


class Hang(BaseException):
    """One input took longer than the hang limit."""


class Violation(Exception):
    """An input broke an invariant of the product (a non-finite number on the blackboard or the page, a
    control character in printed text, a name out of its character set, state per sender growing):
    counted apart from crashes."""


# --- generators ---------------------------------------------------------------------------------

INTERESTING = [0x00, 0x01, 0x7F, 0x80, 0x81, 0xFF, 0xFE, 0x30, 0x02, 0x04, 0x06, 0x22, 0x7B, 0x5B, 0x5D, 0x7D]


def mutate(rng: random.Random, seed: bytes, others: list[bytes] | None = None) -> bytes:
    """A valid input, damaged 1-8 times: bit flips, interesting bytes, inserts, deletes, cuts,
    repeats, splices with another valid input."""
    b = bytearray(seed)
    for _ in range(rng.randint(1, 8)):
        op = rng.randrange(8)
        n = len(b)
        if op == 0 and n:
            b[rng.randrange(n)] ^= 1 << rng.randrange(8)
        elif op == 1 and n:
            b[rng.randrange(n)] = rng.choice(INTERESTING)
        elif op == 2:
            at = rng.randint(0, n)
            b[at:at] = rng.randbytes(rng.randint(1, 16))
        elif op == 3 and n:
            at = rng.randrange(n)
            del b[at:at + rng.randint(1, 16)]
        elif op == 4 and n:
            del b[rng.randint(0, n):]
        elif op == 5 and n:
            at = rng.randrange(n)
            chunk = b[at:at + rng.randint(1, 32)]
            b[at:at] = chunk * rng.randint(1, 4)
        elif op == 6 and others:
            other = rng.choice(others)
            b = b[:rng.randint(0, n)] + other[rng.randint(0, len(other)):]
        elif op == 7 and n:
            b[rng.randrange(n)] = rng.randrange(256)
    return bytes(b)


def damaged(rng: random.Random, seeds: list[bytes], noise_share: float = 0.15, most: int = 400) -> bytes:
    if rng.random() < noise_share:
        return rng.randbytes(rng.randint(0, most))
    seed = rng.choice(seeds)
    return seed if rng.random() < 0.02 else mutate(rng, seed, seeds)


TEXT = string.printable + "éß€☃\u0000\u200b\ud7ff\U0001f916"


def text(rng: random.Random, most: int = 12) -> str:
    return "".join(rng.choice(TEXT) for _ in range(rng.randint(0, most)))


def number(rng: random.Random) -> Any:
    return rng.choice([
        0, 1, -1, rng.randint(-10, 10), rng.randint(-2**63, 2**63), 2**64, 10**400 if rng.random() < 0.05 else 7,
        rng.uniform(-1e3, 1e3), rng.choice([1e300, -1e300, 5e-324, float("inf"), float("-inf"), float("nan")]),
        0.5, -0.0])


def value(rng: random.Random, depth: int = 0, keys: list[str] | None = None) -> Any:
    """Any JSON-ish value: scalars of every type and edge, lists and objects (with `keys` likely)."""
    r = rng.random()
    if depth > 3 or r < 0.55:
        return rng.choice([None, True, False, number(rng), number(rng), text(rng), text(rng, 40), ""])
    if r < 0.75:
        return [value(rng, depth + 1, keys) for _ in range(rng.randint(0, 4))]
    return {(rng.choice(keys) if keys and rng.random() < 0.8 else text(rng, 8)): value(rng, depth + 1, keys)
            for _ in range(rng.randint(0, 5))}


def dumps(obj: Any) -> str:
    return json.dumps(obj, allow_nan=True, default=str)


def mutated_json(rng: random.Random, valid: list[dict[str, Any]], keys: list[str]) -> Any:
    """A valid object with fields replaced, dropped or added, or a fresh object of the known keys."""
    if rng.random() < 0.3:
        return {k: value(rng, 1, keys) for k in rng.sample(keys, rng.randint(0, len(keys)))}
    obj = dict(rng.choice(valid))
    for _ in range(rng.randint(1, 4)):
        op = rng.randrange(4)
        k = rng.choice(keys)
        if op == 0 and obj:
            obj.pop(rng.choice(list(obj)))
        elif op == 3 and isinstance(obj.get(k), dict):
            inner = dict(obj[k])
            inner[rng.choice(list(inner) or [text(rng, 6)])] = value(rng, 2, keys)
            obj[k] = inner
        else:
            obj[k] = value(rng, 1, keys)
    return obj


def as_text(rng: random.Random, obj: Any, seeds: list[bytes]) -> bytes:
    """The object as JSON, sometimes damaged as bytes (then the parser sees broken JSON)."""
    raw = dumps(obj).encode()
    if rng.random() < 0.25:
        return mutate(rng, raw, seeds)
    if rng.random() < 0.03:
        d = rng.randint(50, 5000)
        return (b"[" * d + b"]" * d) if rng.random() < 0.5 else (b'{"a":' * d + b"1" + b"}" * d)
    return raw


# --- surfaces -----------------------------------------------------------------------------------


SURFACES: dict[str, tuple[str, Callable[..., tuple[Gen, Check]]]] = {}


def surface(name: str, what: str) -> Callable[[Callable[..., tuple[Gen, Check]]], Callable[..., tuple[Gen, Check]]]:
    def register(fn: Callable[..., tuple[Gen, Check]]) -> Callable[..., tuple[Gen, Check]]:
        SURFACES[name] = (what, fn)
        return fn
    return register


class Team:
    """A receiving endpoint with an identity and a live session from a peer (rate limits out of
    the way), shared by the transport surfaces."""

    def __init__(self) -> None:
        from erni.transport.endpoint import Endpoint
        from erni.transport.identity import load_identity
        from erni.transport.limits import Limits
        from tests.transport.helpers import authority, identity

        limits = Limits(handshakes_per_host=1e9, handshakes_total=1e9, beacons_total=1e9)
        self.rx = Endpoint("fuzz-rx", identity=load_identity(identity("fuzz-rx"), authority().dir / "revoked.crl"),
                           limits=limits)
        self.tx = Endpoint("fuzz-tx", identity=load_identity(identity("fuzz-tx")), limits=limits)
        self.rx.start()
        self.tx.start()
        self.tx.send(self.rx.address, "hello", None, reliable=True)
        wait_until(lambda: confirmed(self.tx, self.rx) and confirmed(self.rx, self.tx), timeout=10, interval=0.01,
                   message="fuzz endpoints did not connect")
        self.session = self.tx.session_with(self.rx.address)

    def accept(self, frame: bytes) -> None:
        got = self.rx.accept_frame(frame, "udp", ("127.0.0.1", 9))   # None or verified messages; raises nothing
        if got is not None and not all(m.sender == "fuzz-tx" for m in got[0]):
            raise AssertionError(f"a message from {[m.sender for m in got[0]]} through fuzz-tx's session")

    def close(self) -> None:
        self.tx.stop()
        self.rx.stop()


_team: Team | None = None


def team() -> Team:
    global _team
    if _team is None:
        _team = Team()
    return _team


def _valid_envelope(tx: Any, kind: str = "task.add") -> Any:
    from erni.blackboard import Task
    from erni.transport.wire import Envelope

    task = Task(verb="BotMotion", preposition="goto", params={"x": 1, "y": 2})
    return Envelope(sender="fuzz-tx", role="robot", to="fuzz-rx", inst=tx.inst, reply=tx.address, seq=1, id="1",
                    kind=kind, type="Task", body=task.model_dump(mode="json"))


def framed(rng: random.Random, frame: bytes, others: list[bytes]) -> bytes:
    """A damaged frame whose length prefix mostly still matches (else nearly all stop at the size check);
    a signed frame is often damaged in one part (body, certificate, signature) and put back together."""
    import struct

    from erni.transport.session import cut_signed
    from erni.transport.wire import BEACON, HELLO, REPLY

    if frame[4] in (HELLO, REPLY, BEACON) and rng.random() < 0.5:
        s = cut_signed(frame, 65536)
        parts = [s.body, s.cert, s.proof]
        i = rng.randrange(3)
        parts[i] = mutate(rng, parts[i])[:60000]
        body, cert, proof = parts
        inner = bytes([s.kind]) + struct.pack(">H", len(body)) + body + struct.pack(">H", len(cert)) + cert + proof
        return struct.pack(">I", len(inner)) + inner
    out = mutate(rng, frame, others)
    if len(out) > 4 and rng.random() < 0.8:
        out = struct.pack(">I", len(out) - 4) + out[4:]
    return out


@surface("frames before authentication",
         "random bytes and mutated valid frames of every kind (sealed data, sealed batch, signed handshake, "
         "signed beacon, plain) through `Endpoint.accept_frame` and the TCP stream cutter")
def frames_before(_: argparse.Namespace) -> tuple[Gen, Check]:
    from erni.transport.session import initiate
    from erni.transport.wire import (
        BEACON,
        EnvelopeHead,
        EnvelopeItem,
        FrameError,
        StreamDecoder,
        batch_payload,
        encode_plain,
    )

    t = team()
    env = _valid_envelope(t.tx)
    beacon = env.model_copy(update={"kind": "beacon", "type": "Beacon", "body": {"role": "robot"}, "to": ""})
    status = env.model_copy(update={"kind": "status", "id": "2", "seq": 2})
    head = env.model_dump_json(include=set(EnvelopeHead.model_fields)).encode()
    items = [m.model_dump_json(include=set(EnvelopeItem.model_fields)).encode() for m in (env, status)]
    seeds = [t.session.seal(env.model_dump_json().encode(), 65536),
             initiate(t.tx.auth, t.tx.inst, t.tx.address, ("127.0.0.1", 9), "fuzz-rx").frame,
             t.tx.auth.sign(BEACON, beacon.model_dump_json().encode()),
             encode_plain(env),
             t.session.seal(batch_payload(head, items), 65536)]

    def check(frame: bytes) -> None:
        t.accept(frame)
        try:
            StreamDecoder(4096).feed(frame)
        except FrameError:
            pass

    def gen(rng: random.Random) -> bytes:
        if rng.random() < 0.15:
            return rng.randbytes(rng.randint(0, 600))
        return framed(rng, rng.choice(seeds), seeds)

    return gen, check


BODY_KEYS = ["verb", "preposition", "params", "uid", "source", "destination", "state", "x", "y", "name", "th",
             "result", "reason", "priority"]
ENVELOPE_KEYS = ["v", "sender", "role", "to", "inst", "reply", "seq", "id", "kind", "type", "body", "extra"]


@surface("frames after authentication",
         "what a key holder can send in its own session, sealed correctly: mutated valid envelopes and batches "
         "(any field any JSON value), any JSON, any bytes; through `Endpoint.accept_frame` (AEAD, replay window, "
         "envelope, batch and body validation)")
def frames_after(_: argparse.Namespace) -> tuple[Gen, Check]:
    from erni.transport.wire import TYPES, EnvelopeHead

    HEAD = set(EnvelopeHead.model_fields)
    t = team()
    valid = [json.loads(_valid_envelope(t.tx, k).model_dump_json()) for k in ("task.add", "status", "result")]
    seeds = [dumps(v).encode() for v in valid]
    seq = iter(range(10, 10**12))

    def gen(rng: random.Random) -> bytes:
        r = rng.random()
        if r < 0.1:
            return rng.randbytes(rng.randint(0, 300))
        obj = mutated_json(rng, valid, ENVELOPE_KEYS)
        if isinstance(obj, dict) and rng.random() < 0.7:
            obj["seq"] = next(seq)   # a fresh sequence number gets past the replay window to validation
        if isinstance(obj, dict) and r < 0.5:   # a well-formed envelope around a damaged body
            obj = dict(rng.choice(valid), seq=next(seq), type=rng.choice([*TYPES, "Nope", None]))
            obj["body"] = mutated_json(rng, [valid[0]["body"]], BODY_KEYS) if rng.random() < 0.8 else value(rng)
        if r < 0.25:   # a batch of statuses: [head, [item, ...]], head or items damaged
            head = {k: v for k, v in rng.choice(valid).items() if k in HEAD}
            if rng.random() < 0.3:
                head = mutated_json(rng, [head], list(HEAD))
            items = []
            for _ in range(rng.randint(0, 4)):
                item = {k: v for k, v in rng.choice(valid).items() if k not in HEAD or k == "v"}
                item = dict(mutated_json(rng, [item], ENVELOPE_KEYS) if rng.random() < 0.7 else item, seq=next(seq))
                if rng.random() < 0.5:
                    item["body"] = mutated_json(rng, [valid[0]["body"]], BODY_KEYS)
                items.append(item)
            return as_text(rng, [head, items], seeds)
        return as_text(rng, obj, seeds)

    return gen, lambda payload: t.accept(t.session.seal(payload, 65536))


HELLO_KEYS = ["sender", "role", "to", "inst", "reply", "eph", "nonce", "crl", "answers", "v", "extra"]


@surface("handshakes",
         "mutated signed hellos to the responder; mutated answers to a handshake of the receiver's own; hellos "
         "and answers with any field any JSON value, correctly signed by a key holder; through `Endpoint.accept_frame`")
def handshakes(_: argparse.Namespace) -> tuple[Gen, Check]:
    from erni.transport.session import REPLY, cut_signed, initiate, parse_hello, respond
    from erni.transport.wire import HELLO

    t = team()
    rx, tx = t.rx, t.tx
    state: dict[str, Any] = {}

    def fresh() -> None:
        init = initiate(rx.auth, rx.inst, rx.address, tx.address, "fuzz-tx")
        hello = parse_hello(cut_signed(init.frame, 65536).body)
        reply, _ = respond(tx.auth, hello, init.frame, None, tx.inst, tx.address)
        with rx.sessions.lock:
            rx.sessions.initiations[init.digest] = init
        state.update(init=init, reply=reply, reply_json=json.loads(cut_signed(reply, 65536).body))

    fresh()
    hello_frame = initiate(tx.auth, tx.inst, tx.address, rx.address, "fuzz-rx").frame
    hello_json = json.loads(cut_signed(hello_frame, 65536).body)

    def gen(rng: random.Random) -> bytes:
        if state["init"].digest not in rx.sessions.initiations:
            fresh()   # the last answer completed (or the endpoint expired) the pending handshake
        r = rng.random()
        if r < 0.3:
            return framed(rng, hello_frame, [state["reply"]])
        if r < 0.6:
            return framed(rng, state["reply"], [hello_frame])
        if r < 0.8:
            obj = mutated_json(rng, [hello_json], HELLO_KEYS)
            return tx.auth.sign(HELLO, as_text(rng, obj, []))
        obj = mutated_json(rng, [state["reply_json"]], HELLO_KEYS)
        if rng.random() < 0.7:
            obj["answers"] = state["init"].digest
        return tx.auth.sign(REPLY, as_text(rng, obj, []))

    return gen, t.accept


@surface("certificates and revocation lists",
         "noise and mutated valid DER (an agent's certificate, the authority's revocation list) through "
         "certificate checking and revocation-list adoption")
def certificates(_: argparse.Namespace) -> tuple[Gen, Check]:
    from erni.transport.identity import IdentityError

    t = team()
    trust = t.rx.identity.trust
    seeds = [t.tx.identity.cert_der, trust.crl_der]

    def check(der: bytes) -> None:
        try:
            trust.check(der)
        except IdentityError:
            pass
        if trust.adopt(der) not in (True, False):
            raise AssertionError("adopt answered neither True nor False")

    return (lambda rng: damaged(rng, seeds, 0.1, 600)), check


@surface("ARCOS bytes",
         "the robot's byte stream in random chunks: mutated SIP, CONFIG, SIMSTAT, battery and SYNC2 bodies "
         "re-framed with a valid checksum (so the parsers see them), damaged frames, noise; through "
         "`PacketReader` and the driver's packet parsers")
def arcos_bytes(_: argparse.Namespace) -> tuple[Gen, Check]:
    from erni.plugins.motion import arcos
    from erni.sim.robot import ArcosFirmware, SimRobot, SimRobotConfig

    fw = ArcosFirmware(SimRobot(SimRobotConfig(name="fuzz")))
    bodies = [fw.sip(), fw.config_packet(), fw.simstat_packet(), fw.battery_packet(),
              b"Pioneer\x00p3dx\x00fuzz\x00"]

    def gen(rng: random.Random) -> list[bytes]:
        stream = b""
        for _ in range(rng.randint(1, 4)):
            r = rng.random()
            body = mutate(rng, rng.choice(bodies), bodies) or b"\x32"
            if r < 0.6:
                stream += arcos.frame(body[:240])
            elif r < 0.85:
                stream += mutate(rng, arcos.frame(rng.choice(bodies)[:240]))
            else:
                stream += rng.randbytes(rng.randint(0, 80))
        cuts = sorted(rng.randint(0, len(stream)) for _ in range(rng.randint(0, 4)))
        return [stream[a:b] for a, b in zip([0, *cuts], [*cuts, len(stream)])]

    def check(chunks: list[bytes]) -> None:
        reader = arcos.PacketReader()
        for chunk in chunks:
            for body in reader.feed(chunk):
                try:   # the driver's dispatch (`Driver._packet`), and the SYNC2 answer of the handshake
                    if arcos.is_sip(body):
                        arcos.parse_sip(body)
                    elif body[0] == arcos.SIMSTAT_REPLY:
                        arcos.parse_simstat(body)
                    elif body[0] == arcos.BATTERY_REPLY:
                        arcos.parse_battery_info(body)
                    elif body[0] == arcos.CONFIG_REPLY:
                        arcos.parse_config(body)
                    else:
                        arcos.parse_sync2(body)
                except arcos.ProtocolError:
                    pass

    return gen, check


def _snmp_network() -> Any:
    from erni.sim.manet import ManetNetwork, RadioModel

    net = ManetNetwork(RadioModel(100.0, 50.0, 0.1))
    for i in range(5):
        net.add_node(f"n{i}", i * 60.0, 0.0)
    return net


def _snmp_requests() -> list[bytes]:
    from erni.plugins.mobinet import ber
    from erni.plugins.mobinet import snmp as mib

    oids = [mib.SYS_NAME, mib.SYS_UP_TIME, mib.NHDP_DISC_IF, mib.NHDP + (2,), (1, 3, 6, 1, 2, 1, 4, 24), (1, 3)]
    out = []
    for community in (b"public", b"fuzz-writer"):
        out += [ber.encode_request(ber.GET, community, 7, [(o, (ber.NULL, None)) for o in oids[:3]], 0, 0),
                ber.encode_request(ber.GET_NEXT, community, 8, [(o, (ber.NULL, None)) for o in oids], 0, 0),
                ber.encode_request(ber.GET_BULK, community, 9, [(o, (ber.NULL, None)) for o in oids[2:]], 1, 20)]
    position = [(mib.ERNI_POS_X, (ber.INTEGER, 1500)), (mib.ERNI_POS_Y, (ber.INTEGER, -2500)),
                (mib.ERNI_POS_HEADING, (ber.INTEGER, 9000))]
    out.append(ber.encode_request(ber.SET, b"fuzz-writer", 10, position, 0, 0))
    out.append(ber.encode_request(ber.SET, b"fuzz-writer", 11, [(mib.SYS_NAME, (ber.OCTET_STRING, b"x"))], 0, 0))
    v1 = bytearray(out[0])
    i = v1.index(b"\x02\x01\x01")   # version 1 (v2c) -> 0 (v1)
    v1[i + 2] = 0
    return out + [bytes(v1)]


EDGE_INTS = [0, 1, -1, 127, 128, 255, 256, 2**31 - 1, 2**31, -(2**31), -(2**31) - 1, 2**32 - 1, 2**32, 2**63,
             2**64 - 1, 2**64, -(2**63), 10**30]


def _ber_oid(oid: tuple[int, ...]) -> bytes:
    from erni.plugins.mobinet import ber

    if len(oid) < 2:
        return b"".join(ber._base128(max(0, a)) for a in oid)
    return b"".join(ber._base128(max(0, a)) for a in (oid[0] * 40 + oid[1], *oid[2:]))


def snmp_oid(rng: random.Random, known: list[tuple[int, ...]]) -> tuple[int, ...]:
    """A served OID, or one cut, extended or with an arc changed (to an edge value)."""
    oid = list(rng.choice(known))
    op = rng.randrange(5)
    if op == 1:
        oid = oid[:rng.randint(0, len(oid))]
    elif op == 2:
        oid += [rng.choice([0, 1, 255, rng.randrange(2**32), 2**64]) for _ in range(rng.randint(1, 4))]
    elif op == 3 and oid:
        oid[rng.randrange(len(oid))] = rng.choice([0, 1, 39, 40, 127, 128, 2**31, 2**32, 2**70])
    elif op == 4:
        oid = [rng.randrange(3), rng.randrange(40)] + [rng.randrange(300) for _ in range(rng.randint(0, 30))]
    return tuple(oid)


def snmp_value(rng: random.Random) -> bytes:
    """One varbind value of any tag, with edge contents (a wrong type, a wrong length, an empty one)."""
    from erni.plugins.mobinet import ber

    tag = rng.choice([ber.INTEGER, ber.OCTET_STRING, ber.NULL, ber.OBJECT_IDENTIFIER, ber.IP_ADDRESS, ber.COUNTER32,
                      ber.GAUGE32, ber.TIME_TICKS, ber.OPAQUE, ber.COUNTER64, ber.NO_SUCH_OBJECT,
                      ber.NO_SUCH_INSTANCE, ber.END_OF_MIB_VIEW, ber.SEQUENCE, rng.randrange(256)])
    r = rng.random()
    if r < 0.4:
        n = rng.choice(EDGE_INTS) if rng.random() < 0.7 else rng.randint(-(2**40), 2**40)
        content = n.to_bytes((n.bit_length() + 8) // 8 or 1, "big", signed=True)
    elif r < 0.6:
        content = rng.randbytes(rng.choice([0, 1, 3, 4, 5, 6, 16, rng.randint(0, 300)]))
    elif r < 0.7:
        content = _ber_oid(tuple(rng.randrange(2**rng.choice([2, 7, 32, 70])) for _ in range(rng.randint(0, 12))))
    else:
        content = b""
    return ber.tlv(tag, content)


def snmp_message(rng: random.Random, pdu: int, community: bytes, rid: int, a: int, b: int,
                 binds: list[tuple[tuple[int, ...], bytes]], version: int = 1) -> bytes:
    """A v1/v2c message from its parts, as an agent or a client encodes it (any value of every part)."""
    from erni.plugins.mobinet import ber

    def integer(n: int) -> bytes:
        return ber.tlv(ber.INTEGER, n.to_bytes((n.bit_length() + 8) // 8 or 1, "big", signed=True))

    body = b"".join(ber.tlv(ber.SEQUENCE, ber.tlv(ber.OBJECT_IDENTIFIER, _ber_oid(oid)) + value)
                    for oid, value in binds)
    pdu_body = integer(rid) + integer(a) + integer(b) + ber.tlv(ber.SEQUENCE, body)
    return ber.tlv(ber.SEQUENCE, integer(version) + ber.tlv(ber.OCTET_STRING, community) + ber.tlv(pdu, pdu_body))


def flipped(rng: random.Random, data: bytes) -> bytes:
    """Bytes changed in place (every length still holds)."""
    b = bytearray(data)
    for _ in range(rng.randint(1, 4)):
        if b:
            b[rng.randrange(len(b))] = rng.choice(INTERESTING) if rng.random() < 0.5 else rng.randrange(256)
    return bytes(b)


class _Traceback(logging.Handler):
    """Collects records that carry a traceback: a product handler that swallowed an exception."""

    def __init__(self) -> None:
        super().__init__(logging.DEBUG)
        self.seen: list[str] = []

    def emit(self, record: logging.LogRecord) -> None:
        if record.exc_info:
            self.seen.append(f"{record.name}: {record.getMessage()}: "
                             f"{''.join(traceback.format_exception(*record.exc_info)).strip().splitlines()[-1]}")


TRACEBACKS = _Traceback()


@surface("SNMP requests (simulated node)",
         "mutated v1/v2c Get, GetNext, GetBulk and Set requests (read and write community) and noise through "
         "`ManetSnmpAgent.handle`, the node's datagram handler; a logged traceback (genErr) counts as a crash")
def snmp_requests(_: argparse.Namespace) -> tuple[Gen, Check]:
    from erni.plugins.mobinet import ber
    from erni.sim.snmp_agent import ManetSnmpAgent

    agent = ManetSnmpAgent(_snmp_network(), write_community="fuzz-writer")
    seeds = _snmp_requests()
    known = list(agent.table("n1").keys) + [(1, 3, 6, 1, 4, 1)]
    pdus = [ber.GET, ber.GET_NEXT, ber.GET_BULK, ber.SET, ber.RESPONSE, ber.TRAP_V1, ber.INFORM, ber.TRAP_V2,
            ber.REPORT, 0x30, 0x04]

    def gen(rng: random.Random) -> bytes:
        r = rng.random()
        if r < 0.3:
            return damaged(rng, seeds, 0.2, 300)
        binds = [(snmp_oid(rng, known), snmp_value(rng) if rng.random() < 0.5 else b"\x05\x00")
                 for _ in range(rng.choice([0, 1, 1, 2, 3, 8, 60]))]
        message = snmp_message(rng, rng.choice(pdus), rng.choice([b"public", b"fuzz-writer", b"", b"publi"]),
                               rng.choice(EDGE_INTS), rng.choice(EDGE_INTS + [0] * 8), rng.choice(EDGE_INTS + [10] * 8),
                               binds, rng.choice([1] * 8 + [0] * 4 + [3, 2, -1]))
        return flipped(rng, message) if r < 0.45 else message

    def check(data: bytes) -> None:
        reply = agent.handle("n1", data, ("127.0.0.1", 9))
        if reply is not None and not isinstance(reply, bytes):
            raise AssertionError(f"handle answered {type(reply).__name__}")

    return gen, check


@surface("SNMP responses (MobiNet's client)",
         "a full `SnmpSource.read` of every part (walks, bulk, gets) where one or more answers of the simulated "
         "node are mutated, cut or replaced by noise; the UDP exchange is in process, decoding and checking are "
         "the client's own; the error type is `SourceError`")
def snmp_responses(_: argparse.Namespace) -> tuple[Gen, Check]:
    from erni.plugins.mobinet import ber
    from erni.plugins.mobinet.resource import PARTS, SourceError
    from erni.plugins.mobinet.snmp import SnmpSource
    from erni.sim.snmp_agent import ManetSnmpAgent

    agent = ManetSnmpAgent(_snmp_network())
    loop = asyncio.new_event_loop()

    class InProcess(SnmpSource):
        plan: tuple[random.Random, float] = (random.Random(0), 0.0)

        async def _request(self, what: str, pdu: int, varbinds: list[Any], *, write: bool = False,
                           max_repetitions: int = 0) -> list[Any]:
            rng, share = self.plan
            self._request_id = self._request_id % 0x7FFFFFFF + 1
            rid = self._request_id
            self.requests += 1
            answer = agent.handle("n1", ber.encode_request(pdu, self.community.encode(), rid, varbinds, 0,
                                                           max_repetitions), ("127.0.0.1", 9))
            if answer is not None and rng.random() < share:
                r = rng.random()
                if r < 0.4:
                    answer = mutate(rng, answer)
                elif r < 0.5:
                    answer = rng.randbytes(rng.randint(0, 200))
                else:   # a well-formed answer with other varbinds, values, status or request-id
                    answer = forged(rng, answer, rid)
            try:   # what `_Link.datagram_received` does with a datagram
                got = ber.decode_response(answer or b"")
            except ber.BerError as err:
                raise SourceError(f"SNMP {what} to {self.where}: timeout; malformed answer: {err}") from None
            if got.request_id != rid or got.version != 1:
                raise SourceError(f"SNMP {what} to {self.where}: timeout")
            return self._checked(what, got)

    def forged(rng: random.Random, answer: bytes, rid: int) -> bytes:
        try:
            got = ber.decode_response(answer)
        except ber.BerError:
            return flipped(rng, answer)
        binds = [(oid, ber.encode_value(v) if v.tag not in ber.EXCEPTIONS else ber.tlv(v.tag, b""))
                 for oid, v in got.varbinds]
        for _ in range(rng.randint(1, 4)):
            op = rng.randrange(6)
            i = rng.randrange(len(binds)) if binds else 0
            if op == 0 and binds:
                binds[i] = (binds[i][0], snmp_value(rng))
            elif op == 1 and binds:
                binds[i] = (snmp_oid(rng, [b[0] for b in binds]), binds[i][1])
            elif op == 2 and binds:
                del binds[i]
            elif op == 3 and binds:
                binds.insert(i, binds[rng.randrange(len(binds))])
            elif op == 4:
                rng.shuffle(binds)
            else:
                binds.append((snmp_oid(rng, [b[0] for b in binds] or [(1, 3)]), snmp_value(rng)))
        status = rng.choice([0] * 6 + EDGE_INTS[:6] + [rng.randrange(-5, 25)])
        index = rng.choice([0, 0, 1, len(binds), len(binds) + 1, -1, 2**31])
        message = snmp_message(rng, ber.RESPONSE if rng.random() < 0.95 else rng.choice([ber.GET, ber.REPORT]),
                               b"public", rid if rng.random() < 0.95 else rng.choice(EDGE_INTS), status, index,
                               binds, 1 if rng.random() < 0.95 else rng.choice([0, 3]))
        return flipped(rng, message) if rng.random() < 0.1 else message

    src = InProcess("127.0.0.1", 161, timeout=0.2, retries=0, cache_seconds=0.0)

    def gen(rng: random.Random) -> tuple[int, float]:
        return rng.getrandbits(64), rng.choice([0.05, 0.2, 0.5, 1.0])

    def check(plan: tuple[int, float]) -> None:
        seed, share = plan
        src.plan = (random.Random(seed), share)
        src._cache.clear()
        try:
            loop.run_until_complete(src.read(frozenset(PARTS)))
        except SourceError:
            pass

    return gen, check


WS_KEYS = ["type", "robots", "action", "params", "text", "selection", "uid", "on", "rate", "x", "y"]
WS_VALID = [
    {"type": "command", "robots": ["robot1"], "action": "goto", "params": {"x": 1, "y": -2.5}},
    {"type": "say", "text": "robot 1 stop", "selection": ["robot2"]},
    {"type": "select", "robots": ["robot1", "robot2"]},
    {"type": "cancel_task", "uid": "abc"},
    {"type": "mic", "on": True},
    {"type": "ping"},
]


@surface("WebSocket messages (GUI)",
         "mutated valid page messages of every type (any field any JSON value), any JSON, broken JSON as text "
         "and bytes, nesting up to 5,000 deep, through `protocol.parse_message`; the error type is `BadMessage`")
def websocket(_: argparse.Namespace) -> tuple[Gen, Check]:
    from erni.plugins.ui.protocol import BadMessage, parse_message

    seeds = [dumps(v).encode() for v in WS_VALID]

    def gen(rng: random.Random) -> str | bytes:
        obj = value(rng, 0, WS_KEYS) if rng.random() < 0.1 else mutated_json(rng, WS_VALID, WS_KEYS)
        raw = as_text(rng, obj, seeds)
        return raw if rng.random() < 0.3 else raw.decode("utf-8", "replace")

    def check(message: str | bytes) -> None:
        try:
            parse_message(message)
        except BadMessage as err:
            if "\n" in str(err):
                raise AssertionError(f"a refusal of more than one line: {err}") from None

    return gen, check


TOML_VALUES: list[Callable[[random.Random], str]] = [
    lambda r: str(r.randint(-5, 100)), lambda r: dumps(text(r)), lambda r: r.choice(["true", "false"]),
    lambda r: repr(r.uniform(-1, 100)), lambda r: dumps([text(r, 6) for _ in range(r.randint(0, 3))]),
    lambda r: r.choice(["inf", "nan", "-inf", "1e999", "0x10", "1979-05-27", "{a = 1}", "[[]]", '"', "'''"]),
]
AGENT_KEYS = ["name", "workers", "slow_plugin_seconds", "log_level", "journal", "colour", "other"]
PLUGIN_KEYS = ["class", "name", "enabled", "settings"]
PLUGIN_CLASSES = ["echo", "transport", "motion", "mobinet", "mission", "ui", "erni.replay:ReplayPlugin",
                  "erni.plugins.echo:EchoPlugin", "nope:Nope", "os:system", "", "erni.blackboard:Plugin"]
SETTING_KEYS = ["port", "url", "robot", "identity", "insecure", "key", "listen", "peers", "host", "community",
                "write_community", "period", "timeout", "speed", "max_speed", "name", "token", "path", "source",
                "strategy", "agents", "log", "rate", "poll", "safe_speed", "bind", "retries"]


@surface("config files",
         "agent TOML: known and unknown keys, values of every TOML type, plugin tables naming every shipped "
         "plugin (and unknown classes) with known and unknown settings of any value, trailing garbage, byte-damaged text; through `parse_config` and "
         "`build_agent` (resolution and settings validation, nothing started); the error type is `ConfigError`")
def configs(_: argparse.Namespace) -> tuple[Gen, Check]:
    from erni.blackboard import ConfigError
    from erni.blackboard.config import build_agent, parse_config

    def gen(rng: random.Random) -> str:
        if rng.random() < 0.7:   # a good [agent] table: the plugins' settings are reached
            lines = ["[agent]", 'name = "fuzz"']
        else:
            lines = ["[agent]"] + [f"{k} = {rng.choice(TOML_VALUES)(rng)}"
                                   for k in rng.sample(AGENT_KEYS, rng.randint(0, 5))]
        for _ in range(rng.randint(0, 3)):
            lines.append("[[plugin]]")
            if rng.random() < 0.7:
                lines.append(f"class = {dumps(rng.choice(PLUGIN_CLASSES))}")
            lines += [f"{k} = {rng.choice(TOML_VALUES)(rng)}" for k in rng.sample(PLUGIN_KEYS[1:3], rng.randint(0, 2))]
            if rng.random() < 0.5:
                lines.append("[plugin.settings]")
                lines += [f"{rng.choice(SETTING_KEYS) if rng.random() < 0.8 else json.dumps(text(rng, 6))} = "
                          f"{rng.choice(TOML_VALUES)(rng)}" for _ in range(rng.randint(0, 4))]
        out = "\n".join(lines)
        if rng.random() < 0.2:
            out += "\n" + text(rng, 30)
        if rng.random() < 0.2:
            out = mutate(rng, out.encode()).decode("utf-8", "replace")
        return out

    def check(toml: str) -> None:
        try:
            build_agent(parse_config(toml, "fuzz.toml"), "fuzz.toml")
        except ConfigError as err:
            if not str(err).startswith("fuzz.toml: "):
                raise AssertionError(f"a refusal that does not name the file: {err}") from None

    return gen, check


TASK_PAIRS = [("BotMotion", p) for p in ("goto", "turn", "forward", "backward", "stop", "velocity", "patrol")] + [
    ("RemoteBotMotion", "goto"), ("RemoteBotMotion", "cancel"), ("NetWatch", "path_cost"), ("Deploy", "spread"),
    ("Deploy", "relay"), ("Nope", "fly"), ("BotMotion", "fly"), ("", "")]
PARAM_KEYS = ["x", "y", "theta", "distance", "speed", "angle", "degrees", "v", "w", "points", "target", "robots",
              "to", "from", "loops", "timeout", "relay", "strategy", "heading"]


@surface("task parameters",
         "every verb/preposition pair (known and unknown) with parameters of known and unknown names and any "
         "JSON values, through `Task.parse`; the error type is `TaskError`, one line")
def task_parameters(_: argparse.Namespace) -> tuple[Gen, Check]:
    from erni.blackboard import Task, TaskError

    def gen(rng: random.Random) -> dict[str, Any]:
        verb, prep = rng.choice(TASK_PAIRS)
        params = value(rng, 0, PARAM_KEYS) if rng.random() < 0.1 else {
            rng.choice(PARAM_KEYS): value(rng, 1, PARAM_KEYS) for _ in range(rng.randint(0, 5))}
        task: dict[str, Any] = {"verb": verb, "preposition": prep, "params": params}
        if rng.random() < 0.2:
            task[rng.choice(["destination", "source", "uid", "priority", "extra"])] = value(rng, 2)
        return task

    def check(task: dict[str, Any]) -> None:
        try:
            Task.parse(task)
        except TaskError as err:
            if "\n" in str(err):
                raise AssertionError(f"a refusal of more than one line: {err}") from None

    return gen, check


LOG_KEYS = ["t", "agent", "op", "type", "data"]


@surface("replay logs",
         "a log file: a valid or damaged header, then lines of mutated valid events (any field any JSON value, "
         "times up to 1e300, infinities), any JSON, broken lines; through `replay.read_log`; the error type is "
         "`LogError`, and every problem one line naming file and line")
def replay_logs(_: argparse.Namespace) -> tuple[Gen, Check]:
    from erni.replay import LogError, read_log

    path = Path(tempfile.mkdtemp(prefix="erni-fuzz-")) / "x.jsonl"
    header = {"erni_record": 1, "via": "fuzz"}
    valid = [{"t": 0.5, "agent": "robot1", "op": "add", "type": "Pose",
              "data": {"name": "robot1", "x": 1.0, "y": 2.0, "th": 0.0}},
             {"t": 1.0, "agent": "control", "op": "change", "type": "Task",
              "data": {"verb": "BotMotion", "preposition": "goto", "params": {"x": 1, "y": 2}}},
             {"t": 2.0, "agent": "robot1", "op": "remove", "type": "Pose", "data": {"name": "robot1"}}]
    seeds = [dumps(v).encode() for v in valid]

    def gen(rng: random.Random) -> bytes:
        first = dumps(header).encode()
        if rng.random() < 0.05:
            first = mutate(rng, first)
        lines = [first]
        for _ in range(rng.randint(0, 6)):
            obj = mutated_json(rng, valid, LOG_KEYS) if rng.random() < 0.85 else value(rng, 0, LOG_KEYS)
            if isinstance(obj, dict) and rng.random() < 0.2:
                obj["t"] = rng.choice([1e300, -1.0, float("inf"), float("nan"), 2**70, 2.6e6, True, "1"])
            lines.append(as_text(rng, obj, seeds))
        return b"\n".join(lines)

    def check(raw: bytes) -> None:
        path.write_bytes(raw)
        try:
            _, _, problems = read_log(path)
        except LogError as err:
            if "\n" in str(err):
                raise AssertionError(f"a refusal of more than one line: {err}") from None
            return
        bad = [p for p in problems if not p.startswith(f"{path}:") or "\n" in p]
        if bad:
            raise AssertionError(f"a problem line that is not one line naming the file: {bad[0]!r}")

    return gen, check


@surface("spoken phrases",
         "sequences of grammar words, numbers as words and digits, robot names, fillers, random words and any "
         "text, through `grammar.parse` and `Dialogue.hear` (listening, standing by, asked again); the grammar's "
         "error type is `Refusal`; a listening dialogue answers everything")
def spoken(_: argparse.Namespace) -> tuple[Gen, Check]:
    from erni.plugins.ui import Dialogue, Naming, Refusal, parse, vocabulary

    words = vocabulary() + ["1", "2.5", "-3", "9", "0", "1e9", "nan", "inf", "-0", "one", "two", "point",
                            "minus", "hundred", "thousand", "and", "robot", "robot1", "robot 7", "everyone",
                            "metres", "degrees", "please", "uh"]
    known = [f"robot{i}" for i in range(1, 7)]
    dialogue = Dialogue(Naming("robot{n}"), verb="BotMotion", source="control")

    def gen(rng: random.Random) -> str:
        r = rng.random()
        if r < 0.15:
            return text(rng, 60)
        said = [rng.choice(words) for _ in range(rng.randint(0, 14))]
        if r < 0.3 and said:
            said[rng.randrange(len(said))] = text(rng, 8)
        return " ".join(said)

    def check(phrase: str) -> None:
        try:
            parse(phrase)
        except Refusal:
            pass
        listening = dialogue.listening
        reply = dialogue.hear(phrase, known, unsure=rng_select.random() < 0.05)
        if listening and reply.say is None:   # a listening dialogue answers every utterance
            raise AssertionError("the listening dialogue said nothing")
        if rng_select.random() < 0.05:   # back to listening after a "stand by", another selection
            dialogue.listening = True
            dialogue.select([known[rng_select.randrange(6)]])

    rng_select = random.Random(1)
    return gen, check


# --- runner -------------------------------------------------------------------------------------


@contextmanager
def time_limit(seconds: float) -> Iterator[None]:
    def hang(signum: int, frame: Any) -> None:
        raise Hang(f"no answer within {seconds:g} s")

    old = signal.signal(signal.SIGALRM, hang)
    try:
        yield
    finally:
        signal.setitimer(signal.ITIMER_REAL, 0)
        signal.signal(signal.SIGALRM, old)


@dataclass
class Result:
    name: str
    inputs: int = 0
    crashes: int = 0
    violations: int = 0
    seconds: float = 0.0
    examples: list[str] = field(default_factory=list)
    covered: dict[str, tuple[int, int]] = field(default_factory=dict)  # module -> (lines run by inputs, statements)


_TRANSPORT_PLUGIN = tuple(f"erni/transport/{m}.py" for m in
                          ("plugin", "tasking", "presence", "replication", "watchers", "authorization"))
HANDLERS: dict[str, tuple[str, ...]] = {
    "transport plugin": _TRANSPORT_PLUGIN, "policy": ("erni/transport/policy.py",),
    "driver": ("erni/plugins/motion/driver.py",), "ui plugin": ("erni/plugins/ui/plugin.py",),
    "server": ("erni/plugins/ui/server.py",), "replay": ("erni/replay.py",), "bags": ("erni/bags.py",),
}
"""The handler modules whose statement coverage `--coverage` reports for every surface: where an input
goes once its parser has taken it (authorization, the blackboard, the driver, the page, publishing)."""


class Coverage:
    """Statement coverage of the handler modules by the inputs alone (a surface's setup is not counted)."""

    def __init__(self) -> None:
        import coverage

        self.files = {name: [str(ROOT / rel) for rel in rels] for name, rels in HANDLERS.items()}
        self.cov = coverage.Coverage(data_file=None, include=[f for fs in self.files.values() for f in fs],
                                     config_file=False)

    def start(self) -> None:
        self.cov.erase()
        self.cov.start()

    def stop(self) -> dict[str, tuple[int, int]]:
        self.cov.stop()
        out = {}
        for name, paths in self.files.items():
            run = total = 0
            for path in paths:  # a handler of several modules counts their statements together
                _, statements, _, missing, _ = self.cov.analysis2(path)
                run, total = run + len(statements) - len(missing), total + len(statements)
            out[name] = (run, total)
        return out


def run_surface(name: str, examples: int, seed: int, hang: float, budget: float | None = None,
                report: Callable[[str], None] = print, only: int | None = None,
                coverage: Coverage | None = None) -> Result:
    """Give `examples` inputs to surface `name` (or as many as `budget` seconds allow); count crashes and
    invariant violations (`Violation`). `only`: generate inputs up to that index and give the surface that
    one alone (a reproducer). `coverage`: measure the handler modules' lines the inputs run."""
    what, setup = SURFACES[name]
    gen, check = setup(argparse.Namespace())
    rng = random.Random(f"{seed}:{name}")
    res = Result(name)
    start = time.monotonic()
    if coverage is not None:
        coverage.start()
    try:
        with time_limit(hang):
            for i in range(examples):
                item = gen(rng)
                if only is not None and i != only:
                    continue
                before = len(TRACEBACKS.seen)
                problem = None
                broken = False
                try:
                    signal.setitimer(signal.ITIMER_REAL, hang)
                    check(item)
                    signal.setitimer(signal.ITIMER_REAL, 0)
                except Hang as err:
                    problem = f"hang: {err}"
                except Violation as err:
                    signal.setitimer(signal.ITIMER_REAL, 0)
                    if only is not None:
                        raise
                    problem, broken = f"invariant violated: {str(err)[:300]}", True
                except Exception as err:   # noqa: BLE001 - anything escaping is what this counts
                    signal.setitimer(signal.ITIMER_REAL, 0)
                    if only is not None:
                        raise   # reproducing: the whole traceback
                    problem = f"{type(err).__name__}: {str(err)[:300]}"
                if problem is None and len(TRACEBACKS.seen) > before:
                    problem = f"logged traceback: {TRACEBACKS.seen[-1][:300]}"
                res.inputs += 1
                if problem is not None:
                    if broken:
                        res.violations += 1
                    else:
                        res.crashes += 1
                    if len(res.examples) < 5:
                        res.examples.append(f"input {i} (seed {seed}): {problem}\n    input: {item!r:.600}\n"
                                            f"    again: python -m tests.reliability.fuzz_run -s {name!r} --seed "
                                            f"{seed} --only {i} -n {i + 1}")
                        report(f"  {'VIOLATION' if broken else 'CRASH'} in {name}: {res.examples[-1]}")
                if only is not None:
                    break
                if budget is not None and time.monotonic() - start > budget:
                    break
                if report is print and (i + 1) % 10000 == 0:
                    report(f"  {name}: {i + 1} inputs, {res.crashes} crashes, {res.violations} violations, "
                           f"{time.monotonic() - start:.0f} s")
    finally:
        if coverage is not None:
            res.covered = coverage.stop()
    res.seconds = time.monotonic() - start
    return res


def table(results: list[Result]) -> str:
    """The results as a Markdown table: inputs, crashes, violations, seconds, and with coverage the
    lines of each handler module the inputs ran (of its statements, in the header)."""
    covered = any(r.covered for r in results)
    totals = next((r.covered for r in results if r.covered), {})
    head = ["surface", "inputs", "crashes", "violations", "seconds"]
    if covered:
        head += [f"{m} ({totals[m][1]})" for m in HANDLERS]
    rows = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for r in results:
        cells = [r.name, f"{r.inputs:,}", str(r.crashes), str(r.violations), f"{r.seconds:.0f}"]
        if covered:
            cells += [str(r.covered[m][0]) if r.covered else "" for m in HANDLERS]
        rows.append("| " + " | ".join(cells) + " |")
    return "\n".join(rows)


def quiet_logging() -> None:
    """Product logging off (refusals are logged by design), except tracebacks, which are crashes."""
    root = logging.getLogger()
    for h in list(root.handlers):
        root.removeHandler(h)
    root.addHandler(TRACEBACKS)
    root.setLevel(logging.WARNING)
    logging.getLogger("erni").setLevel(logging.WARNING)


def commit() -> str:
    try:
        out = subprocess.run(["git", "-C", str(ROOT), "rev-parse", "--short", "HEAD"], capture_output=True,
                             text=True, check=True).stdout.strip()
        dirty = subprocess.run(["git", "-C", str(ROOT), "status", "--porcelain", "--untracked-files=no"],
                               capture_output=True, text=True).stdout.strip()
        return out + ("+" if dirty else "")
    except (OSError, subprocess.CalledProcessError):
        return "unknown"


def write_counts(results: list[Result], examples: int, seed: int, measured: str) -> Path:
    """Merge the results into artifacts/fuzz-counts.json under "scale"; `measured`: the commit run."""
    out = ROOT / "artifacts" / "fuzz-counts.json"
    out.parent.mkdir(exist_ok=True)
    try:
        data = json.loads(out.read_text())
    except (OSError, ValueError):
        data = {}
    scale = data.get("scale", {}) if isinstance(data.get("scale"), dict) else {}
    scale.setdefault("surfaces", {})
    scale.update({"command": "python -m tests.reliability.fuzz_run", "examples_per_surface": examples, "seed": seed})
    for r in results:
        scale["surfaces"][r.name] = {"inputs": r.inputs, "crashes": r.crashes, "violations": r.violations,
                                     "seconds": round(r.seconds, 1), "commit": measured, "first_crashes": r.examples}
        if r.covered:
            scale["surfaces"][r.name]["covered"] = {m: list(v) for m, v in r.covered.items()}
    data["scale"] = scale
    out.write_text(json.dumps(data, indent=2) + "\n")
    return out


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m tests.reliability.fuzz_run", description=__doc__.split("\n")[0])
    p.add_argument("-n", "--examples", type=int, default=int(os.environ.get("ERNI_FUZZ_EXAMPLES", "100000")),
                   help="inputs per surface (default 100000, or ERNI_FUZZ_EXAMPLES)")
    p.add_argument("-s", "--surface", action="append", choices=sorted(SURFACES), metavar="NAME",
                   help="run only this surface (repeatable); default: all")
    p.add_argument("--seed", type=int, default=int(os.environ.get("ERNI_FUZZ_SEED", "0")))
    p.add_argument("--hang", type=float, default=10.0, help="seconds one input may take (default 10)")
    p.add_argument("--budget", type=float, default=None, help="stop a surface after this many seconds")
    p.add_argument("--only", type=int, default=None, metavar="INDEX",
                   help="give the surface only input INDEX of the sequence (reproduce a crash; with -s)")
    p.add_argument("--list", action="store_true", help="list the surfaces and what each is given")
    p.add_argument("--no-write", action="store_true", help="do not update artifacts/fuzz-counts.json")
    p.add_argument("--coverage", action="store_true", help="measure the statement coverage of the handler "
                   "modules by each surface's inputs (coverage.py; slower) and print it in the table")
    args = p.parse_args(argv)
    if args.list:
        for name, (what, _) in SURFACES.items():
            print(f"{name}: {what}")
        return 0
    quiet_logging()
    measured = commit()   # the code loaded now is the code measured, whatever changes on disk meanwhile
    results = []
    try:
        for name in args.surface or list(SURFACES):
            print(f"{name}: {args.examples} inputs ...", flush=True)
            r = run_surface(name, args.examples, args.seed, args.hang, args.budget, only=args.only,
                            coverage=Coverage() if args.coverage else None)
            results.append(r)
            print(f"{name}: {r.inputs} inputs, {r.crashes} crashes, {r.violations} violations, {r.seconds:.0f} s",
                  flush=True)
            if not args.no_write and args.only is None:
                write_counts([r], args.examples, args.seed, measured)
    finally:
        close_all()
    print("\n" + table(results))
    return 1 if any(r.crashes or r.violations for r in results) else 0


def close_all() -> None:
    """Stop what the surfaces started (endpoints, agents)."""
    global _team
    deep = sys.modules.get("tests.reliability.fuzz_deep")
    if deep is not None:
        deep.close_all()
    if _team is not None:
        _team.close()
        _team = None


from tests.reliability import fuzz_deep  # noqa: E402,F401 - the deeper harnesses replace four surfaces and add one

if __name__ == "__main__":
    from tests.reliability.fuzz_run import main as _main  # the module as the harnesses import it, not __main__

    sys.exit(_main())
