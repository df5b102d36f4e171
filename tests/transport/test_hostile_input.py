"""Garbage, truncated, oversized, wrongly keyed and replayed frames: dropped, counted, harmless."""

from __future__ import annotations

import random
import socket
import struct
import time

import pytest

from erni.blackboard import Task
from erni.blackboard.testing import wait_until
from erni.transport import Peer
from erni.transport.wire import Envelope, encode
from tests.transport.helpers import KEY, free_port, make_agent


@pytest.fixture
def robot():
    agent = make_agent("robot1", free_port(), max_frame=4096)
    yield agent
    agent.stop()


def frame_for(task: Task, key: bytes, seq: int, epoch: int = 1, sender: str = "intruder") -> bytes:
    env = Envelope(sender=sender, reply=("127.0.0.1", 9), epoch=epoch, seq=seq, id=f"id{seq}",
                   kind="task.add", type="Task", body=task.model_dump(mode="json"))
    return encode(env, key)


def task() -> Task:
    return Task(verb="BotMotion", preposition="forward", params={"distance": 1}, source="x",
                destination="robot1")


def counters(agent) -> dict[str, int]:
    return agent.plugin("transport").endpoint.counters


def test_garbage_datagrams_and_streams_reach_nothing(robot):
    addr = robot.plugin("transport").address
    rng = random.Random(1)
    udp = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    good = frame_for(task(), KEY.encode(), 1)
    payloads = [bytes(rng.randrange(256) for _ in range(rng.randrange(1, 600))) for _ in range(200)]
    payloads += [good[:n] for n in (3, 4, 10, len(good) - 1)]  # truncated
    payloads += [struct.pack(">I", 2**31) + good[4:], b"\x00" * 4]  # absurd and empty lengths
    for i, p in enumerate(payloads):
        udp.sendto(p, addr)
        if i % 20 == 19:
            time.sleep(0.005)  # stay within the socket buffer: datagrams lost by the kernel go uncounted
    for chunk in (bytes(rng.randrange(256) for _ in range(3000)), struct.pack(">I", 10**9) + b"xx",
                  good[: len(good) // 2]):
        with socket.create_connection(addr) as tcp:
            tcp.sendall(chunk)
    udp.close()
    wait_until(lambda: sum(v for k, v in counters(robot).items() if k.startswith("dropped.")) >= 150)
    time.sleep(0.2)
    assert robot.query(Task) == []
    # the agent still works: a good frame after all that garbage is accepted
    with socket.create_connection(addr) as tcp:
        tcp.sendall(frame_for(task(), KEY.encode(), 2))
        wait_until(lambda: robot.query(Task))


def test_wrong_key_is_refused_and_counted(robot):
    addr = robot.plugin("transport").address
    with socket.create_connection(addr) as tcp:
        tcp.sendall(frame_for(task(), b"not-the-team-key", 1))
        wait_until(lambda: counters(robot).get("dropped.auth", 0) >= 1)
    assert robot.query(Task) == []


def test_oversized_frames_are_refused(robot):
    addr = robot.plugin("transport").address
    big = Task(verb="BotMotion", preposition="forward", params={"distance": 1}, source="x" * 60,
               destination="robot1").with_result(message="y" * 10_000)
    with socket.create_connection(addr) as tcp:
        tcp.sendall(frame_for(big, KEY.encode(), 1))
        wait_until(lambda: counters(robot).get("dropped.size", 0) >= 1)
    assert robot.query(Task) == []


def test_replayed_frames_are_refused_and_restarts_accepted(robot):
    addr = robot.plugin("transport").address
    first = frame_for(task(), KEY.encode(), 5, epoch=100)
    udp = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    udp.sendto(first, addr)
    wait_until(lambda: len(robot.query(Task)) == 1)
    with robot.transaction() as tx:  # the performer's side forgets the task
        tx.remove(robot.query(Task)[0])
    udp.sendto(first, addr)  # the very same bytes again
    wait_until(lambda: counters(robot).get("dropped.replay", 0) == 1)
    older_boot = frame_for(task(), KEY.encode(), 99, epoch=50)
    udp.sendto(older_boot, addr)
    wait_until(lambda: counters(robot).get("dropped.replay", 0) == 2)
    assert robot.query(Task) == []
    restarted = frame_for(task(), KEY.encode(), 1, epoch=200)  # a rebooted sender starts at 1
    udp.sendto(restarted, addr)
    wait_until(lambda: len(robot.query(Task)) == 1)
    udp.close()


def test_agent_without_the_team_key_cannot_task(robot):
    port = robot.plugin("transport").settings.discovery_port
    outsider = make_agent("outsider", port, echo=False, key="another-key")
    try:
        time.sleep(0.5)  # beacons both ways are refused
        assert not [p for p in robot.query(Peer) if p.name == "outsider"]
        ep = outsider.plugin("transport").endpoint
        ep.send(robot.plugin("transport").address, "task.add", task(), reliable=True, ttl=1.0)
        wait_until(lambda: counters(robot).get("dropped.auth", 0) >= 3)
        assert robot.query(Task) == []
    finally:
        outsider.stop()


def test_insecure_mode_must_be_explicit():
    from pydantic import ValidationError

    from erni.transport import TransportSettings

    with pytest.raises(ValidationError, match="no team key: set key, the NO_SUCH_VAR environment"):
        TransportSettings(key_env="NO_SUCH_VAR")
    assert TransportSettings(insecure=True).insecure


def test_key_never_appears_in_logs_or_reprs(caplog):
    from erni.transport import TransportSettings

    s = TransportSettings(key="s3cret-team-key")
    assert "s3cret" not in repr(s) and "s3cret" not in str(s.model_dump())
