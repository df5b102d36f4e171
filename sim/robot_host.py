"""RobotHost: simulated ARCOS robots served over TCP (8101, 8102, ...) or ptys from one thread.

Robot i listens on its own TCP port, as MobileSim and AMRISim do, or on a pty that any
serial client opens like `/dev/ttyUSB0`. One thread (`robot-sim`) owns every socket and pty,
and steps the physics of all robots at `physics_hz` from an injectable clock; without the
thread, `run_once()` and `advance()` let a test drive time itself.
"""

from __future__ import annotations

import errno
import logging
import math
import os
import selectors
import socket
import threading
import time
import tty
from collections.abc import Callable
from dataclasses import dataclass, field

from erni.blackboard.errors import NetworkError, UsageError
from erni.sim.robot import ArcosFirmware, SimRobot, SimRobotConfig, next_on_grid
from erni.sim.swarm import Swarm
from erni.sim.world import World

log = logging.getLogger("erni.sim.robot")

@dataclass
class _Endpoint:
    robot: SimRobot
    firmware: ArcosFirmware
    listener: socket.socket | None = None
    conn: socket.socket | None = None
    master: int | None = None
    slave: int | None = None
    url: str = ""
    pending: bytearray = field(default_factory=bytearray)


class RobotHost:
    """Serves simulated robots over TCP (one port each) or ptys from one I/O and physics thread.

    The physics and the sonar of all robots are computed together (`erni.sim.swarm`);
    `vectorised=False` steps them robot by robot instead (the reference the batch is checked against).
    """

    def __init__(self, world: World | None = None, *, physics_hz: float = 100.0,
                 clock: Callable[[], float] = time.monotonic, host: str = "127.0.0.1",
                 vectorised: bool = True) -> None:
        if physics_hz <= 0:
            raise UsageError(f"physics_hz must be > 0, got {physics_hz}")
        self.world = world or World()
        self.clock = clock
        self.host = host
        self.period = 1.0 / physics_hz
        self.vectorised = vectorised  # False: robot by robot (`SimRobot.step`, `ArcosFirmware.tick`)
        self._swarm: Swarm | None = None
        self.endpoints: list[_Endpoint] = []
        self._sel = selectors.DefaultSelector()
        self._wake_r, self._wake_w = socket.socketpair()
        self._wake_r.setblocking(False)
        self._sel.register(self._wake_r, selectors.EVENT_READ, ("wake", None))
        self._thread: threading.Thread | None = None
        self._stopping = threading.Event()
        self._lock = threading.Lock()
        self._last = clock()
        self._next = self._last + self.period
        self._closed = False
        self.on_step: Callable[[], None] | None = None  # called after each physics step, the lock held

    @property
    def robots(self) -> list[SimRobot]:
        """The hosted robots, in the order they were added."""
        return [e.robot for e in self.endpoints]

    def add_robot(self, config: SimRobotConfig | None = None, *, port: int | None = 0,
                  pty: bool = False) -> SimRobot:
        """Add a robot on TCP `port` (0 = any free port) or, with pty=True, on a new pty."""
        if self._thread is not None:
            raise UsageError("add robots before start(): the host thread owns the selector")
        index = len(self.endpoints)
        config = config or SimRobotConfig(name=f"sim{index + 1}")
        start = self.world.start_pose(index, config.name)
        robot = SimRobot(config, self.world, start.x, start.y, math.radians(start.heading))
        robot.start = (robot.x, robot.y, robot.th)
        robot.others = self._others_of(robot)
        ep = _Endpoint(robot, ArcosFirmware(robot))
        if pty:
            ep.master, ep.slave = os.openpty()
            tty.setraw(ep.slave)
            os.set_blocking(ep.master, False)
            ep.url = os.ttyname(ep.slave)
            self._sel.register(ep.master, selectors.EVENT_READ, ("pty", ep))
        elif port is not None:
            lst = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
            lst.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
            try:
                lst.bind((self.host, port))
            except OSError as err:
                lst.close()
                raise NetworkError(err.errno, f"cannot listen on {self.host}:{port} for robot "
                                         f"{config.name!r}: {err.strerror}") from None
            lst.listen(2)
            lst.setblocking(False)
            ep.listener = lst
            ep.url = f"socket://{self.host}:{lst.getsockname()[1]}"
            self._sel.register(lst, selectors.EVENT_READ, ("listen", ep))
        else:
            raise UsageError("a robot needs a TCP port (0 for any) or pty=True")
        ep.firmware.label = f"{config.name} ({ep.url})"
        self.endpoints.append(ep)
        log.debug("robot %s (%s %s) serves %s", config.name, config.robot_class, config.subclass, ep.url)
        return robot

    def _others_of(self, robot: SimRobot) -> Callable[[], list[tuple[tuple[float, float], float]]]:
        """What `robot` can bump into or sense besides the world: the other robots (centre, radius)."""
        return lambda: [((o.x, o.y), o.config.radius) for o in self.robots if o is not robot]

    def url(self, index: int = 0) -> str:
        """Return the pyserial URL (or pty path) a driver opens to reach robot `index`."""
        return self.endpoints[index].url

    def firmware(self, index: int = 0) -> ArcosFirmware:
        """Return robot `index`'s protocol endpoint."""
        return self.endpoints[index].firmware

    # --- running ------------------------------------------------------------------------

    def start(self) -> RobotHost:
        """Serve the robots from a thread named `robot-sim`; returns self."""
        if self._thread is None:
            self._last = self.clock()
            self._next = self._last + self.period
            self._thread = threading.Thread(target=self._run, name="robot-sim", daemon=True)
            self._thread.start()
        return self

    def stop(self) -> None:
        """Stop the thread (joined) and close every socket and pty."""
        self._stopping.set()
        try:
            self._wake_w.send(b"x")
        except OSError:
            pass
        if self._thread is not None:
            self._thread.join(timeout=5)
            self._thread = None
        self._close_all()

    def __enter__(self) -> RobotHost:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()

    def _run(self) -> None:
        while not self._stopping.is_set():
            try:
                self.run_once(max(0.0, self._next - self.clock()))
            except Exception:  # one bad client must not kill every robot
                log.exception("robot simulator loop error")

    def run_once(self, timeout: float = 0.0) -> None:
        """Serve pending I/O (waiting at most `timeout`), step physics if due, flush output."""
        with self._lock:
            for key, _ in self._sel.select(timeout):
                kind, ep = key.data
                if kind == "wake":
                    try:
                        self._wake_r.recv(64)
                    except OSError:
                        pass
                elif kind == "listen":
                    self._accept(ep)
                elif kind == "conn":
                    self._read_conn(ep)
                elif kind == "pty":
                    self._read_pty(ep)
            now = self.clock()
            if now >= self._next:
                self.advance(now - self._last, now, grid=self._next)
                self._last = now
                if self.on_step is not None:
                    self.on_step()
                # the next step on the grid, skipping those a stall missed: the grid keeps its
                # phase, so every robot's SIPs stay on the ticks they started on
                self._next = next_on_grid(self._next, now, self.period)
            self._flush()

    def advance(self, dt: float, now: float | None = None, grid: float | None = None) -> None:
        """Step every robot's physics by dt, fire the sonar due and let each firmware emit its due SIPs
        (`grid`: this step's time on the host's grid, `now` or earlier when the step comes late)."""
        now = self.clock() if now is None else now
        if self.vectorised:
            if self._swarm is None or self._swarm.world is not self.world:
                self._swarm = Swarm(self.world)
            self._swarm.step(self.robots, dt, now)
            self._swarm.fire([ep.firmware for ep in self.endpoints], now)
            for ep in self.endpoints:
                ep.firmware.tick(now, fire=False, slack=self.period / 2, grid=grid)
            return
        for ep in self.endpoints:
            ep.robot.step(dt, now)
            ep.firmware.tick(now, slack=self.period / 2, grid=grid)

    def _accept(self, ep: _Endpoint) -> None:
        assert ep.listener is not None
        try:
            conn, peer = ep.listener.accept()
        except OSError:
            return
        log.debug("%s: client %s:%d connected", ep.firmware.label, *peer[:2])
        if ep.conn is not None:
            log.debug("%s: the previous client is dropped for the new one", ep.firmware.label)
            self._drop(ep)
        conn.setblocking(False)
        conn.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        ep.conn = conn
        ep.firmware.close()
        self._sel.register(conn, selectors.EVENT_READ, ("conn", ep))

    def _drop(self, ep: _Endpoint) -> None:
        if ep.conn is not None:
            log.debug("%s: client disconnected (%d packets, %d bad, %d unknown commands, %d SIPs sent)",
                      ep.firmware.label, *(ep.firmware.counts[k] for k in ("packets", "bad", "unknown", "sips")))
            self._sel.unregister(ep.conn)
            ep.conn.close()
            ep.conn = None
        ep.pending.clear()
        ep.firmware.close()

    def _read_conn(self, ep: _Endpoint) -> None:
        assert ep.conn is not None
        try:
            data = ep.conn.recv(4096)
        except (BlockingIOError, InterruptedError):
            return
        except OSError:
            data = b""
        if not data:
            self._drop(ep)
            return
        ep.firmware.receive(data, self.clock())

    def _read_pty(self, ep: _Endpoint) -> None:
        assert ep.master is not None
        try:
            data = os.read(ep.master, 4096)
        except (BlockingIOError, InterruptedError):
            return
        except OSError as err:
            if err.errno != errno.EIO:
                raise
            return
        ep.firmware.receive(data, self.clock())

    def _flush(self) -> None:
        for ep in self.endpoints:
            out = ep.firmware.take_output()
            if ep.master is not None:
                if out:
                    try:
                        os.write(ep.master, out)
                    except (BlockingIOError, InterruptedError):
                        pass  # nobody reads the line: bytes are lost, as on a serial cable
                    except OSError:
                        pass
                continue
            if ep.conn is None:
                continue
            ep.pending += out
            if len(ep.pending) > 262144:
                del ep.pending[:-65536]  # a client that stopped reading loses old SIPs
            if ep.pending:
                try:
                    sent = ep.conn.send(ep.pending)
                    del ep.pending[:sent]
                except (BlockingIOError, InterruptedError):
                    pass
                except OSError:
                    self._drop(ep)

    def _close_all(self) -> None:
        if self._closed:
            return
        self._closed = True
        for ep in self.endpoints:
            if ep.conn is not None:
                ep.conn.close()
            if ep.listener is not None:
                ep.listener.close()
            for fd in (ep.master, ep.slave):
                if fd is not None:
                    try:
                        os.close(fd)
                    except OSError:
                        pass
        self._sel.close()
        self._wake_r.close()
        self._wake_w.close()
