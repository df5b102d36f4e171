"""Garbage, strangers, floods and resource exhaustion before authentication: dropped, counted, bounded.

Also the agent's own sockets: an agent that cannot bind exits with one line; port 0 gives TCP
and UDP the same, checked, number.
"""

from __future__ import annotations

import os
import random
import resource
import signal
import socket
import struct
import subprocess
import sys
import time
from pathlib import Path

import pytest

from erni.blackboard import Task
from erni.blackboard.testing import wait_until
from tests.transport.helpers import Tap, agent_config, datagrams_read, free_port, make_agent, make_client, settled

ROOT = Path(__file__).resolve().parents[2]


@pytest.fixture
def robot():
    agent = make_agent("robot1", free_port(), max_frame=4096, max_connections_per_host=8, frame_timeout=0.5)
    yield agent
    agent.stop()


def task() -> Task:
    return Task(verb="BotMotion", preposition="forward", params={"distance": 1}, source="x",
                destination="robot1")


def counters(agent) -> dict[str, int]:
    return agent.plugin("transport").endpoint.counters


def addr_of(agent) -> tuple[str, int]:
    return agent.plugin("transport").address


def closed_by_peer(sock: socket.socket, timeout: float) -> bool:
    """True when the other end closes the connection within `timeout` seconds (what it said first is read)."""
    deadline = time.monotonic() + timeout
    try:
        while True:
            sock.settimeout(max(0.001, deadline - time.monotonic()))
            if sock.recv(65536) == b"":
                return True
    except (ConnectionResetError, BrokenPipeError):
        return True
    except (TimeoutError, OSError):
        return False


def test_garbage_datagrams_and_streams_reach_nothing(robot):
    addr = addr_of(robot)
    rng = random.Random(1)
    udp = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    payloads = [bytes(rng.randrange(256) for _ in range(rng.randrange(1, 600))) for _ in range(200)]
    payloads += [struct.pack(">I", 2**31) + b"D" + b"x" * 20, b"\x00" * 4, b"\x00\x00\x00\x09K12345678"]

    def dropped() -> int:
        return sum(v for k, v in counters(robot).items() if k.startswith("dropped."))

    before = dropped()
    for i, p in enumerate(payloads):
        udp.sendto(p, addr)
        if i % 20 == 19:  # stay within the socket buffer (datagrams lost by the kernel go uncounted):
            # the batch before this one has been read and dropped before more go
            wait_until(lambda i=i: dropped() >= before + i + 1 - 20, timeout=30)
    datagrams_read(robot, udp)  # every one of them read (and the marker dropped), anything they brought handled
    counted = len(payloads) - 1  # all but the hint, of no session of ours: ignored, not counted
    assert dropped() >= before + counted + 1
    for chunk in (bytes(rng.randrange(256) for _ in range(3000)), struct.pack(">I", 10**9) + b"xx",
                  b"\x00\x00\x00\x40D" + os.urandom(20)):
        with socket.create_connection(addr) as tcp:
            tcp.sendall(chunk)
    udp.close()
    wait_until(lambda: dropped() >= before + counted + 1 + 3, timeout=30)  # and each stream, at its first bytes
    settled(robot)
    assert robot.query(Task) == []
    client = make_client(addr)  # the agent still works: a real client after all that garbage
    try:
        client.send(addr, "task.add", task())
        wait_until(lambda: robot.query(Task))
    finally:
        client.endpoint.stop()


def test_a_stranger_of_another_team_is_refused_and_never_listed(robot, tmp_path):
    from erni.transport.identity import Authority

    other = Authority.create(tmp_path / "other-team")
    path = other.issue("outsider", "robot")
    port = robot.plugin("transport").settings.discovery_port
    outsider = make_agent("outsider", port, echo=False, identity=str(path))
    try:
        ep = outsider.plugin("transport").endpoint
        ep.send(addr_of(robot), "task.add", task(), reliable=True, ttl=1.0)
        wait_until(lambda: counters(robot).get("dropped.auth", 0) >= 2)  # its beacons and its handshakes
        settled(robot)  # what the robot's transport was handed so far has run: no session, no task
        assert robot.query(Task) == []
        assert robot.blackboard.get("peer:outsider") is None
    finally:
        outsider.stop()


def test_oversized_frames_are_refused(robot):
    with socket.create_connection(addr_of(robot)) as tcp:
        tcp.sendall(struct.pack(">I", 5000) + b"D" + b"\x00" * 100)
        wait_until(lambda: counters(robot).get("dropped.size", 0) >= 1)
        assert closed_by_peer(tcp, 2)


def test_connections_beyond_the_caps_are_refused_and_others_still_served(robot):
    flood = []
    try:
        for _ in range(40):  # from one host, beyond its cap of 8
            s = socket.socket()
            s.bind(("127.0.0.3", 0))
            s.connect(addr_of(robot))
            flood.append(s)
        # beyond the host's cap the oldest stranger of that host makes room (or the newcomer is refused)
        wait_until(lambda: counters(robot).get("refused.connections", 0) + counters(robot).get("closed.evicted", 0) >= 32)
        assert sum(closed_by_peer(s, 0.05) for s in flood) >= 32
        client = make_client(addr_of(robot))  # another host is not held up by that one
        try:
            client.send(addr_of(robot), "task.add", task())
            wait_until(lambda: robot.query(Task))
        finally:
            client.endpoint.stop()
    finally:
        for s in flood:
            s.close()


def test_a_frame_of_no_session_is_closed_at_once_not_at_the_frame_timeout():
    """The start of a frame names a session the agent does not know: the stream is closed on it,
    long before the frame timeout (10 minutes here) would close it for being incomplete."""
    patient = make_agent("robot1", free_port(), max_frame=4096, frame_timeout=600.0)
    try:
        unknown = socket.create_connection(addr_of(patient))
        unknown.sendall(struct.pack(">IB8sQ", 3000, ord("D"), b"12345678", 1) + b"x" * 1000)
        assert closed_by_peer(unknown, 30.0)
        wait_until(lambda: counters(patient).get("dropped.session", 0) >= 1, timeout=30)
        assert counters(patient).get("closed.timeout", 0) == 0
        unknown.close()
    finally:
        patient.stop()


def test_idle_and_partial_frame_connections_are_closed(robot):
    addr = addr_of(robot)
    idle = socket.create_connection(addr)
    unknown = socket.create_connection(addr)  # a frame of no session of ours: closed (at once: the test above)
    unknown.sendall(struct.pack(">IB8sQ", 3000, ord("D"), b"12345678", 1) + b"x" * 1000)
    assert closed_by_peer(unknown, 30.0)
    client = make_client(addr)  # a real session, whose id an eavesdropper could read on the mesh
    tap_sid = None
    try:
        client.send(addr, "watch.request", None)
        wait_until(lambda: client.endpoint.session_with(addr) is not None)
        tap_sid = client.endpoint.session_with(addr).sid
        partial = socket.create_connection(addr)
        partial.sendall(struct.pack(">IB8sQ", 3000, ord("D"), tap_sid, 10**9) + b"x" * 1000)
        started = time.monotonic()
        assert closed_by_peer(partial, 30.0), "a frame left half-sent is not held forever"
        assert time.monotonic() - started >= 0.3  # not before its 0.5 s frame timeout
        assert closed_by_peer(idle, 30.0), "a connection that never authenticates is closed"
        assert counters(robot).get("closed.timeout", 0) >= 2 and counters(robot).get("dropped.session", 0) >= 1
    finally:
        client.endpoint.stop()
        for s in (idle, unknown):
            s.close()


def _rss_kib(pid: int) -> int:
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1])
    raise AssertionError("no VmRSS")


def _cpu_seconds(pid: int) -> float:
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def _start(config: Path, nofile: int | None = None) -> subprocess.Popen[str]:
    def limits() -> None:
        if nofile:
            resource.setrlimit(resource.RLIMIT_NOFILE, (nofile, nofile))

    return subprocess.Popen([sys.executable, "-m", "erni", "agent", str(config)], cwd=ROOT,
                            stderr=subprocess.PIPE, text=True, preexec_fn=limits,
                            env={**os.environ, "PYTHONUNBUFFERED": "1"})


def _stop(proc: subprocess.Popen[str]) -> str:
    proc.send_signal(signal.SIGINT)
    try:
        proc.wait(10)
    except subprocess.TimeoutExpired:
        proc.kill()
        proc.wait(5)
    return proc.stderr.read() if proc.stderr else ""


def _unread_at(port: int) -> int:
    """Bytes waiting unread in the receive queues of the TCP sockets on local `port` (/proc/net/tcp)."""
    unread = 0
    for line in Path("/proc/net/tcp").read_text().splitlines()[1:]:
        fields = line.split()
        if int(fields[1].rsplit(":", 1)[1], 16) == port:
            unread += int(fields[4].split(":")[1], 16)
    return unread


def _peers_ok(addr: tuple[str, int]) -> bool:
    client = make_client(addr)
    try:
        client.send(addr, "peers.request", None)
        deadline = time.monotonic() + 3
        while time.monotonic() < deadline:
            msg = client.receive(0.1)
            if msg is not None and msg.kind == "peers.reply":
                return True
        return False
    finally:
        client.endpoint.stop()


@pytest.mark.slow
def test_half_sent_frames_and_a_full_fd_table_cost_bounded_memory_and_no_spinning(tmp_path):
    """400 connections each holding half of a 250 kB frame, at an agent limited to 256 open files."""
    port = free_port(socket.SOCK_STREAM)
    config = agent_config(tmp_path / "robot.toml", "robot1", listen=f"127.0.0.1:{port}", frame_timeout=3.0,
                          max_connections=64, echo=None)
    proc = _start(config, nofile=256)
    flood: list[socket.socket] = []
    tap = None
    try:
        addr = ("127.0.0.1", port)
        wait_until(lambda: _peers_ok(addr), timeout=15, interval=0.3)
        tap = Tap(addr)  # an eavesdropper learns a live session id
        client = make_client(tap.address)
        client.send(tap.address, "watch.request", None, reliable=False)
        wait_until(lambda: any(d[4] == ord("D") for d in tap.datagrams))
        sid = next(d for d in tap.datagrams if d[4] == ord("D"))[5:13]
        client.endpoint.stop()
        before_rss, before_cpu = _rss_kib(proc.pid), _cpu_seconds(proc.pid)
        half = struct.pack(">IB8sQ", 250_000, ord("D"), sid, 10**9) + os.urandom(125_000)
        for i in range(400):
            s = socket.socket()
            s.bind((f"127.0.0.{10 + i % 20}", 0))
            s.settimeout(2)
            try:
                s.connect(addr)
                s.sendall(half)
            except OSError:
                pass  # refused or reset: the cap at work
            flood.append(s)
        # the agent has read what the flood sent it (no byte waits unread at its port): what it holds, it holds now
        wait_until(lambda: _unread_at(port) == 0, timeout=30, interval=0.05)
        grown = (_rss_kib(proc.pid) - before_rss) / 1024
        spent = _cpu_seconds(proc.pid) - before_cpu
        assert _peers_ok(addr), "the agent still answers while the flood is held"
        cpu_window = time.monotonic()
        cpu_start = _cpu_seconds(proc.pid)
        time.sleep(2.0)  # real time must pass: the CPU the agent spends in it is what is measured
        busy = (_cpu_seconds(proc.pid) - cpu_start) / (time.monotonic() - cpu_window)
        print(f"half frames: RSS +{grown:.1f} MiB, CPU {spent:.2f} s while flooded, then {busy:.0%} of a core")
        assert grown < 24, f"memory held for unauthenticated frames grew by {grown:.0f} MiB"
        assert busy < 0.25, "the receive loop spins"
        alive = [s for s in flood if not closed_by_peer(s, 0.01)]
        # past frame_timeout (3 s of the agent's clock, in its own process): every half frame is dropped
        wait_until(lambda: all(closed_by_peer(s, 0.01) for s in alive), timeout=30, interval=0.1)
    finally:
        for s in flood:
            s.close()
        if tap is not None:
            tap.close()
        log = _stop(proc)
    assert "Traceback" not in log, log


def test_an_agent_that_cannot_bind_exits_with_one_line(tmp_path):
    busy = socket.socket()
    busy.bind(("127.0.0.1", 0))
    busy.listen(1)
    port = busy.getsockname()[1]
    config = agent_config(tmp_path / "robot.toml", "robot1", listen=f"127.0.0.1:{port}", echo=None)
    try:
        out = subprocess.run([sys.executable, "-m", "erni", "agent", str(config)], capture_output=True,
                             text=True, timeout=30, cwd=ROOT)
    finally:
        busy.close()
    assert out.returncode == 2
    lines = out.stderr.strip().splitlines()
    assert len(lines) == 1, out.stderr
    assert f"cannot listen on 127.0.0.1:{port} (TCP)" in lines[0] and "in use" in lines[0]


def test_port_zero_gives_tcp_and_udp_one_checked_number(monkeypatch):
    """The first free TCP port is taken for UDP: the endpoint draws another, never two numbers."""
    from erni.transport import endpoint as module

    real = socket.socket
    for _ in range(50):  # a number UDP holds (ours) and TCP does not (no other program's connection)
        taken = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        taken.bind(("127.0.0.1", 0))
        port = taken.getsockname()[1]
        try:
            with real(socket.AF_INET, socket.SOCK_STREAM) as probe:
                probe.bind(("127.0.0.1", port))
            break
        except OSError:
            taken.close()
    first = [True]

    class Steered(real):  # the kernel's first TCP pick happens to be a number UDP holds
        def bind(self, address):
            if self.type == socket.SOCK_STREAM and address[1] == 0 and first[0]:
                first[0] = False
                return super().bind((address[0], port))
            return super().bind(address)

    monkeypatch.setattr(module.socket, "socket", Steered)
    from erni.transport import Endpoint

    ep = Endpoint("solo", insecure=True)
    try:
        ep.start()
        assert not first[0], "the collision happened"
        assert ep.address[1] != port
        assert ep._tcp.getsockname()[1] == ep._udp.getsockname()[1] == ep.address[1]
    finally:
        ep.stop()
        taken.close()


def test_insecure_mode_must_be_explicit():
    from pydantic import ValidationError

    from erni.transport import TransportSettings

    with pytest.raises(ValidationError, match="no identity: set identity"):
        TransportSettings(key_env="NO_SUCH_VAR")
    with pytest.raises(ValidationError, match="cannot read the identity"):
        TransportSettings(identity="/no/such/robot.pem")
    assert TransportSettings(insecure=True).insecure


def test_key_never_appears_in_logs_or_reprs():
    from erni.transport import TransportSettings

    s = TransportSettings(key="s3cret-team-key")
    assert "s3cret" not in repr(s) and "s3cret" not in str(s.model_dump())


def test_a_short_data_frame_naming_a_live_session_is_dropped_and_the_agent_hears_on(robot):
    """A sealed frame's session id travels in clear: an eavesdropper without any key sent a 'D'
    frame of 13-20 bytes naming it, and the header's unpacking killed the receive thread."""
    addr = addr_of(robot)
    client = make_client(addr)
    try:
        client.send(addr, "watch.request", None)
        wait_until(lambda: client.endpoint.session_with(addr) is not None)
        sid = client.endpoint.session_with(addr).sid
        udp = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        for cut in range(0, 13):  # every length from the bare kind and session id to one byte short of a header
            udp.sendto(struct.pack(">I", 9 + cut) + b"D" + sid + b"\x00" * cut, addr)
        udp.close()
        wait_until(lambda: counters(robot).get("dropped.short", 0) >= 13)
        before = len(robot.query(Task))
        client.send(addr, "task.add", task())  # over the same session: the receive thread lives
        wait_until(lambda: len(robot.query(Task)) > before)
    finally:
        client.endpoint.stop()


def test_a_fault_of_the_frame_path_drops_that_frame_only(robot, monkeypatch, caplog):
    """Any exception of the frame path but a FrameError (a bug, as the short frame above was) is
    counted and logged once with its traceback; the receive thread goes on."""
    import erni.transport.inbound as inbound

    real = inbound.check_frame

    def faulty(raw, max_frame):
        if raw.endswith(b"POISON"):
            raise RuntimeError("a bug in the frame path")
        return real(raw, max_frame)

    monkeypatch.setattr(inbound, "check_frame", faulty)
    addr = addr_of(robot)
    udp = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    for _ in range(3):
        udp.sendto(struct.pack(">I", 7) + b"xPOISON", addr)
    udp.close()
    wait_until(lambda: counters(robot).get("dropped.fault", 0) >= 3)
    assert sum("the frame path failed on it" in r.getMessage() for r in caplog.records) == 1
    before = len(robot.query(Task))
    client = make_client(addr)
    try:
        client.send(addr, "task.add", task())
        wait_until(lambda: len(robot.query(Task)) > before)
    finally:
        client.endpoint.stop()
