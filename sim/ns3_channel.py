"""The ns-3 channel of the real-mesh tier (`erni sim --netns --channel ns3`).

One ns-3 process, in real time, carries every node's frames through an 802.11a ad-hoc network:
each node's namespace gets a TAP device `mesh0` (instead of the veth into the bridge that the
nftables radio filters), attached to that node's ns-3 FdNetDevice and bridged by the program to
the node's ns-3 WifiNetDevice. Linux does IP, ARP and routing (babeld) as on the nftables
channel; ns-3 does the medium: propagation loss and fading, the PHY's error model, CSMA/CA
with its backoff, collisions and hidden terminals, retries and Minstrel rate control. The
robots' positions are written to the program's standard input as they drive.

The program is ERNI's own C++ (`erni/sim/ns3/channel.cc`, its header says the model), compiled
on first use against Debian's libns3-dev (ns-3 3.37) into `$XDG_CACHE_HOME/erni/ns3-channel/`
(`~/.cache/...` by default), once per source and ns-3 version. Nothing here runs at import.

Real time: ns-3's RealtimeSimulatorImpl in best-effort mode (events that come due while the
simulator is busy run late, never skipped). A probe event every 100 ms measures how far the
simulator is behind the wall clock; the program prints it once a second and `Ns3Channel.lag`
keeps it, and a lag beyond LAG_WARN_MS is logged as a warning with its figure.
"""

from __future__ import annotations

import contextlib
import fcntl
import hashlib
import logging
import os
import shutil
import subprocess
import threading
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path

from erni.blackboard.errors import ErniError

log = logging.getLogger("erni.sim.ns3_channel")

SOURCE = Path(__file__).with_name("ns3") / "channel.cc"
MODULES = ("ns3-core", "ns3-network", "ns3-wifi", "ns3-mobility", "ns3-fd-net-device", "ns3-propagation",
           "ns3-internet", "ns3-applications")
INSTALL = "--channel ns3 needs ns-3: apt install libns3-dev g++ pkg-config"
LAG_WARN_MS = 50.0      # a probe this late counts as late, and a report beyond it is logged
MAX_NODES = 24
"""The most nodes (robots and the control node) one ns-3 channel carries in real time here.

Measured on this 2-core machine with bench/bench_ns3_channel.py's real-time steps (every node in
range of every other, broadcasting a team's traffic: 40 datagrams of 700 bytes a second): up to
24 nodes the simulator's largest lag stayed under 5 ms in two runs out of three (290 ms in the
third, beside a second run on the machine); 32 nodes lagged 13 ms in one run and 419 ms in
another, 40 nodes over 400 ms in every run. A scenario asking for more is refused; under other load
the lag warning reports what happens below the limit."""


EDGE_RATIO = 1.44
"""How much farther than its reach (the distance where a frame arrives at ns-3's preamble-detection
threshold, -82 dBm, on average) the channel still delivers 10 % of unicast datagrams: the radio
model's default `min_quality`, the weakest link it counts. Measured in pure ns-3 runs (3 seeds, 500
datagrams of 500 bytes at 100/s per distance): at 1.44 times the reach 11 % arrive, at 1.3 times 29
%, at 1.0 times 94 %, at 1.7 times under 1 %; the ratio holds at any reach (the loss depends on
distance over reach alone)."""


def reach(comm_range: float) -> float:
    """The ns-3 channel's reach (the program's `--range-m`) for a scenario's `comm_range`: set so that
    ns-3 delivers about 10 % of unicast datagrams at `comm_range`, as little as the radio model still
    counts as a link; with the default 10 m / 6 m radio, about 30 % at 9 m (the model's 0.3 at 8.8 m)
    and 95 % at 6.9 m, so a scenario's geometry means the same on both channels."""
    return comm_range / EDGE_RATIO


class Ns3Error(ErniError):
    """The ns-3 channel could not be built, started or driven."""


class Ns3Unavailable(Ns3Error):
    """ns-3 (Debian's libns3-dev), g++ or pkg-config is missing."""


def unavailable_reason() -> str | None:
    """Why the ns-3 channel cannot be built here (one line naming the packages), or None."""
    missing = [tool for tool in ("g++", "pkg-config") if shutil.which(tool) is None]
    if missing:
        return f"{INSTALL} ({', '.join(missing)} not found)"
    done = subprocess.run(["pkg-config", "--exists", *MODULES], capture_output=True)
    if done.returncode != 0:
        return f"{INSTALL} (pkg-config finds no ns-3 modules)"
    return None


def check_channel(nodes: int) -> None:
    """Raise Ns3Unavailable when ns-3 is missing, Ns3Error when `nodes` are more than keep real time."""
    reason = unavailable_reason()
    if reason:
        raise Ns3Unavailable(reason)
    if nodes > MAX_NODES:
        raise Ns3Error(f"--channel ns3: {nodes} nodes (robots and the control node) asked, but one ns-3 "
                       f"channel keeps real time on this machine with at most {MAX_NODES}")


def cache_dir() -> Path:
    """Where compiled channel programs are kept."""
    base = os.environ.get("XDG_CACHE_HOME") or str(Path.home() / ".cache")
    return Path(base) / "erni" / "ns3-channel"


def _ns3_version() -> str:
    done = subprocess.run(["pkg-config", "--modversion", "ns3-core"], capture_output=True, text=True)
    return done.stdout.strip()


def binary() -> Path:
    """The compiled channel program: built now (about 20 s) unless this source and ns-3 have one."""
    reason = unavailable_reason()
    if reason:
        raise Ns3Unavailable(reason)
    source = SOURCE.read_bytes()
    key = hashlib.sha256(source + _ns3_version().encode()).hexdigest()[:16]
    out = cache_dir() / key / "erni-ns3-channel"
    if out.exists():
        return out
    out.parent.mkdir(parents=True, exist_ok=True)
    with open(out.parent / ".lock", "w") as lock:  # two runs starting at once build it once
        fcntl.flock(lock, fcntl.LOCK_EX)
        if out.exists():
            return out
        cflags = subprocess.run(["pkg-config", "--cflags", *MODULES], capture_output=True, text=True).stdout.split()
        # Debian's .pc files name a stray "-I/usr;" and static libraries of libgsl-dev: only the
        # include paths are taken from them, and the ns-3 libraries are named here
        cflags = [f for f in cflags if f.startswith("-I") and ";" not in f and os.path.isdir(f[2:])]
        libs = [f"-l{m}" for m in ("ns3-wifi", "ns3-fd-net-device", "ns3-mobility", "ns3-internet",
                                  "ns3-applications", "ns3-network", "ns3-propagation", "ns3-core")]
        tmp = out.with_suffix(f".{os.getpid()}.tmp")
        log.warning("building the ns-3 channel program (once, about 20 s): %s", out)
        done = subprocess.run(["g++", "-O2", "-std=c++17", "-o", str(tmp), str(SOURCE), *cflags, *libs],
                              capture_output=True, text=True)
        if done.returncode != 0:
            errors = [line for line in done.stderr.splitlines() if "error" in line][:3]
            raise Ns3Unavailable(f"{INSTALL} (building {SOURCE.name} failed: {' | '.join(errors)[:300]})")
        os.replace(tmp, out)
    return out


@dataclass
class Lag:
    """How far the real-time simulator is behind the wall clock (from the program's reports)."""

    sim_time: float = 0.0     # simulated seconds at the last report
    now_ms: float = 0.0       # lag at the last report
    max_ms: float = 0.0       # the largest lag seen
    late: int = 0             # probes later than LAG_WARN_MS
    probes: int = 0           # probes in all (10 a second)


@dataclass
class MacDrops:
    """Frames the kernels handed to the ns-3 wifi devices, and those the MACs dropped (all nodes)."""

    sent: int = 0
    queue_full: int = 0
    expired: int = 0          # waited longer than the MAC queue's lifetime (ns-3's 500 ms)
    retry_limit: int = 0      # unicast frames not acknowledged after every retry


@dataclass
class ChannelNode:
    """One node of the ns-3 channel: its name, namespace and first position."""

    name: str
    netns: str
    x: float = 0.0
    y: float = 0.0


@dataclass
class Ns3Channel:
    """The running channel program: start it, move its nodes, read its lag, stop it."""

    nodes: Sequence[ChannelNode]
    range_m: float
    log_path: Path
    seed: int = 1
    run: int = 1
    lag: Lag = field(default_factory=Lag)
    mac: MacDrops = field(default_factory=MacDrops)
    proc: subprocess.Popen[str] | None = None
    _lock: threading.Lock = field(default_factory=threading.Lock)
    _warned_at: float = 0.0
    _reported_exit: bool = False

    def argv(self, program: Path) -> list[str]:
        """The program's command line."""
        argv = [str(program), "emulate", "--range-m", f"{self.range_m:g}", "--seed", str(self.seed),
                "--run", str(self.run), "--late-ms", f"{LAG_WARN_MS:g}"]
        for n in self.nodes:
            argv += ["--node", n.name, n.netns, f"{n.x:.3f}", f"{n.y:.3f}"]
        return argv

    def start(self, wrap: Sequence[str] = (), preexec_fn: Callable[[], None] | None = None,
              timeout: float = 20.0) -> None:
        """Start the program (inside `wrap`, e.g. `ip netns exec HUB`) and wait until its TAPs exist."""
        check_channel(len(self.nodes))
        program = binary()
        errors = open(self.log_path, "a")
        try:
            self.proc = subprocess.Popen([*wrap, *self.argv(program)], stdin=subprocess.PIPE,
                                         stdout=subprocess.PIPE, stderr=errors, text=True, bufsize=1,
                                         start_new_session=True, preexec_fn=preexec_fn)
        finally:
            errors.close()
        assert self.proc.stdout is not None
        ready = threading.Event()
        threading.Thread(target=self._read, args=(ready,), name="ns3-channel", daemon=True).start()
        deadline = time.monotonic() + timeout
        while not ready.wait(0.1):
            if self.proc.poll() is not None or time.monotonic() > deadline:
                why = self._log_tail() or f"exit code {self.proc.poll()}"
                self.stop()
                raise Ns3Error(f"the ns-3 channel did not start: {why}")

    def _log_tail(self) -> str:
        with contextlib.suppress(OSError):
            lines = [line for line in self.log_path.read_text().splitlines() if line.strip()]
            return lines[-1][:300] if lines else ""
        return ""

    def _read(self, ready: threading.Event) -> None:
        assert self.proc is not None and self.proc.stdout is not None
        for line in self.proc.stdout:
            words = line.split()
            if not words:
                continue
            if words[0] == "ready":
                ready.set()
            elif words[0] == "mac" and len(words) == 5:
                self.mac = MacDrops(*(int(w) for w in words[1:]))
            elif words[0] == "lag" and len(words) == 6:
                lag = Lag(float(words[1]), float(words[2]), float(words[3]), int(words[4]), int(words[5]))
                self.lag = lag
                if lag.now_ms > LAG_WARN_MS and time.monotonic() - self._warned_at > 10.0:
                    self._warned_at = time.monotonic()
                    log.warning("the ns-3 channel is %.0f ms behind real time (at most %.0f ms; %d of %d "
                                "probes late): its frames arrive late", lag.now_ms, lag.max_ms, lag.late,
                                lag.probes)

    @property
    def alive(self) -> bool:
        """True while the program runs."""
        return self.proc is not None and self.proc.poll() is None

    def move(self, positions: Mapping[str, tuple[float, float]]) -> None:
        """Move nodes of the channel (metres); names it does not know are left out. A channel that
        exited is logged once, as an error: the namespaces then have no medium at all."""
        if self.proc is not None and self.proc.poll() is not None and not self._reported_exit:
            self._reported_exit = True
            log.error("the ns-3 channel exited (code %s): no frame crosses between the namespaces; "
                      "its log: %s (%s)", self.proc.returncode, self.log_path, self._log_tail() or "empty")
        known = {n.name for n in self.nodes}
        text = "".join(f"pos {name} {x:.3f} {y:.3f}\n" for name, (x, y) in positions.items() if name in known)
        if not text or self.proc is None or self.proc.stdin is None:
            return
        with self._lock:
            try:
                self.proc.stdin.write(text)
                self.proc.stdin.flush()
            except (OSError, ValueError):  # the program is gone: stop() reports nothing more
                pass

    def stop(self, timeout: float = 5.0) -> None:
        """Ask the program to stop (end of input), then kill it if it does not."""
        proc, self.proc = self.proc, None
        if proc is None:
            return
        with contextlib.suppress(OSError, ValueError):
            if proc.stdin is not None:
                proc.stdin.write("quit\n")
                proc.stdin.close()
        try:
            proc.wait(timeout)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait(5)
        with contextlib.suppress(OSError, ValueError):
            if proc.stdout is not None:
                proc.stdout.close()


def pure_run(program: Path, distance: float, packets: int, interval: float, size: int, *,
             range_m: float, seed: int = 1, run: int = 1) -> tuple[int, int]:
    """The same channel in a pure ns-3 run (simulated time, ns-3's UDP): (sent, received)."""
    done = subprocess.run([str(program), "pure", "--distance", f"{distance:g}", "--packets", str(packets),
                           "--interval", f"{interval:g}", "--size", str(size), "--range-m", f"{range_m:g}",
                           "--seed", str(seed), "--run", str(run)], capture_output=True, text=True, timeout=300)
    words = done.stdout.split()
    if done.returncode != 0 or len(words) != 3 or words[0] != "pure":
        raise Ns3Error(f"pure ns-3 run failed: {(done.stderr or done.stdout).strip()[:300]}")
    return int(words[1]), int(words[2])
