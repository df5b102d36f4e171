"""Agents with a transport on loopback, for the transport tests: one team authority per test
session, an identity per agent name (issued on first use)."""

from __future__ import annotations

import socket
import subprocess
import tempfile
import threading
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

from erni.blackboard import Agent, Pose, Task
from erni.blackboard.testing import wait_until

try:
    from erni.transport.identity import Authority
except ImportError:  # a transport without identities (the tests then fall back to the team key)
    Authority = None  # type: ignore[assignment,misc]

KEY = "test-team-key"  # a shared team key, for the tests of that mode
_KEYS: dict[str, Any] = {}
_LOCK = threading.Lock()


def authority() -> Authority:
    """The test session's team authority (made once, in a temporary directory)."""
    with _LOCK:
        if "authority" not in _KEYS:
            _KEYS["dir"] = tempfile.TemporaryDirectory(prefix="erni-test-keys-")
            _KEYS["authority"] = Authority.create(_KEYS["dir"].name, team="erni tests")
        return _KEYS["authority"]


def identity(name: str, role: str = "") -> str:
    """Path of the identity bundle of `name` in `role` (issued once per session; by default role
    control for a control node, robot otherwise)."""
    if Authority is None:
        return ""
    role = role or ("control" if name.startswith("control") else "robot")
    auth = authority()
    with _LOCK:
        key = f"{name}/{role}"
        if key not in _KEYS:
            _KEYS[key] = str(auth.issue(name, role, Path(auth.dir) / f"{name}.{role}.pem"))
        return str(_KEYS[key])


def auth_settings(name: str, role: str = "") -> dict[str, Any]:
    """Transport settings that authenticate agent `name`: its identity (the team key where the
    transport has no identities)."""
    return {"identity": identity(name, role)} if Authority is not None else {"key": KEY}


def free_port(kind: int = socket.SOCK_DGRAM) -> int:
    """A port free for TCP and UDP now, below the ephemeral range: no socket bound to port 0 (in
    this test run or in another program on the machine) takes it before the test binds it."""
    import random

    try:
        low = int(Path("/proc/sys/net/ipv4/ip_local_port_range").read_text().split()[0])
    except (OSError, ValueError, IndexError):
        low = 32768
    for _ in range(200):
        port = random.randrange(10_000, max(10_001, low))
        try:
            for k in (socket.SOCK_STREAM, socket.SOCK_DGRAM):
                with socket.socket(socket.AF_INET, k) as s:
                    s.bind(("127.0.0.1", port))
        except OSError:
            continue
        return port
    with socket.socket(socket.AF_INET, kind) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


class HeldClock:
    """The wall's monotonic clock until `hold()`, then still but for `advance()`: an agent on it runs
    in real time, then times its waits (a performer's silence, its link deadline) as the test says."""

    def __init__(self) -> None:
        self.held: float | None = None
        self._watchers: list[Any] = []

    def __call__(self) -> float:
        return time.monotonic() if self.held is None else self.held

    def on_advance(self, fn: Any) -> None:
        self._watchers.append(fn)

    def hold(self) -> float:
        self.held = time.monotonic()
        return self.held

    def advance(self, seconds: float) -> None:
        assert self.held is not None and seconds >= 0
        self.held += seconds
        for fn in list(self._watchers):
            fn()


def settled(agent: Agent, plugin: str = "transport", timeout: float = 10.0) -> None:
    """Wait until what `agent`'s `plugin` was handed with `later()` so far (the messages its endpoint
    received) has been handled and its run committed: a marker handed after them runs in a later run
    (or the same one), and is called after that run's commit."""
    done = threading.Event()
    target = agent.plugin(plugin)
    target.later(lambda: target.after_commit(done.set))
    assert done.wait(timeout), f"{agent.name}/{plugin} did not run within {timeout} s"


def _transport(agent: Agent) -> Any:
    """The agent's transport plugin (its collaborators, untyped here)."""
    return agent.plugin("transport")


def datagrams_read(target: Any, udp: socket.socket, timeout: float = 30.0) -> None:
    """Wait until `target` (an agent with the transport, or an Endpoint) has read every datagram sent
    on `udp` so far: a datagram too short to be a frame is sent after them on the same socket, and
    its drop counted (one receive thread reads a port's datagrams in order, and hands what they carry
    on before it reads the next). For an agent, then wait until what they handed its transport has
    been handled (`settled`)."""
    endpoint: Any = _transport(target).endpoint if isinstance(target, Agent) else target
    counters: dict[str, int] = endpoint.counters
    before = counters.get("dropped.size", 0)
    udp.sendto(b"?", endpoint.address)
    wait_until(lambda: counters.get("dropped.size", 0) > before, timeout=timeout,
               message=f"{endpoint.name} read no marker datagram within {timeout} s")
    if isinstance(target, Agent):
        settled(target, timeout=timeout)


def beacon_after(sender: Agent, receiver: Agent, timeout: float = 30.0) -> None:
    """Wait until `receiver` has heard an in-session beacon that `sender` sent it after everything
    it sent it unreliably so far (statuses and beacons to one peer leave in order, one socket to
    one port, read in order), and has handled what came before it (`settled`): a status `sender`
    shared with `receiver` before now would be on its board."""
    name = receiver.name
    record = _transport(sender).presence.peers.get(name)
    sent: int = record.beacons_sent if record is not None else 0
    heard: dict[str, Any] = _transport(receiver).presence.peers

    def later_beacon() -> bool:
        rec = heard.get(sender.name)
        return rec is not None and rec.beacon_count is not None and rec.beacon_count.last > sent

    wait_until(later_beacon, timeout=timeout,
               message=f"{name} heard no beacon {sender.name} sent after #{sent} within {timeout} s")
    settled(receiver, timeout=timeout)


class SkipClock:
    """Monotonic time that runs as the wall's, plus what `skip()` added: a timer of the code under
    test on it falls due at once when the test skips past it, and nothing else stands still."""

    def __init__(self) -> None:
        self.skipped = 0.0

    def __call__(self) -> float:
        return time.monotonic() + self.skipped

    def skip(self, seconds: float) -> None:
        assert seconds >= 0
        self.skipped += seconds


def make_agent(name: str, discovery_port: int, *, echo: bool = True, start: bool = True,
               clock: Callable[[], float] | None = None, **settings: Any) -> Agent:
    """An agent with the transport (fast timings, its own identity) and, optionally, the echo performer.
    `clock`: the agent's clock (a test's, to time the transport's waits: see `erni.testing.ManualClock`)."""
    agent = Agent(name, workers=2) if clock is None else Agent(name, workers=2, clock=clock)
    # a control node operates the team, as under `erni sim`: its role lets it task the robots
    role = settings.setdefault("role", "control" if name.startswith("control") else "robot")
    base: dict[str, Any] = {"discovery_port": discovery_port, "beacon_period": 0.1,
                            "peer_timeout": 0.6, "ack_timeout": 0.3, "connect_timeout": 0.3,
                            "task_ttl": 5.0}
    if not settings.get("insecure") and "key" not in settings and "identity" not in settings:
        base.update(auth_settings(name, role))
    base.update(settings)
    agent.add_plugin("transport", settings=base, name="transport")
    if echo:
        agent.add_plugin("echo", settings={"verbs": ["BotMotion"], "delay": 0.05}, name="motion")
    return agent.start() if start else agent


def make_client(via: tuple[str, int] | None, **kw: Any) -> Any:
    """A started command-line client of the test team (identity `cli`, role cli)."""
    import os

    from erni.transport.client import Client

    if Authority is None:
        os.environ["ERNI_TEST_KEY"] = KEY
        client = Client(via, key_env="ERNI_TEST_KEY", **kw)
    else:
        client = Client(via, identity=identity("cli", "cli"), **kw)
    client.endpoint.start()
    return client


class Tap:
    """An eavesdropper on the path to one agent: TCP and UDP on one port forwarded to `target`,
    everything the client side sends recorded as it crossed the wire."""

    def __init__(self, target: tuple[str, int]):
        self.target = target
        for _ in range(32):
            self._tcp = socket.socket()
            self._tcp.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
            self._tcp.bind(("127.0.0.1", 0))
            self._udp = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
            try:
                self._udp.bind(self._tcp.getsockname())
                break
            except OSError:
                self._tcp.close()
                self._udp.close()
        self.address: tuple[str, int] = self._tcp.getsockname()
        self._tcp.listen(16)
        self._tcp.settimeout(0.1)
        self._udp.settimeout(0.1)
        self.streams: list[bytearray] = []  # client -> agent, one per TCP connection
        self.datagrams: list[bytes] = []  # client -> agent
        self._client_udp: tuple[str, int] | None = None
        self._stop = threading.Event()
        self._threads = [threading.Thread(target=self._accept, daemon=True),
                         threading.Thread(target=self._relay_udp, daemon=True)]
        for t in self._threads:
            t.start()

    def _accept(self) -> None:
        while not self._stop.is_set():
            try:
                conn, _ = self._tcp.accept()
            except (TimeoutError, OSError):
                continue
            upstream = socket.create_connection(self.target)
            record = bytearray()
            self.streams.append(record)
            for src, dst, rec in ((conn, upstream, record), (upstream, conn, None)):
                t = threading.Thread(target=self._pump, args=(src, dst, rec), daemon=True)
                t.start()
                self._threads.append(t)

    def _pump(self, src: socket.socket, dst: socket.socket, record: bytearray | None) -> None:
        src.settimeout(0.1)
        try:
            while not self._stop.is_set():
                try:
                    data = src.recv(65536)
                except TimeoutError:
                    continue
                if not data:
                    break
                if record is not None:
                    record += data
                dst.sendall(data)
        except OSError:
            pass
        finally:
            for s in (src, dst):
                try:
                    s.shutdown(socket.SHUT_RDWR)
                except OSError:
                    pass
            src.close()

    def _relay_udp(self) -> None:
        while not self._stop.is_set():
            try:
                data, src = self._udp.recvfrom(65536)
            except (TimeoutError, OSError):
                continue
            if src == self.target:
                if self._client_udp is not None:
                    self._udp.sendto(data, self._client_udp)
            else:
                self._client_udp = src
                self.datagrams.append(data)
                self._udp.sendto(data, self.target)

    def close(self) -> None:
        self._stop.set()
        for t in self._threads:
            t.join(2)
        self._tcp.close()
        self._udp.close()


ECHO = """
[[plugin]]
class = "echo"
name = "motion"
[plugin.settings]
verbs = ["BotMotion"]
delay = {delay}
"""


def agent_config(path: Path, name: str, *, listen: str = "127.0.0.1:0", discovery_port: int = 0,
                 role: str = "", echo: float | None = 0.2, agent: str = "", **settings: Any) -> Path:
    """Write an `erni agent` config: the transport with this agent's identity, optionally the echo plugin
    (role control for a control node, robot otherwise, unless given)."""
    from erni.sim.team import toml_value

    role = role or ("control" if name.startswith("control") else "robot")

    values = {"listen": listen, "discovery_port": discovery_port, "role": role, "beacon_period": 0.2,
              **auth_settings(name, role), **settings}
    lines = ["[agent]", f"name = {toml_value(name)}", agent, "[[plugin]]", 'class = "transport"',
             "[plugin.settings]"] + [f"{k} = {toml_value(v)}" for k, v in values.items()]
    text = "\n".join(lines) + "\n" + (ECHO.format(delay=echo) if echo is not None else "")
    path.write_text(text, encoding="utf-8")
    return path


def two_tasks_recorded(control: Agent, robot: Agent, recorder: subprocess.Popen[str], *,
                       theta: float = 0.0, timeout: float = 30.0) -> tuple[list[Task], str, str]:
    """While `recorder` (an `erni record ...` of the control node) runs: wait until it has leased its
    watch, then robot1 publishes its Pose and the control node sends it two forward tasks, one after
    the other, the Pose stepping to x = 1 and 2 as they go; wait until both end and the recorder exits.
    Returns the tasks and the recorder's stdout and stderr."""
    # the recorder has leased its watch of the control node (its stream starts with what is there now)
    watchers = _transport(control).watchers.watchers
    wait_until(lambda: watchers, timeout=timeout, message=f"the recorder leased no watch within {timeout} s")
    pose = Pose(robot="robot1", x=0.0, theta=theta)
    with robot.transaction() as tx:
        tx.add(pose)
    tasks = [Task(verb="BotMotion", preposition="forward", params={"distance": d}, source="control",
                  destination="robot1") for d in (1.0, 2.0)]
    for i, task in enumerate(tasks):
        with control.transaction() as tx:
            tx.add(task)
        with robot.transaction() as tx:
            tx.change(pose.evolve(x=float(i + 1)))
        # the step has reached the control node (a watch event of its own) and the task has ended
        # before the next one goes: the recording shows the Pose stepping as the tasks go
        def stepped(x: float = float(i + 1)) -> bool:
            return getattr(control.blackboard.get(pose.uid), "x", None) == x

        def ended(uid: str = task.uid) -> bool:
            return bool(getattr(control.blackboard.get(uid), "done", False))

        wait_until(stepped, timeout=timeout)
        wait_until(ended, timeout=timeout)
    wait_until(lambda: all(control.blackboard.get(t.uid).done for t in tasks))
    out, err = recorder.communicate(timeout=timeout)
    assert recorder.returncode == 0, err
    return tasks, out, err


class FullSocket:
    """The endpoint's UDP socket with its send buffer full while `full` is set: sendto raises
    EAGAIN at once, as a non-blocking socket does (loopback drops instead, so it is simulated)."""

    def __init__(self, sock: socket.socket):
        self.sock, self.full, self.refused = sock, threading.Event(), 0

    def sendto(self, data: bytes, *flags_addr: Any) -> int:  # (data, addr) or (data, flags, addr), as a socket's
        if self.full.is_set():
            self.refused += 1
            raise BlockingIOError(11, "Resource temporarily unavailable")
        return self.sock.sendto(data, *flags_addr)

    def __getattr__(self, name: str) -> Any:
        return getattr(self.sock, name)


def endpoint(name: str, **kw: Any) -> tuple[Any, list[Any]]:
    """A started Endpoint of identity `name` and the list its messages go to."""
    from erni.transport import Endpoint
    from erni.transport.identity import load_identity

    ep = Endpoint(name, identity=load_identity(identity(name)), ack_timeout=2.0, connect_timeout=0.5, **kw)
    got: list[Any] = []
    ep.on_message = got.append
    ep.start()
    return ep, got


@contextmanager
def session_up(a_name: str, b_name: str, **a_kw: Any) -> Iterator[tuple[Any, Any, list[Any]]]:
    """Two endpoints whose session is up (a's first status, r0, has reached b); stopped after.
    `a_kw`: more arguments of a's Endpoint (its `pace`, say)."""
    a, _ = endpoint(a_name, **a_kw)
    b, got = endpoint(b_name)
    try:
        a.send(b.address, "status", Pose(robot="r0"), reliable=False, to=b_name)  # starts the session
        wait_until(lambda: len(got) == 1)
        yield a, b, got
    finally:
        a.stop()
        b.stop()
