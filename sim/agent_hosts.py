"""A simulated team whose robot agents run on more than one host.

The world host runs `erni sim` as always (the simulator's robots, their SNMP nodes, the radio
model, the control node) and the agents of its own share of the robots; each agent host runs
the agents of its share with `erni sim --join DIR`. Every agent listens on its host's address,
reaches its simulated robot (TCP) and SNMP node (UDP) on the world host, and finds the others
by broadcast beacons on the hosts' shared segment.

The simulated radio crosses hosts as well: the world host serves the agents' reachability on a
TCP port of its own (the radio feed) and each agent host hands it on to its agents through the
same pipes `erni sim` gives agents on one host (`erni.sim.radio`). The agent host and the world
host each prove to the other that they hold the secret of the bundle (a challenge answered with
HMAC-SHA256), so neither takes lines from a stranger; the bundle
(`RUN/hosts/host-K`: configs, keys, the join file) is this user's only and is copied to the host.
When the world host ends the run its feed closes, and every agent host stops its agents.
"""

from __future__ import annotations

import hashlib
import hmac
import ipaddress
import json
import logging
import os
import secrets
import signal
import socket
import subprocess
import sys
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import IO, Any

from erni.blackboard.errors import ConfigError, NetworkError, UsageError
from erni.sim.netns import die_with_parent
from erni.sim.radio import FD_ENV
from erni.sim.team_configs import AgentProcess, private_file, stop_processes

log = logging.getLogger("erni.sim.agent_hosts")

JOIN_FILE = "join.json"  # in a host's bundle: where the world host is, which agents, the secret
MAX_LINE = 65536  # the longest line of the radio feed either side reads (a reach of 240 names is ~3 KB)
BUNDLE_DIRS = ("agents", "logs", "journal", "keys")  # what a bundle holds beside its join file
HANDSHAKE_TIMEOUT = 5.0  # seconds an agent host has to answer the feed's challenge


def broadcast_of(address: str) -> str:
    """The broadcast address of the interface of this host that holds `address` (UsageError if none)."""
    try:
        ipaddress.IPv4Address(address)
    except ValueError:
        raise UsageError(f"--listen {address!r}: expected an IPv4 address of this host") from None
    try:
        out = subprocess.run(["ip", "-j", "-4", "addr", "show"], capture_output=True, text=True, timeout=5,
                             check=True).stdout
    except (OSError, subprocess.SubprocessError) as err:
        raise UsageError(f"--listen {address}: cannot list this host's addresses with `ip` ({err})") from None
    for link in json.loads(out or "[]"):
        for info in link.get("addr_info", []):
            if info.get("local") == address:
                net = ipaddress.IPv4Network(f"{address}/{info.get('prefixlen', 32)}", strict=False)
                return str(info.get("broadcast") or net.broadcast_address)
    raise UsageError(f"--listen {address}: no interface of this host has that address "
                     "(expected the address the agent hosts reach this host at)")


def world_share(robots: int, hosts: int, here: int | None = None) -> int:
    """How many of `robots` agents the world host runs beside `hosts` agent hosts: `here`, else an even share
    (rounded up: this host's first)."""
    return here if here is not None else -(-robots // (1 + hosts))


@dataclass(frozen=True)
class Placement:
    """Which host runs which robot's agent: host 1 is this (the world) host at `world`, host K >= 2
    the agent host at `hosts[K - 2]`; `broadcast` is where every agent beacons."""

    world: str
    hosts: tuple[str, ...]
    share: dict[str, int]
    broadcast: str

    @classmethod
    def plan(cls, names: list[str], world: str, hosts: list[str], here: int | None = None) -> Placement:
        """Deal `names` out in contiguous shares, this host's first: `here` of them on this host (default an
        even share; this host also runs the simulator and the control node), the rest as even as they go."""
        for h in hosts:
            try:
                ipaddress.IPv4Address(h)
            except ValueError:
                raise UsageError(f"--agent-host {h!r}: expected the IPv4 address of an agent host") from None
        if world in hosts or len(set(hosts)) != len(hosts):
            raise UsageError(f"--agent-host: every host once, and not this one ({world}); got {', '.join(hosts)}")
        if len(names) < 1 + len(hosts):
            raise UsageError(f"--agent-host: {len(names)} robot(s) cannot fill {1 + len(hosts)} hosts; "
                             f"expected at least one robot per host")
        here = world_share(len(names), len(hosts), here)
        if not 0 <= here <= len(names) - len(hosts):
            raise UsageError(f"--agents-here {here}: expected 0 to {len(names) - len(hosts)} (of {len(names)} robots, "
                             f"at least one for each agent host)")
        rest = len(names) - here
        share = {name: 1 if i < here else 2 + (i - here) * len(hosts) // rest for i, name in enumerate(names)}
        return cls(world, tuple(hosts), share, broadcast_of(world))

    def address(self, name: str) -> str:
        """The address of the host that runs agent `name` (the control node runs on this host)."""
        k = self.share.get(name, 1)
        return self.world if k == 1 else self.hosts[k - 2]

    def remote(self, name: str) -> bool:
        """True when agent `name` runs on an agent host."""
        return self.share.get(name, 1) != 1

    def names_of(self, k: int) -> list[str]:
        """The robots host `k` runs."""
        return [n for n, h in self.share.items() if h == k]


def bundle_dir(run_dir: Path, k: int) -> Path:
    """Where the bundle of agent host `k` is written."""
    return run_dir / "hosts" / f"host-{k}"


def private_bundle(bundle: Path) -> Path:
    """Make `bundle` and its folders (agents, logs, journal, keys) this user's only (0700, whatever the umask)."""
    for path in (bundle.parent, bundle, *(bundle / sub for sub in BUNDLE_DIRS)):
        path.mkdir(exist_ok=True)
        os.chmod(path, 0o700)
    return bundle


def _mac(secret: str, nonce: str, who: int | str) -> str:
    """The proof that `who` (an agent host's number, or "world") holds `secret`, for challenge `nonce`."""
    return hmac.new(bytes.fromhex(secret), f"{nonce}:{who}".encode(), hashlib.sha256).hexdigest()


def _read_line(f: IO[bytes]) -> Any:
    """One JSON line of the feed (None at its end); ValueError for a line too long or not JSON."""
    line = f.readline(MAX_LINE + 1)
    if not line:
        return None
    if len(line) > MAX_LINE:
        raise NetworkError(f"a line longer than {MAX_LINE} bytes")
    return json.loads(line)


@dataclass
class _Joined:
    """One agent host's feed connection: what is still to be sent to it, and the thread sending it."""

    sock: socket.socket
    pending: dict[str, list[str] | None] = field(default_factory=dict)
    fail: set[str] = field(default_factory=set)  # agents its host is to kill
    wake: threading.Condition = field(default_factory=threading.Condition)
    closed: bool = False


class RadioFeed:
    """The world host's side: serve each agent host the reachability of its agents.

    `tell(name, hears)` never blocks (the simulator's feed loop calls it): the newest value per agent
    waits for the host's writer thread. `current(name)` gives a joining host its agents' reach now."""

    def __init__(self, placement: Placement, current: Callable[[str], list[str] | None]) -> None:
        self.placement = placement
        self.current = current
        self.secrets = {k: secrets.token_hex(32) for k in range(2, 2 + len(placement.hosts))}
        self._sock = socket.create_server((placement.world, 0))
        self.address: tuple[str, int] = self._sock.getsockname()[:2]
        self._joined: dict[int, _Joined] = {}
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._threads: list[threading.Thread] = []  # one per connection: its greeting, then its writer
        self._thread = threading.Thread(target=self._accept, name="sim-radio-feed", daemon=True)
        self._thread.start()

    def joined(self) -> set[int]:
        """The agent hosts connected now."""
        with self._lock:
            return {k for k, j in self._joined.items() if not j.closed}

    def tell(self, name: str, hears: list[str] | None) -> None:
        """Agent `name` (on an agent host) hears `hears` from now on."""
        with self._lock:
            joined = self._joined.get(self.placement.share.get(name, 1))
        if joined is None:
            return  # its host has not joined: it gets the reach of the moment when it does
        with joined.wake:
            joined.pending[name] = hears
            joined.wake.notify()

    def fail(self, name: str) -> None:
        """Have the host of agent `name` kill it (a scenario's failure)."""
        with self._lock:
            joined = self._joined.get(self.placement.share.get(name, 1))
        if joined is None:
            log.warning("radio feed: cannot fail %s: its agent host has not joined", name)
            return
        with joined.wake:
            joined.fail.add(name)
            joined.wake.notify()

    def close(self) -> None:
        """Stop serving: every agent host sees its feed end (and stops its agents)."""
        self._stop.set()
        try:
            self._sock.shutdown(socket.SHUT_RDWR)  # wakes the accept (a close alone does not)
        except OSError:
            pass
        self._sock.close()
        with self._lock:
            joined, self._joined = list(self._joined.values()), {}
        for j in joined:
            with j.wake:
                j.closed = True
                j.wake.notify()
            try:
                j.sock.shutdown(socket.SHUT_RDWR)
            except OSError:
                pass
            j.sock.close()
        self._thread.join(5)
        with self._lock:
            threads = list(self._threads)
        for thread in threads:
            thread.join(HANDSHAKE_TIMEOUT + 1)

    def _accept(self) -> None:
        while not self._stop.is_set():
            try:
                conn, peer = self._sock.accept()
            except OSError:
                return
            thread = threading.Thread(target=self._greet, args=(conn, peer), name="sim-radio-join", daemon=True)
            with self._lock:
                self._threads = [t for t in self._threads if t.is_alive()] + [thread]
            thread.start()

    def _greet(self, conn: socket.socket, peer: tuple[str, int]) -> None:
        """Challenge a connecting host; a host that answers with its bundle's secret is served, once this host
        has answered the host's own challenge (its agents take reach and failures only from their run's world)."""
        nonce = secrets.token_hex(16)
        conn.settimeout(HANDSHAKE_TIMEOUT)
        try:
            conn.sendall((json.dumps({"nonce": nonce}) + "\n").encode())
            with conn.makefile("rb") as f:
                answer = _read_line(f)
            k = answer.get("host") if isinstance(answer, dict) else None
            secret = self.secrets.get(k) if isinstance(k, int) else None
            if not isinstance(k, int) or secret is None \
                    or not hmac.compare_digest(str(answer.get("mac", "")), _mac(secret, nonce, k)):
                conn.sendall(b'{"error": "not an agent host of this run (wrong bundle?)"}\n')
                log.warning("radio feed: %s:%d did not prove it is an agent host of this run", *peer)
                conn.close()
                return
            conn.sendall((json.dumps({"proof": _mac(secret, str(answer.get("nonce", ""))[:64], "world")}) + "\n").encode())
        except (OSError, ValueError, AttributeError) as err:
            log.warning("radio feed: %s:%d: bad greeting (%s)", peer[0], peer[1], err)
            conn.close()
            return
        joined = _Joined(conn)
        with self._lock:
            if self._stop.is_set():  # closed meanwhile: this host sees its feed end at once
                conn.close()
                return
            old = self._joined.get(k)
            self._joined[k] = joined
        if old is not None:  # the host joined again (its launcher restarted): the old link is done
            with old.wake:
                old.closed = True
                old.wake.notify()
        with joined.wake:
            joined.pending.update({name: self.current(name) for name in self.placement.names_of(k)})
        log.info("radio feed: agent host %d joined from %s", k, peer[0])
        self._write(joined)

    def _write(self, joined: _Joined) -> None:
        joined.sock.settimeout(None)
        while True:
            with joined.wake:
                while not joined.pending and not joined.fail and not joined.closed:
                    joined.wake.wait()
                if joined.closed:
                    return
                (batch, joined.pending), (fail, joined.fail) = (joined.pending, {}), (joined.fail, set())
            data = "".join(json.dumps({"agent": n, "hears": h}) + "\n" for n, h in batch.items()) + \
                "".join(json.dumps({"agent": n, "fail": True}) + "\n" for n in sorted(fail))
            try:
                joined.sock.sendall(data.encode())
            except OSError:
                joined.closed = True
                return


def write_join_file(bundle: Path, *, world: tuple[str, int], host: int, secret: str, agents: list[str],
                    log_level: str) -> Path:
    """The join file of agent host `host`'s bundle (private: it holds the secret)."""
    path = private_file(bundle / JOIN_FILE)
    path.write_text(json.dumps({"world": list(world), "host": host, "secret": secret, "agents": agents,
                                "log_level": log_level}, indent=1) + "\n", encoding="utf-8")
    return path


def spawn_behind_radio(agent: AgentProcess, env: dict[str, str], log_level: str,
                       cwd: Path | None = None) -> int:
    """Start `python -m erni.sim.radio CONFIG` for `agent`; return the write end of its radio pipe
    (non-blocking: whoever feeds it never waits on the agent)."""
    read, write = os.pipe()
    os.set_blocking(write, False)
    try:
        with open(agent.log, "ab") as out:
            agent.proc = subprocess.Popen(
                [sys.executable, "-m", "erni.sim.radio", str(agent.config), "--log-level", log_level],
                stdin=subprocess.DEVNULL, stdout=out, stderr=subprocess.STDOUT, cwd=cwd,
                env={**env, FD_ENV: str(read)}, pass_fds=(read,),
                start_new_session=True, umask=0o077,  # its journal: this user's only
                # SIGTERM: an agent still stops cleanly (its journal closed) when the launcher dies
                preexec_fn=die_with_parent(signal.SIGTERM))
    except BaseException:
        os.close(write)
        raise
    finally:
        os.close(read)
    return write


def tell_pipe(agent: AgentProcess, names: list[str] | None) -> None:
    """Push the names `agent` can hear now into its radio pipe (never blocks)."""
    if agent.radio is None:
        return
    try:
        os.write(agent.radio, (json.dumps(names) + "\n").encode())
    except BlockingIOError:
        log.warning("radio pipe of %s is full: it is not reading (stuck?)", agent.name)
    except OSError:  # the agent is gone
        agent.close_radio()


class AgentHost:
    """An agent host's side (`erni sim --join DIR`): run the agents of its bundle behind the radio the
    world host feeds, until that feed ends or `stop()`."""

    def __init__(self, bundle: str | Path) -> None:
        self.dir = Path(bundle).resolve()
        try:
            join = json.loads((self.dir / JOIN_FILE).read_text(encoding="utf-8"))
            self.world = (str(join["world"][0]), int(join["world"][1]))
            self.host, self.secret = int(join["host"]), str(join["secret"])
            bytes.fromhex(self.secret)
            self.names = [str(n) for n in join["agents"]]
            if not self.names:
                raise ConfigError(f"{JOIN_FILE} names no agent")
            self.log_level = str(join.get("log_level", "WARNING"))
        except (OSError, ValueError, KeyError, TypeError, IndexError) as err:
            raise UsageError(f"--join {bundle}: expected the bundle `erni sim --agent-host` wrote "
                             f"(RUN/hosts/host-K with {JOIN_FILE}); {type(err).__name__}: {err}") from None
        self.agents = {n: AgentProcess(n, self.dir / "agents" / f"{n}.toml", self.dir / "logs" / f"{n}.log",
                                       (self.world[0], 0)) for n in self.names}
        missing = [str(a.config) for a in self.agents.values() if not a.config.is_file()]
        if missing:
            raise UsageError(f"--join {bundle}: agent config(s) missing: {', '.join(missing)}")
        self._sock: socket.socket | None = None
        self._stopping = threading.Event()

    def connect(self, timeout: float = 60.0) -> None:
        """Reach the world host's radio feed and prove this host is of the run (UsageError if not)."""
        deadline = time.monotonic() + timeout
        while True:
            try:
                sock = socket.create_connection(self.world, timeout=HANDSHAKE_TIMEOUT)
                break
            except OSError as err:
                if time.monotonic() > deadline or self._stopping.is_set():
                    raise UsageError(f"--join: the world host's radio feed at {self.world[0]}:{self.world[1]} "
                                     f"does not answer ({err}); is its `erni sim` running?") from None
                self._stopping.wait(0.5)
        f = sock.makefile("rb")
        where = f"the radio feed at {self.world[0]}:{self.world[1]}"
        try:
            nonce, mine = str(_read_line(f)["nonce"]), secrets.token_hex(16)
            sock.sendall((json.dumps({"host": self.host, "mac": _mac(self.secret, nonce, self.host), "nonce": mine})
                          + "\n").encode())
            proof = _read_line(f)
            if isinstance(proof, dict) and "error" in proof:
                raise UsageError(f"--join: {where} refused this host: {str(proof['error'])[:200]}")
            if not hmac.compare_digest(str(proof["proof"]), _mac(self.secret, mine, "world")):
                raise UsageError(f"--join: {where} did not prove it is the world host of this bundle's run")
        except (OSError, ValueError, TypeError, KeyError) as err:
            sock.close()
            if isinstance(err, UsageError):
                raise
            raise UsageError(f"--join: {where} did not greet as `erni sim` does ({type(err).__name__}: {err})") from None
        sock.settimeout(None)
        self._sock, self._feed = sock, f

    def start(self) -> None:
        """Start every agent of the bundle, each told at once what the world host said of its radio."""
        for folder in ("logs", "journal"):  # not the bundle's parent: wherever it was copied is the user's
            (self.dir / folder).mkdir(exist_ok=True)
            os.chmod(self.dir / folder, 0o700)
        env = {**os.environ, "PYTHONUNBUFFERED": "1"}
        for agent in self.agents.values():
            private_file(agent.log)
            agent.radio = spawn_behind_radio(agent, env, self.log_level, cwd=self.dir)

    def relay(self) -> str:
        """Hand the feed's lines to the agents until it ends; return why it ended."""
        assert self._sock is not None
        while True:
            try:
                line = _read_line(self._feed)
            except (OSError, ValueError) as err:
                return "stopped" if self._stopping.is_set() else f"the radio feed broke ({err})"
            if self._stopping.is_set():
                return "stopped"
            if line is None:
                return "the world host ended the run"
            if isinstance(line, dict) and "error" in line:
                return f"the world host refused this host: {str(line['error'])[:200]}"
            agent = self.agents.get(str(line.get("agent"))) if isinstance(line, dict) else None
            if agent is not None and line.get("fail") is True:
                agent.kill()
                log.warning("agent %s killed: the scenario fails it", agent.name)
                continue
            hears = line.get("hears") if isinstance(line, dict) else None
            if agent is None or not (hears is None or (isinstance(hears, list)
                                                       and all(isinstance(n, str) for n in hears))):
                log.warning("radio feed: ignored a line that is not an agent's reach: %.80r", line)
                continue
            tell_pipe(agent, hears)

    def alive(self) -> list[str]:
        """The agents still running."""
        return [n for n, a in self.agents.items() if a.alive]

    def stop(self, timeout: float = 8.0) -> None:
        """Stop every agent (SIGTERM, then SIGKILL) and leave the feed."""
        self._stopping.set()
        if self._sock is not None:
            try:
                self._sock.shutdown(socket.SHUT_RDWR)
            except OSError:
                pass
        stop_processes([a.proc for a in self.agents.values() if a.proc is not None], timeout)
        for agent in self.agents.values():
            agent.close_radio()
        if self._sock is not None:
            self._sock.close()
