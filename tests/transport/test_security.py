"""The threat model of docs/explanation/reliability.md, attack by attack, on real agents over loopback sockets.

An outsider on the mesh sees and sends any packet but holds no key; a key holder has one
agent's identity (or, in team-key mode, the shared key). Each test mounts one attack and
checks that it does nothing beyond what the threat model allows.
"""

from __future__ import annotations

import socket
import time

import pytest

from erni.blackboard import Task, TaskState
from erni.blackboard.testing import wait_until
from erni.transport.wire import Envelope, Message
from tests.transport.helpers import (
    KEY,
    Tap,
    authority,
    beacon_after,
    datagrams_read,
    free_port,
    identity,
    make_agent,
    make_client,
    settled,
)

BEACON, DATA = b"B"[0], b"D"[0]  # frame kinds (transport/wire.py)


def holder_of(name: str):
    """What the holder of `name`'s identity can sign with."""
    from erni.transport.identity import load_identity
    from erni.transport.session import IdentityAuth

    return IdentityAuth(load_identity(identity(name)))


def initiate(auth, *args):
    from erni.transport.session import initiate as start

    return start(auth, *args)


@pytest.fixture
def team():
    agents = []
    port = free_port()

    def spawn(name: str, **kw):
        agent = make_agent(name, kw.pop("discovery_port", port), **kw)
        agents.append(agent)
        return agent

    spawn.port = port
    yield spawn
    for a in agents:
        a.stop()


def counters(agent) -> dict[str, int]:
    return agent.plugin("transport").endpoint.counters


def addr_of(agent) -> tuple[str, int]:
    return agent.plugin("transport").address


def up(agent, name: str) -> bool:
    peer = agent.blackboard.get(f"peer:{name}")
    return peer is not None and peer.up


def send_raw_tcp(addr, data: bytes) -> None:
    with socket.create_connection(addr, timeout=2) as s:
        s.sendall(data)
        s.settimeout(0.5)
        try:
            s.recv(65536)
        except OSError:
            pass


def _sniff_a_task(control, robot1):
    """A client tasks robot1 through control across a tap; the task ends and is cancelled.
    Returns (tap, client, task): what an eavesdropper on the mesh captured."""
    tap = Tap(addr_of(control))
    client = make_client(tap.address)
    task = Task(verb="BotMotion", preposition="forward", params={"distance": 3.0}, destination="robot1",
                source=client.endpoint.name)
    client.send(tap.address, "task.add", task)
    wait_until(lambda: (t := control.blackboard.get(task.uid)) is not None and t.done)
    with control.transaction() as tx:  # the requester cancels (removes) it: gone everywhere
        tx.remove(task.uid)
    wait_until(lambda: not robot1.blackboard.contains(task.uid))
    assert any(tap.streams) or tap.datagrams, "the tap saw the task go by"
    return tap, client, task


def test_task_parameters_never_cross_the_mesh_in_clear(team):
    control = team("control", echo=False, role="control")
    robot1 = team("robot1")
    wait_until(lambda: up(control, "robot1"))
    tap, client, task = _sniff_a_task(control, robot1)
    try:
        wire = b"".join([bytes(s) for s in tap.streams] + tap.datagrams)
        for secret in (task.uid.encode(), b"forward", b"distance", b"BotMotion"):
            assert secret not in wire, f"{secret!r} crossed the mesh in clear"
    finally:
        client.endpoint.stop()
        tap.close()


def test_captured_task_frames_do_nothing_at_another_agent_or_after_a_restart(team):
    """The sniffed `cli -> control` task, replayed at robot2 and at the restarted control node."""
    control = team("control", echo=False, role="control")
    robot1, robot2 = team("robot1"), team("robot2")
    wait_until(lambda: up(control, "robot1") and up(control, "robot2") and up(robot2, "robot1"))
    tap, client, task = _sniff_a_task(control, robot1)
    try:
        runs = robot1.plugin("motion").runs
        streams = [bytes(s) for s in tap.streams if s]
        before = counters(robot2).get("dropped.session", 0)
        for stream in streams:  # replayed at another agent
            send_raw_tcp(addr_of(robot2), stream)
        # each stream is closed at its first frame, of a session robot2 never had
        wait_until(lambda: counters(robot2).get("dropped.session", 0) >= before + len(streams), timeout=30)
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as udp:
            for datagram in tap.datagrams:
                udp.sendto(datagram, addr_of(robot2))
            datagrams_read(robot2, udp)  # read, and what they brought handled
        listen = "{}:{}".format(*addr_of(control))
        control.stop()  # replayed at the same agent after it restarted
        again = team("control", echo=False, role="control", listen=listen)
        for stream in streams:
            send_raw_tcp(addr_of(again), stream)
        wait_until(lambda: counters(again).get("dropped.session", 0) >= len(streams), timeout=30)
        settled(again)
        for agent in (robot1, robot2, again):
            assert not agent.blackboard.contains(task.uid), f"{agent.name} took the replayed task"
        assert robot1.plugin("motion").runs == runs, "robot1 did not act on a replay"
        assert counters(robot2).get("dropped.session", 0) >= 1 and counters(again).get("dropped.session", 0) >= 1
    finally:
        client.endpoint.stop()
        tap.close()


def test_a_frame_replayed_in_its_own_session_is_dropped(team):
    control = team("control", echo=False, role="control")
    tap = Tap(addr_of(control))
    client = make_client(tap.address)
    try:
        client.send(tap.address, "watch.request", None, reliable=False)
        wait_until(lambda: any(d[4] == DATA for d in tap.datagrams))  # the handshake, then the data frame
        data = [d for d in tap.datagrams if d[4] == DATA]
        wait_until(lambda: counters(control).get("received", 0) >= 1)  # the original arrived
        before = counters(control).get("received", 0)
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as udp:
            for _ in range(3):
                udp.sendto(data[0], addr_of(control))
            datagrams_read(control, udp)  # all three read
        assert counters(control).get("dropped.replay", 0) >= 3
        assert counters(control).get("received", 0) == before
    finally:
        client.endpoint.stop()
        tap.close()


def _hello_from(auth, sender: str, to: str = "") -> bytes:
    """A handshake frame as `auth` would sign it, but claiming the name `sender`."""
    auth.name = sender
    return initiate(auth, "3" * 32, ("127.0.0.1", 9), ("127.0.0.1", 9), to).frame


def test_a_key_holder_cannot_speak_as_another_agent(team):
    robot1 = team("robot1")
    holder = holder_of("robot3")
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as udp:
        udp.bind(("127.0.0.1", 0))
        udp.settimeout(0.5)
        udp.sendto(_hello_from(holder, "control"), addr_of(robot1))
        wait_until(lambda: counters(robot1).get("dropped.auth", 0) >= 1)
        with pytest.raises(TimeoutError):
            udp.recvfrom(65536)  # no answer: no session as "control"

    # with its own name it gets a session, but the session speaks for robot3 only
    mallory = make_agent("robot3", 0, echo=False)
    try:
        ep = mallory.plugin("transport").endpoint
        ep.send(addr_of(robot1), "beacon", None, reliable=False, to="robot1")
        wait_until(lambda: ep.session_with(addr_of(robot1)) is not None)
        session = ep.session_with(addr_of(robot1))
        task = Task(verb="BotMotion", preposition="stop", source="control", destination="robot1")
        for sender, to in (("control", "robot1"), ("robot3", "robot2")):
            env = Envelope(sender=sender, role="robot", to=to, inst=ep.inst, reply=ep.address, seq=99, id=sender,
                           kind="task.add", type="Task", body=task.model_dump(mode="json"))
            with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as udp:
                udp.sendto(session.seal(env.model_dump_json().encode(), 65536), addr_of(robot1))
        wait_until(lambda: counters(robot1).get("dropped.auth", 0) >= 2
                   and counters(robot1).get("dropped.receiver", 0) >= 1)
        assert not robot1.blackboard.contains(task.uid)
    finally:
        mallory.stop()


def test_a_revoked_identity_is_cut_off_and_the_revocation_spreads(team, tmp_path):
    auth = authority()
    crl = tmp_path / "control.crl"
    crl.write_bytes((auth.dir / "revoked.crl").read_bytes())
    control = team("control", echo=False, role="control", revocations=str(crl))
    robot1 = team("robot1", revocations=str(tmp_path / "robot1.crl"))  # learns the list from peers
    mallory = team("mallory", echo=False)
    wait_until(lambda: up(control, "mallory") and up(robot1, "mallory") and up(robot1, "control"))
    revoked = auth.revoke("mallory")
    assert revoked
    crl.write_bytes((auth.dir / "revoked.crl").read_bytes())  # the operator updates the control node
    wait_until(lambda: counters(control).get("sessions.revoked", 0) >= 1, timeout=5)
    wait_until(lambda: counters(robot1).get("sessions.revoked", 0) >= 1, timeout=5)  # from control
    from erni.transport.identity import read_crl

    kept = read_crl(tmp_path / "robot1.crl")  # robot1 keeps the newer list where its config says
    assert {r.serial_number for r in kept} == set(revoked) and kept.issuer == read_crl(crl).issuer
    task = Task(verb="BotMotion", preposition="stop", source="mallory", destination="robot1")
    with mallory.transaction() as tx:
        tx.add(task)
    wait_until(lambda: counters(robot1).get("dropped.revoked", 0) >= 1, timeout=5)
    wait_until(lambda: not up(robot1, "mallory"), timeout=5)
    assert not robot1.blackboard.contains(task.uid)


def test_beacons_cannot_lock_a_peer_out_or_fake_a_dead_one(team):
    """A team-key holder forges control's beacon (the 'huge epoch' attack): robot2 still obeys control."""
    port = free_port()
    control = make_agent("control", port, echo=False, role="control", key=KEY)
    robot2 = make_agent("robot2", port, key=KEY)
    dead = make_agent("robot9", port, key=KEY, echo=False)
    try:
        wait_until(lambda: up(robot2, "control") and up(control, "robot2") and up(robot2, "robot9"))
        from erni.transport.session import TeamKeyAuth

        holder = TeamKeyAuth("control", "control", KEY.encode())
        forged = Envelope(sender="control", role="control", inst="f" * 32, reply=("127.0.0.1", 9), seq=2**62,
                          id="x", kind="beacon", type="Beacon", body={"role": "control"})
        frame = holder.sign(BEACON, forged.model_dump_json().encode())
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as udp:
            for _ in range(20):
                udp.sendto(frame, ("127.0.0.1", port))
                udp.sendto(frame, addr_of(robot2))
            datagrams_read(robot2, udp)  # the forgeries at robot2's port read, and what they brought handled
        peer = robot2.blackboard.get("peer:control")
        assert peer.up and peer.address == "{}:{}".format(*addr_of(control)), "a beacon never moves a live peer"
        task = Task(verb="BotMotion", preposition="forward", params={"distance": 1}, source="control",
                    destination="robot2")
        with control.transaction() as tx:
            tx.add(task)
        wait_until(lambda: control.blackboard.get(task.uid).state is TaskState.SUCCEEDED)

        # robot9 dies; its own beacon, captured and replayed, does not bring it back up
        tap_frames: list[bytes] = []
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as sniff:
            sniff.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
            sniff.bind(("", port))
            sniff.settimeout(0.5)
            while not tap_frames:
                data, _ = sniff.recvfrom(65536)
                if data[4:5] == b"B" and b'"robot9"' in data:
                    tap_frames.append(data)
        dead.stop()
        wait_until(lambda: not up(robot2, "robot9"), timeout=3)
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as udp:
            for _ in range(10):
                udp.sendto(tap_frames[0], addr_of(robot2))
            datagrams_read(robot2, udp)  # all ten read, and what they brought handled
        assert not up(robot2, "robot9"), "a replayed beacon is a hint, never a sign of life"
    finally:
        for agent in (control, robot2, dead):
            agent.stop()


def test_identity_beacons_cannot_be_forged_by_another_key_holder(team):
    robot2 = team("robot2")
    holder = holder_of("robot3")
    forged = Envelope(sender="control", role="control", inst="f" * 32, reply=("127.0.0.1", 9), seq=1,
                      id="x", kind="beacon", type="Beacon", body={"role": "control"})
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as udp:
        udp.sendto(holder.sign(BEACON, forged.model_dump_json().encode()), addr_of(robot2))
    wait_until(lambda: counters(robot2).get("dropped.auth", 0) >= 1)
    assert robot2.blackboard.get("peer:control") is None


def test_handshake_floods_are_answered_at_a_bounded_rate(team):
    robot1 = team("robot1")
    holder = holder_of("robot3")
    frames = [initiate(holder, "3" * 32, ("127.0.0.1", 9), addr_of(robot1), "").frame for _ in range(200)]
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as udp:
        for i, frame in enumerate(frames):
            udp.sendto(frame, addr_of(robot1))
            if i % 20 == 19:  # stay within the socket buffer (datagrams lost by the kernel go uncounted):
                # the batch before this one has been answered or dropped before more go
                wait_until(lambda i=i: counters(robot1).get("dropped.rate", 0)
                           + counters(robot1).get("handshakes.answered", 0) >= i + 1 - 20, timeout=30)
    # a progress bound: each hello costs a signature check, slow on a loaded machine (5 s was missed at load 14)
    wait_until(lambda: counters(robot1).get("dropped.rate", 0) + counters(robot1).get("handshakes.answered", 0)
               >= 150, timeout=30, message="the hellos were not all answered or dropped within 30 s")
    assert counters(robot1).get("handshakes.answered", 0) <= 60  # burst of 20, then 20 per second
    assert counters(robot1).get("dropped.rate", 0) >= 100


def test_a_frame_for_another_agent_in_the_envelope_is_refused():
    """The plain (insecure) envelope names its receiver too: a frame for robot2 at robot1 is dropped."""
    port = free_port()
    robot1 = make_agent("robot1", port, insecure=True)
    try:
        from erni.transport.wire import encode_plain

        task = Task(verb="BotMotion", preposition="stop", source="x", destination="robot2")
        env = Envelope(sender="x", to="robot2", inst="1" * 32, reply=("127.0.0.1", 9), seq=1, id="a",
                       kind="task.add", type="Task", body=task.model_dump(mode="json"))
        send_raw_tcp(addr_of(robot1), encode_plain(env))
        wait_until(lambda: counters(robot1).get("dropped.receiver", 0) >= 1)
        assert not robot1.blackboard.contains(task.uid)
    finally:
        robot1.stop()


def test_a_robot_restarted_with_a_wrong_clock_joins(team, monkeypatch):
    control = team("control", echo=False, role="control")
    robot = team("robot1")
    wait_until(lambda: up(control, "robot1"))
    listen = "{}:{}".format(*addr_of(robot))
    robot.stop()
    wait_until(lambda: not up(control, "robot1"), timeout=3)
    year_2020 = 1_577_836_800.0
    monkeypatch.setattr(time, "time", lambda: year_2020)
    monkeypatch.setattr(time, "time_ns", lambda: int(year_2020 * 1e9))
    again = team("robot1", listen=listen)  # its clock says 2020 while it starts
    monkeypatch.undo()
    wait_until(lambda: up(control, "robot1"), timeout=5)
    task = Task(verb="BotMotion", preposition="stop", source="control", destination="robot1")
    with control.transaction() as tx:
        tx.add(task)
    wait_until(lambda: control.blackboard.get(task.uid).state is TaskState.SUCCEEDED)
    assert again.blackboard.contains(task.uid)
    assert control.blackboard.get("peer:robot1").epoch == 2, "seen as a restart of robot1"


def test_the_client_sees_each_final_state_once(team):
    control = team("control", echo=False, role="control")
    robot1 = team("robot1")
    wait_until(lambda: up(control, "robot1"))
    client = make_client(addr_of(control))
    finals: list[Message] = []
    kinds: list[str] = []
    original = client.endpoint.on_message

    def count(msg: Message) -> None:
        kinds.append(msg.kind)
        if msg.kind == "task.result" and msg.body.result.state.done:
            finals.append(msg)
        original(msg)

    client.endpoint.on_message = count
    try:
        task = Task(verb="BotMotion", preposition="stop", destination="robot1", source=client.endpoint.name)
        client.send(addr_of(control), "task.add", task)
        wait_until(lambda: finals)
        beacon_after(robot1, control)  # what robot1 sent control of the task has come and been handled
        # then a reply on the path control's results take to the client: a second final, sent before
        # it, would have arrived before it
        client.send(addr_of(control), "peers.request", None)
        wait_until(lambda: "peers.reply" in kinds, timeout=30)
        assert len(finals) == 1, f"the final state crossed the wire {len(finals)} times"
    finally:
        client.endpoint.stop()


def test_a_revocation_list_of_another_authority_is_ignored(tmp_path):
    from cryptography.hazmat.primitives.serialization import Encoding

    from erni.transport.identity import Authority, load_identity

    mine = load_identity(identity("robot1"))
    other = Authority.create(tmp_path / "other")
    other.revoke(f"{mine.serial:x}")  # a list that would revoke robot1, signed by a stranger
    assert not mine.trust.adopt(other.crl().public_bytes(Encoding.DER))
    assert mine.serial not in mine.trust.revoked
