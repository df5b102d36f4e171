"""Fuzzing of the input surfaces owned by the core, transport, motion and MobiNet.

Every surface takes hypothesis-generated input and must either accept it or refuse it with the
surface's own error type; nothing else may escape, nothing may hang, nothing reaches the
blackboard unvalidated. `ERNI_FUZZ_EXAMPLES` sets the budget (CI: the default; on demand:
`ERNI_FUZZ_EXAMPLES=20000 pytest tests/reliability/test_fuzz.py`); the number of inputs each
surface was given is written to `artifacts/fuzz-counts.json`. The 100,000-inputs-per-surface run is
`python -m tests.reliability.fuzz_run` (`fuzz_run.py`; its surfaces run in CI in `test_fuzz_scale.py`).
"""

from __future__ import annotations

import asyncio
import json
import os
import socket
import threading
from collections import Counter
from pathlib import Path

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from erni.blackboard import ConfigError, Task, TaskError
from erni.blackboard.config import build_agent, parse_config
from erni.blackboard.testing import wait_until
from erni.plugins.motion.arcos import PacketReader, ProtocolError, is_sip, parse_sip, parse_sync2
from erni.replay import read_log
from erni.transport.wire import (
    Envelope,
    EnvelopeHead,
    EnvelopeItem,
    FrameError,
    StreamDecoder,
    batch_payload,
    encode_plain,
)
from tests.reliability.fuzz_run import confirmed

EXAMPLES = int(os.environ.get("ERNI_FUZZ_EXAMPLES", "300"))
FUZZ = settings(max_examples=EXAMPLES, deadline=None,
                suppress_health_check=[HealthCheck.too_slow, HealthCheck.function_scoped_fixture])
COUNTS: Counter[str] = Counter()


@pytest.fixture(scope="module", autouse=True)
def report():
    yield
    out = Path(__file__).resolve().parents[2] / "artifacts"
    out.mkdir(exist_ok=True)
    path = out / "fuzz-counts.json"
    try:  # the at-scale run's counts (key "scale") stay
        scale = {k: v for k, v in json.loads(path.read_text()).items() if k == "scale"}
    except (OSError, ValueError, AttributeError):
        scale = {}
    path.write_text(json.dumps({"examples_per_test": EXAMPLES, **COUNTS, **scale}, indent=2) + "\n")


@pytest.fixture(scope="module")
def receiver():
    """A started endpoint with identities, a live session from a peer, and rate limits out of the way."""
    from erni.transport.endpoint import Endpoint
    from erni.transport.identity import load_identity
    from erni.transport.limits import Limits
    from tests.transport.helpers import authority, identity

    limits = Limits(handshakes_per_host=1e9, handshakes_total=1e9, beacons_total=1e9)
    rx = Endpoint("fuzz-rx", identity=load_identity(identity("fuzz-rx"), authority().dir / "revoked.crl"),
                  limits=limits)
    tx = Endpoint("fuzz-tx", identity=load_identity(identity("fuzz-tx")), limits=limits)
    rx.start()
    tx.start()
    tx.send(rx.address, "hello", None, reliable=True)
    # a progress bound: the session is up in milliseconds unloaded; both ends hold it confirmed
    wait_until(lambda: confirmed(tx, rx) and confirmed(rx, tx), timeout=30, interval=0.01,
               message="no session within 30 s")
    yield rx, tx, tx.session_with(rx.address)
    tx.stop()
    rx.stop()


def _frames(tx, session) -> list[bytes]:
    """One valid frame of every kind a receiver takes (and a batch of two messages under one head)."""
    from erni.transport.session import initiate
    from erni.transport.wire import BEACON

    task = Task(verb="BotMotion", preposition="goto", params={"x": 1, "y": 2})
    env = Envelope(sender="fuzz-tx", role="robot", to="fuzz-rx", inst=tx.inst, reply=tx.address, seq=1, id="1",
                   kind="task.add", type="Task", body=task.model_dump(mode="json"))
    beacon = env.model_copy(update={"kind": "beacon", "type": "Beacon", "body": {"role": "robot"}, "to": ""})
    status = env.model_copy(update={"kind": "status", "id": "2", "seq": 2})
    head = env.model_dump_json(include=set(EnvelopeHead.model_fields)).encode()
    items = [m.model_dump_json(include=set(EnvelopeItem.model_fields)).encode() for m in (env, status)]
    batch = batch_payload(head, items)
    return [session.seal(env.model_dump_json().encode(), 65536),
            initiate(tx.auth, tx.inst, tx.address, ("127.0.0.1", 9), "fuzz-rx").frame,
            tx.auth.sign(BEACON, beacon.model_dump_json().encode()),
            encode_plain(env),
            session.seal(batch, 65536)]


@FUZZ
@given(data=st.binary(max_size=400), which=st.integers(0, 4),
       flips=st.lists(st.tuples(st.integers(0, 10_000), st.integers(1, 255)), max_size=8),
       cut=st.integers(0, 2000))
def test_transport_frames(receiver, data, which, flips, cut):
    """Random bytes and mutated valid frames of every kind through the whole receive path."""
    COUNTS["transport frames"] += 1
    rx, tx, session = receiver
    frame = bytearray(_frames(tx, session)[which])
    for pos, x in flips:  # mutated valid frames reach deeper than random bytes
        frame[pos % len(frame)] ^= x
    if cut and cut < len(frame):
        frame = frame[:cut]
    for candidate in (data, bytes(frame)):
        got = rx.accept_frame(candidate, "udp", ("127.0.0.1", 9))  # never raises: None or a verified message
        assert got is None or all(m.sender == "fuzz-tx" for m in got[0])
        try:
            StreamDecoder(4096).feed(candidate)
        except FrameError:
            pass


json_values = st.recursive(st.none() | st.booleans() | st.integers() | st.floats() | st.text(max_size=8),
                           lambda inner: st.lists(inner, max_size=3) | st.dictionaries(st.text(max_size=8), inner,
                                                                                         max_size=3), max_leaves=12)


@FUZZ
@given(envelope=st.dictionaries(st.sampled_from(["v", "sender", "role", "to", "inst", "reply", "seq", "id", "kind",
                                                 "type", "body", "extra"]), json_values, max_size=11),
       raw=st.binary(max_size=200))
def test_authenticated_garbage(receiver, envelope, raw):
    """What a key holder can send inside its own session: anything at all, sealed correctly."""
    COUNTS["authenticated frames"] += 1
    rx, tx, session = receiver
    for payload in (json.dumps(envelope).encode(), raw):
        got = rx.accept_frame(session.seal(payload, 65536), "udp", ("127.0.0.1", 9))
        assert got is None or all(m.sender == "fuzz-tx" for m in got[0])


@FUZZ
@given(data=st.binary(max_size=600), flips=st.lists(st.tuples(st.integers(0, 5000), st.integers(1, 255)),
                                                     max_size=6))
def test_certificates_and_revocation_lists(receiver, data, flips):
    """Certificates and revocation lists from the wire: valid ones mutated, and noise."""
    from erni.transport.identity import IdentityError

    COUNTS["certificates and revocation lists"] += 1
    rx, tx, _ = receiver
    trust = rx.identity.trust
    for valid in (tx.identity.cert_der, trust.crl_der):
        mutated = bytearray(valid)
        for pos, x in flips:
            mutated[pos % len(mutated)] ^= x
        for candidate in (data, bytes(mutated)):
            try:
                trust.check(candidate)
            except IdentityError:
                pass
            assert trust.adopt(candidate) in (True, False)


@FUZZ
@given(st.lists(st.binary(max_size=80), max_size=12))
def test_arcos_bytes(chunks):
    COUNTS["ARCOS bytes"] += 1
    reader = PacketReader()
    for chunk in chunks:
        for body in reader.feed(chunk):
            try:
                if is_sip(body):
                    parse_sip(body)
                else:
                    parse_sync2(body)
            except ProtocolError:
                pass


@FUZZ
@given(st.recursive(st.none() | st.booleans() | st.integers() | st.floats(allow_nan=True) | st.text(max_size=8),
                    lambda inner: st.lists(inner, max_size=3) | st.dictionaries(st.text(max_size=8), inner,
                                                                                  max_size=3),
                    max_leaves=12),
       st.sampled_from(["BotMotion", "RemoteBotMotion", "NetWatch", "Deploy", "Nope"]),
       st.sampled_from(["goto", "turn", "forward", "say", "spread", "patrol", "path_cost", "fly"]))
def test_task_parameters(params, verb, prep):
    COUNTS["task parameters"] += 1
    try:
        Task.parse({"verb": verb, "preposition": prep, "params": params})
    except TaskError as err:
        assert "\n" not in str(err)


toml_values = st.one_of(st.integers(-5, 100), st.text(max_size=12), st.booleans(), st.floats(-1, 100),
                        st.lists(st.text(max_size=6), max_size=3))


@FUZZ
@given(agent=st.dictionaries(st.sampled_from(["name", "workers", "slow_plugin_seconds", "log_level",
                                              "journal", "colour"]), toml_values, max_size=5),
       plugins=st.lists(st.dictionaries(st.sampled_from(["class", "name", "enabled", "settings"]),
                                        toml_values, max_size=4), max_size=3),
       garbage=st.none() | st.text(max_size=30))
def test_config_files(agent, plugins, garbage):
    COUNTS["config files"] += 1
    lines = ["[agent]"] + [f"{k} = {json.dumps(v)}" for k, v in agent.items()]
    for p in plugins:
        lines.append("[[plugin]]")
        lines += [f"{k} = {json.dumps(v)}" for k, v in p.items() if k != "settings"]
    text = "\n".join(lines) + ("\n" + garbage if garbage is not None else "")
    try:
        config = parse_config(text, "fuzz.toml")
        build_agent(config, "fuzz.toml")  # resolves plugins, validates settings; does not start
    except ConfigError as err:
        assert str(err).startswith("fuzz.toml: ")


@FUZZ
@given(lines=st.lists(st.one_of(st.text(max_size=60), st.builds(json.dumps, st.dictionaries(
    st.sampled_from(["t", "agent", "op", "type", "data"]), toml_values, max_size=5))), max_size=6))
def test_replay_logs(tmp_path_factory, lines):
    COUNTS["replay logs"] += 1
    path = tmp_path_factory.mktemp("log") / "x.jsonl"
    path.write_text("\n".join([json.dumps({"erni_record": 1, "via": "x"}), *lines]))
    _, events, problems = read_log(path)
    assert all(p.startswith(f"{path}:") and "\n" not in p for p in problems)


class _MutatingProxy:
    """A UDP 'agent' that forwards to the real simulated agent and mutates its answers."""

    def __init__(self, target: tuple[str, int]):
        self.target = target
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.bind(("127.0.0.1", 0))
        self.sock.settimeout(0.05)
        self.mutate = lambda data: data
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="fuzz-snmp-proxy", daemon=True)
        self._thread.start()

    def _run(self) -> None:
        up = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        up.settimeout(0.5)
        while not self._stop.is_set():
            try:
                request, client = self.sock.recvfrom(65536)
            except (TimeoutError, OSError):
                continue
            try:
                up.sendto(request, self.target)
                reply, _ = up.recvfrom(65536)
            except (TimeoutError, OSError):
                continue
            self.sock.sendto(self.mutate(reply), client)
        up.close()

    def close(self) -> None:
        self._stop.set()
        self._thread.join(2)
        self.sock.close()


@pytest.fixture(scope="module")
def snmp_proxy():
    from erni.sim.manet import ManetNetwork, RadioModel
    from erni.sim.snmp_agent import ManetSnmpAgent

    net = ManetNetwork(RadioModel(100.0, 50.0))
    for i in range(4):
        net.add_node(f"n{i}", i * 60.0, 0.0)
    with ManetSnmpAgent(net) as agent:
        proxy = _MutatingProxy(agent.serve("n1"))
        yield proxy
        proxy.close()


@settings(max_examples=max(20, EXAMPLES // 10), deadline=None,
          suppress_health_check=[HealthCheck.too_slow, HealthCheck.function_scoped_fixture])
@given(flips=st.lists(st.tuples(st.integers(0, 2000), st.integers(1, 255)), min_size=1, max_size=6),
       truncate=st.integers(0, 400))
def test_snmp_responses(snmp_proxy, flips, truncate):
    from erni.plugins.mobinet.resource import PARTS, SourceError
    from erni.plugins.mobinet.snmp import SnmpSource

    COUNTS["SNMP responses"] += 1

    def mutate(data: bytes) -> bytes:
        b = bytearray(data)
        for pos, x in flips:
            b[pos % len(b)] ^= x
        return bytes(b[:truncate]) if truncate and truncate < len(b) else bytes(b)

    snmp_proxy.mutate = mutate

    async def go():
        src = SnmpSource(*snmp_proxy.sock.getsockname(), timeout=0.2, retries=0)
        try:
            return await src.read(frozenset(PARTS))
        except SourceError:
            return None
        finally:
            await src.aclose()

    asyncio.run(asyncio.wait_for(go(), 10))
