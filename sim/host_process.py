"""HostProcess: a team's simulated robots (a `RobotHost`) in a process of their own.

On a real team each robot's firmware runs on hardware of its own. In `erni sim` the robot host
shares the machine with every agent, and in the simulator's process it also shared one
interpreter with the SNMP nodes, the radio feed and the team's client: its physics steps, and
so its SIPs, came late whenever one of those held the interpreter. Here it runs as
`python -m erni.sim.host_process STATE`, and the simulator's process sees the robots through:

* STATE, a file both map: a sequence number, the host's `TIMING` counters, then per robot
  `FIELDS` (float64), rewritten after every physics step. The sequence number is odd while a
  step writes, so a reader retries rather than take half a step (a seqlock);
* the child's stdin: first the spec (one JSON line: world, robot configs, physics rate, address),
  then one command a line (`["teleport", i, x, y, th]`, `["cut", i]`); its end stops the child;
* the child's stdout: one JSON line once every robot listens (`{"urls": [...], "starts": [...]}`,
  or `{"error": "..."}`).

The child dies with its parent (SIGTERM when the simulator goes, however it goes).
"""

from __future__ import annotations

import json
import logging
import mmap
import signal
import subprocess
import sys
import threading
from pathlib import Path
from typing import IO, Any

import numpy as np

from erni.blackboard.errors import NetworkError, UsageError
from erni.sim.robot import SimRobotConfig
from erni.sim.world import World

log = logging.getLogger("erni.sim.robot")

FIELDS = ("x", "y", "th", "v", "commanded_v", "energy", "connected")
X, Y, TH, V, COMMANDED_V, ENERGY, CONNECTED = range(len(FIELDS))
TIMING = ("steps", "sips", "skipped")
"""The host's counters since it started: physics steps, SIPs sent, and SIP slots skipped because
a step came too late for them (a machine too busy for the team: each is a Pose its robot lacks)."""
HEADER = 1 + len(TIMING)  # the sequence number, then TIMING
START_TIMEOUT = 60.0  # s for the child to listen for every robot


class RobotView:
    """A simulated robot as the simulator's process sees it: its state after the host's last step."""

    def __init__(self, host: HostProcess, index: int, config: SimRobotConfig,
                 start: tuple[float, float, float]) -> None:
        self._host = host
        self.index = index
        self.config = config
        self.name = config.name
        self.start = start  # the pose it started in (m, m, rad)

    def _get(self, field: int) -> float:
        return float(self._host.snapshot()[self.index, field])

    @property
    def x(self) -> float:
        """East (m)."""
        return self._get(X)

    @property
    def y(self) -> float:
        """North (m)."""
        return self._get(Y)

    @property
    def th(self) -> float:
        """Heading (rad)."""
        return self._get(TH)

    @property
    def v(self) -> float:
        """Translational velocity (m/s)."""
        return self._get(V)

    @property
    def commanded_v(self) -> float:
        """The velocity the robot was told to reach (m/s; its velocity when driven otherwise)."""
        return self._get(COMMANDED_V)

    @property
    def energy(self) -> float:
        """Energy drawn since the start (J)."""
        return self._get(ENERGY)

    def __repr__(self) -> str:
        return f"RobotView({self.name!r}, x={self.x:.2f}, y={self.y:.2f})"


class HostProcess:
    """The simulated robots of a team, served by a `RobotHost` in a child process.

    Add robots, then `start()`; `robots` are `RobotView`s of their state, `url(i)` the address
    a driver opens, `teleport()` and `cut()` the simulator's hand. `host` is the address the
    robots listen on (set it before `start()`).
    """

    def __init__(self, world: World, *, physics_hz: float, host: str = "127.0.0.1") -> None:
        if physics_hz <= 0:
            raise UsageError(f"physics_hz must be > 0, got {physics_hz}")
        self.world = world
        self.physics_hz = physics_hz
        self.host = host
        self.configs: list[SimRobotConfig] = []
        self.robots: list[RobotView] = []
        self.urls: list[str] = []
        self._proc: subprocess.Popen[bytes] | None = None
        self._state: Path | None = None
        self._map: mmap.mmap | None = None
        self._table: np.ndarray | None = None  # the shared file as float64: HEADER, then FIELDS per robot
        self._send_lock = threading.Lock()

    def add_robot(self, config: SimRobotConfig) -> None:
        """Add a robot (before `start()`); it listens on a free TCP port."""
        if self._proc is not None:
            raise UsageError("add robots before start(): the robot host is already running")
        self.configs.append(config)

    def start(self, state: str | Path, log_path: str | Path) -> HostProcess:
        """Start the child, mapping `state`, its output in `log_path`; return once every robot listens."""
        from erni.sim.netns import die_with_parent

        n = len(self.configs)
        self._state = Path(state)
        self._state.write_bytes(bytes(8 * (HEADER + n * len(FIELDS))))
        with open(log_path, "ab") as err:
            self._proc = subprocess.Popen([sys.executable, "-m", "erni.sim.host_process", str(self._state)],
                                          stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=err,
                                          start_new_session=True, preexec_fn=die_with_parent(signal.SIGTERM))
        spec = {"world": self.world.model_dump(mode="json"), "physics_hz": self.physics_hz, "host": self.host,
                "robots": [c.model_dump(mode="json") for c in self.configs]}
        self._command(spec)
        answer = self._answer(log_path)
        with open(self._state, "r+b") as f:
            self._map = mmap.mmap(f.fileno(), 0)
        self._table = np.frombuffer(self._map, dtype=np.float64)
        self.urls = list(answer["urls"])
        self.robots = [RobotView(self, i, c, tuple(answer["starts"][i])) for i, c in enumerate(self.configs)]
        return self

    def _answer(self, log_path: str | Path) -> dict[str, Any]:
        assert self._proc is not None and self._proc.stdout is not None
        out = self._proc.stdout
        line: list[bytes] = []
        reader = threading.Thread(target=lambda: line.append(out.readline()), daemon=True)
        reader.start()
        reader.join(START_TIMEOUT)
        try:
            answer = json.loads(line[0]) if line and line[0] else {}
        except ValueError:
            answer = {}
        if "urls" in answer:
            return answer
        self.stop()
        why = answer.get("error") or f"no answer within {START_TIMEOUT:.0f} s (its log: {log_path})"
        raise NetworkError(0, f"the robot host did not start: {why}")

    def _command(self, message: Any) -> None:
        proc = self._proc
        if proc is None or proc.stdin is None:
            raise UsageError("the robot host is not running")
        with self._send_lock:
            try:
                proc.stdin.write((json.dumps(message) + "\n").encode())
                proc.stdin.flush()
            except (BrokenPipeError, ValueError):
                raise NetworkError(0, f"the robot host is gone (exit {proc.poll()})") from None

    @property
    def pid(self) -> int | None:
        """The robot host's process id while it runs."""
        return self._proc.pid if self._proc is not None else None

    def snapshot(self) -> np.ndarray:
        """Every robot's `FIELDS` after one whole physics step (a copy)."""
        return self._read()[HEADER:].reshape(-1, len(FIELDS))

    def timing(self) -> dict[str, int]:
        """The host's `TIMING` counters as of its last physics step."""
        head = self._read()
        return {name: int(head[1 + k]) for k, name in enumerate(TIMING)}

    def _read(self) -> np.ndarray:
        """The whole shared table as one physics step left it (a copy; the seqlock's read side)."""
        table = self._table
        if table is None:
            raise UsageError("the robot host is not running")
        for _ in range(1000):
            before = table[0]
            copy = table.copy()
            if before == table[0] and not int(before) % 2:
                break
        return copy

    def url(self, index: int) -> str:
        """The pyserial URL a driver opens to reach robot `index`."""
        return self.urls[index]

    def connected(self) -> list[bool]:
        """Per robot, whether a client holds its link (as of the last physics step)."""
        return [bool(c) for c in self.snapshot()[:, CONNECTED]]

    def teleport(self, index: int, x: float, y: float, th: float) -> None:
        """Put robot `index` at (x, y) facing th (rad): the simulator's hand."""
        self._command(["teleport", index, x, y, th])

    def cut(self, index: int) -> None:
        """Pull robot `index`'s cable: the host drops its client's connection."""
        self._command(["cut", index])

    def stop(self, timeout: float = 5.0) -> None:
        """End the child (its stdin closed, then SIGKILL) and unmap the state."""
        proc, self._proc = self._proc, None
        if proc is not None:
            for pipe in (proc.stdin, proc.stdout):
                if pipe is not None:
                    try:
                        pipe.close()
                    except OSError:
                        pass
            try:
                proc.wait(timeout)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait(5)
        self._table = None
        if self._map is not None:
            self._map.close()
            self._map = None
        if self._state is not None:
            self._state.unlink(missing_ok=True)


# --- the child ---------------------------------------------------------------------------------


def _serve(state: str, spec: dict[str, Any], commands: IO[str], out: IO[str]) -> None:
    from erni.sim.robot_host import RobotHost

    world = World.model_validate(spec["world"])
    host = RobotHost(world, physics_hz=float(spec["physics_hz"]), host=str(spec["host"]))
    for cfg in spec["robots"]:
        host.add_robot(SimRobotConfig.model_validate(cfg), port=0)
    n = len(host.endpoints)
    with open(state, "r+b") as f:
        shared = mmap.mmap(f.fileno(), 0)
    table = np.frombuffer(shared, dtype=np.float64)
    seq, rows = table[:HEADER], table[HEADER:].reshape(n, len(FIELDS))
    steps = 0

    def publish() -> None:  # after each physics step, in the host's thread (its lock held)
        nonlocal steps
        seq[0] += 1
        sips = skipped = 0
        for i, ep in enumerate(host.endpoints):
            r = ep.robot
            rows[i] = (r.x, r.y, r.th, r.v, r.target_v if r.trans_mode == "vel" else r.v, r.energy,
                       ep.conn is not None)
            sips += ep.firmware.counts["sips"]
            skipped += ep.firmware.counts["skipped"]
        seq[1:] = (steps, sips, skipped)
        steps += 1
        seq[0] += 1

    with host._lock:
        publish()
    host.on_step = publish
    host.start()
    out.write(json.dumps({"urls": [host.url(i) for i in range(n)],
                          "starts": [list(ep.robot.start) for ep in host.endpoints]}) + "\n")
    out.flush()
    try:
        for line in commands:
            try:
                op, index, *args = json.loads(line)
                ep = host.endpoints[int(index)]
            except (ValueError, TypeError, IndexError) as err:
                log.warning("robot host: bad command %r ignored: %s", line.strip()[:80], err)
                continue
            with host._lock:
                if op == "teleport":
                    ep.robot.set_pose(float(args[0]), float(args[1]), float(args[2]))
                elif op == "cut" and ep.conn is not None:
                    ep.conn.shutdown(2)  # SHUT_RDWR: the host sees the end at its next read
                else:
                    log.warning("robot host: command %r ignored: expected teleport or cut", op)
    finally:
        host.stop()


def main(argv: list[str] | None = None) -> int:
    """`python -m erni.sim.host_process STATE`: serve the robots the spec on stdin names."""
    args = sys.argv[1:] if argv is None else argv
    logging.basicConfig(level=logging.WARNING, format="%(asctime)s %(levelname)-7s %(name)s: %(message)s",
                        datefmt="%H:%M:%S")
    try:
        spec = json.loads(sys.stdin.readline())
        _serve(args[0], spec, sys.stdin, sys.stdout)
    except Exception as err:  # the parent reads this line; a traceback goes to the log
        log.exception("robot host failed")
        print(json.dumps({"error": f"{type(err).__name__}: {str(err).splitlines()[0] if str(err) else ''}"}),
              flush=True)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
