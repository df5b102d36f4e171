"""The ARCOS robot driver: any pyserial URL, handshake, reader thread, watchdog pulse, reconnects.

`ArcosDriver(url, model)` opens `/dev/ttyUSB0`, `socket://host:8101` (MobileSim, AMRISim, the
built-in simulator) or any other pyserial URL. One thread, `arcos-<name>`, owns the port: it
connects (SYNC0/1/2 with retries, OPEN, ENABLE), turns bytes into packets and SIPs into
`RobotState` (SI units, 15-bit positions unwrapped), sends PULSE when the link is idle, and
reconnects when the link drops. Commands may be sent from any thread.
"""

from __future__ import annotations

import logging
import math
import pkgutil
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from importlib.metadata import entry_points

import serial

from erni.blackboard.errors import NetworkError
from erni.plugins.motion import arcos
from erni.plugins.motion.arcos import Cmd
from erni.plugins.motion.robots import RobotModel

log = logging.getLogger("erni.motion.driver")


URL_HANDLERS = "erni.serial_handlers"
"""Entry point group: NAME = package of pyserial handlers for the URL scheme NAME:// (the simulator
declares `simrobot`); the driver adds each package to pyserial's search list before it opens a URL."""


def register_url_handlers() -> list[str]:
    """Add the URL handler packages installed distributions declare to pyserial; return the schemes."""
    schemes = []
    for ep in entry_points(group=URL_HANDLERS):
        schemes.append(ep.name)
        if ep.value not in serial.protocol_handler_packages:
            serial.protocol_handler_packages.append(ep.value)
    return schemes


def known_url_schemes() -> list[str]:
    """The URL schemes a driver can open: pyserial's own (socket://, rfc2217://, loop:// ...) and
    those registered through the `erni.serial_handlers` entry points."""
    import serial.urlhandler

    builtin = [m.name.removeprefix("protocol_") for m in pkgutil.iter_modules(serial.urlhandler.__path__)
               if m.name.startswith("protocol_")]
    return sorted(set(builtin) | set(register_url_handlers()))


def _sync_reply(sync: int) -> Callable[[bytes], bool]:
    """Whether a packet body is the reply to SYNC`sync` (SYNC0/1 echo one byte; SYNC2 names the robot)."""
    return lambda body: body[0] == sync and (sync == 2 or len(body) == 1)


class LinkError(NetworkError, ConnectionError):
    """The robot could not be reached or did not complete the ARCOS handshake."""


@dataclass(frozen=True)
class RobotInfo:
    """What the robot said in its SYNC2 reply."""

    name: str = ""
    robot_class: str = ""
    subclass: str = ""


@dataclass(frozen=True)
class RobotState:
    """The robot as the latest SIP describes it, in SI units (m, rad, m/s, rad/s, V)."""

    x: float
    y: float
    theta: float
    v: float
    w: float
    left: float
    right: float
    battery: float
    stall_left: bool
    stall_right: bool
    bumpers: int
    motors_enabled: bool
    moving: bool
    sonar: dict[int, float]
    stamp: float
    seq: int

    @property
    def stalled(self) -> bool:
        """True when either wheel is stalled."""
        return self.stall_left or self.stall_right


@dataclass
class DriverStats:
    """Counters of one driver: traffic, damage seen on the line, links made and lost."""

    sips: int = 0
    bad_sips: int = 0
    other_packets: int = 0
    commands: int = 0
    dropped_commands: int = 0
    connects: int = 0
    link_losses: int = 0
    handshake_failures: int = 0
    reader: arcos.ReaderStats = field(default_factory=arcos.ReaderStats)


def _wrap15(d: int) -> int:
    return ((d + 0x4000) & 0x7FFF) - 0x4000


class _Unwrapper:
    """Turns 15-bit wire positions into a continuous count by following small deltas."""

    def __init__(self) -> None:
        self.raw: int | None = None
        self.units = 0

    def update(self, raw: int) -> int:
        raw &= 0x7FFF
        if self.raw is None:
            self.units = raw - 0x8000 if raw >= 0x4000 else raw
        else:
            self.units += _wrap15(raw - self.raw)
        self.raw = raw
        return self.units

    def rebase(self, raw: int, units: int) -> None:
        self.raw, self.units = raw & 0x7FFF, units


class ArcosDriver:
    """One ARCOS robot on one pyserial URL; thread-safe commands, callbacks from the reader thread."""

    def __init__(self, url: str, model: RobotModel | None = None, *, name: str = "robot",
                 baudrate: int = 9600, sync_timeout: float = 0.5, sync_attempts: int = 5,
                 pulse_interval: float = 0.5, link_timeout: float = 1.0, reconnect: bool = True,
                 reconnect_delay: float = 0.5, enable_motors: bool = True,
                 on_sip: Callable[[RobotState], None] | None = None,
                 on_link: Callable[[bool, str], None] | None = None,
                 clock: Callable[[], float] = time.monotonic) -> None:
        if not url or not isinstance(url, str):
            raise LinkError(f"url: expected a serial device or pyserial URL, got {url!r}")
        self.url = url
        self.model = model or RobotModel(name="pioneer3")
        self.name = name
        self.baudrate = baudrate
        self.sync_timeout = sync_timeout
        self.sync_attempts = sync_attempts
        self.pulse_interval = pulse_interval
        self.link_timeout = link_timeout
        self.reconnect = reconnect
        self.reconnect_delay = reconnect_delay
        self.enable_motors = enable_motors
        self.on_sip = on_sip
        self.on_link = on_link
        self.clock = clock
        self.info = RobotInfo()
        self.stats = DriverStats()
        self._reader = arcos.PacketReader()
        self.stats.reader = self._reader.stats
        self._port: serial.SerialBase | None = None
        self._write_lock = threading.Lock()
        self._cond = threading.Condition()
        self._state: RobotState | None = None
        self._connected = False
        self._broken = False
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._last_write = 0.0
        self._last_sip = 0.0
        self._ux, self._uy = _Unwrapper(), _Unwrapper()
        self._rebase: tuple[int, int, float] | None = None
        self._frame = (0.0, 0.0, 0.0)  # map pose of the odometric origin (odometry re-localisation)
        self._sonar: dict[int, float] = {}
        self.last_error = ""

    # --- life cycle ---------------------------------------------------------------------

    def open(self, wait: bool = True, timeout: float | None = None) -> ArcosDriver:
        """Start the reader thread; with wait=True, block until connected or raise LinkError."""
        if self._thread is None:
            self._stop.clear()
            self._thread = threading.Thread(target=self._run, name=f"arcos-{self.name}", daemon=True)
            self._thread.start()
        if wait:
            limit = timeout if timeout is not None else self.sync_timeout * 3 * self.sync_attempts + 2.0
            with self._cond:
                ok = self._cond.wait_for(lambda: self._connected or not self._thread_alive(), limit)
            if not ok or not self._connected:
                error = self.last_error or "no answer"
                self.close()
                raise LinkError(f"{self.url}: cannot connect to the robot: {error}")
        return self

    def _thread_alive(self) -> bool:
        return self._thread is not None and self._thread.is_alive()

    def close(self) -> None:
        """Stop the robot, say goodbye (ENABLE 0, CLOSE), close the port and join the thread."""
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=5)
            self._thread = None

    def __enter__(self) -> ArcosDriver:
        return self.open()

    def __exit__(self, *exc: object) -> None:
        self.close()

    @property
    def connected(self) -> bool:
        """True while the handshake is done and SIPs keep arriving."""
        return self._connected

    @property
    def state(self) -> RobotState | None:
        """The latest decoded SIP, or None before the first."""
        return self._state

    def wait_for(self, predicate: Callable[[RobotState], bool], timeout: float) -> RobotState | None:
        """Block until a SIP satisfies `predicate`; return that state, or None on timeout."""
        with self._cond:
            ok = self._cond.wait_for(lambda: self._state is not None and predicate(self._state), timeout)
            return self._state if ok else None

    def wait_for_sip(self, after: int = -1, timeout: float = 2.0) -> RobotState | None:
        """Block until a SIP newer than sequence number `after` arrives."""
        return self.wait_for(lambda s: s.seq > after, timeout)

    # --- commands -----------------------------------------------------------------------

    def command(self, cmd: int, arg: int | bytes | str | None = None) -> bool:
        """Send one command; return False (and count it) when there is no link."""
        return self._write(arcos.encode_command(cmd, arg))

    def _write(self, packet: bytes, during_handshake: bool = False) -> bool:
        with self._write_lock:
            port = self._port
            if port is None or (not self._connected and not during_handshake):
                self.stats.dropped_commands += 1
                return False
            try:
                port.write(packet)
            except (serial.SerialException, OSError) as err:
                self.stats.dropped_commands += 1
                self.last_error = f"write failed: {err}"
                self._broken = True
                return False
            self._last_write = self.clock()
            self.stats.commands += 1
            return True

    def vel(self, v: float) -> bool:
        """Translate at v (m/s)."""
        return self.command(Cmd.VEL, _clamp16(round(v * 1000 / self.model.vel_conv)))

    def rvel(self, deg_s: float) -> bool:
        """Rotate at deg_s (deg/s, positive counter-clockwise)."""
        return self.command(Cmd.RVEL, _clamp16(round(deg_s)))

    def vel2(self, left: float, right: float) -> bool:
        """Drive the wheels at left/right (m/s)."""
        unit = self.model.vel2_divisor * self.model.vel_conv / 1000.0
        lb = max(-128, min(127, round(left / unit))) & 0xFF
        rb = max(-128, min(127, round(right / unit))) & 0xFF
        raw = (lb << 8) | rb
        return self.command(Cmd.VEL2, raw - 0x10000 if raw >= 0x8000 else raw)

    def head(self, deg: float) -> bool:
        """Turn to an absolute odometric heading (deg)."""
        return self.command(Cmd.HEAD, _clamp16(round(deg)))

    def dhead(self, deg: float) -> bool:
        """Turn by deg relative to the current heading setpoint."""
        return self.command(Cmd.DHEAD, _clamp16(round(deg)))

    def move(self, distance: float) -> bool:
        """Travel `distance` (m) straight ahead (negative: back)."""
        return self.command(Cmd.MOVE, _clamp16(round(distance * 1000 / self.model.dist_conv)))

    def setv(self, v: float) -> bool:
        """Set the robot's top translational speed (m/s)."""
        return self.command(Cmd.SETV, _clamp16(round(v * 1000 / self.model.vel_conv)))

    def seta(self, accel: float) -> bool:
        """Set acceleration (m/s^2, positive) or deceleration (negative)."""
        return self.command(Cmd.SETA, _clamp16(round(accel * 1000)))

    def seto(self) -> bool:
        """Reset the robot's odometry to the origin."""
        return self.command(Cmd.SETO)

    def stop(self) -> bool:
        """Stop translating and rotating."""
        return self.command(Cmd.STOP)

    def estop(self) -> bool:
        """Emergency stop."""
        return self.command(Cmd.ESTOP)

    def say(self, tones: bytes | str) -> bool:
        """Play a tone string (pairs of duration in 20 ms units and MIDI note)."""
        return self.command(Cmd.SAY, tones)

    def sonar(self, on: bool) -> bool:
        """Switch the sonar ring on or off."""
        return self.command(Cmd.SONAR, 1 if on else 0)

    def enable(self, on: bool) -> bool:
        """Enable or disable the motors."""
        return self.command(Cmd.ENABLE, 1 if on else 0)

    def pulse(self) -> bool:
        """Keep the watchdog fed."""
        return self.command(Cmd.PULSE)

    def sim_set_pose(self, x: float, y: float, heading_deg: float) -> bool:
        """Move a simulated robot to (x, y) m with heading (deg); odometry follows the move."""
        xmm, ymm = round(x * 1000), round(y * 1000)
        with self._cond:
            self._frame = (0.0, 0.0, 0.0)
            units_x, units_y = round(xmm / self.model.dist_conv), round(ymm / self.model.dist_conv)
            self._rebase = (units_x, units_y, self.clock() + 2.0)
        return self._write(arcos.encode_ints(Cmd.SIM_SET_POSE, _clamp16(xmm), _clamp16(ymm),
                                             _clamp16(round(heading_deg))))

    def relocalise(self, x: float, y: float, theta: float) -> None:
        """Declare that the robot is now at map pose (x, y, theta rad): odometry is re-based."""
        with self._cond:
            s = self._state
            ox, oy, oth = self._odometric() if s is not None else (0.0, 0.0, 0.0)
            fth = theta - oth
            c, sn = math.cos(fth), math.sin(fth)
            self._frame = (x - (c * ox - sn * oy), y - (sn * ox + c * oy), fth)
            if s is not None:
                self._state = replace(s, x=x, y=y, theta=_wrap(theta))

    # --- the reader thread --------------------------------------------------------------

    def _run(self) -> None:
        try:
            while not self._stop.is_set():
                if self._port is None:
                    if not self._connect():
                        if not self.reconnect and self.stats.connects == 0:
                            return
                        self._stop.wait(self.reconnect_delay)
                        continue
                self._service()
        finally:
            self._disconnect(goodbye=True)
            with self._cond:
                self._cond.notify_all()

    def _connect(self) -> bool:
        register_url_handlers()
        try:
            port = serial.serial_for_url(self.url, baudrate=self.baudrate, timeout=0.02,
                                         write_timeout=1.0)
        except (serial.SerialException, OSError, ValueError) as err:
            self.last_error = f"cannot open {self.url}: {err}"
            self.stats.handshake_failures += 1
            return False
        self._port = port
        try:
            info = self._handshake(port)
        except (serial.SerialException, OSError) as err:
            info = None
            self.last_error = f"link error during handshake: {err}"
        if info is None:
            self.stats.handshake_failures += 1
            self._disconnect(goodbye=False)
            return False
        self.info = info
        self._write(arcos.encode_command(Cmd.OPEN), during_handshake=True)
        if self.enable_motors:
            self._write(arcos.encode_command(Cmd.ENABLE, 1), during_handshake=True)
        self._last_sip = self.clock()
        self._broken = False
        with self._cond:
            self._connected = True
            self._cond.notify_all()
        self.stats.connects += 1
        log.info("%s: connected to %s %s %s", self.url, info.name, info.robot_class, info.subclass)
        if self.on_link:
            self.on_link(True, f"connected to {info.robot_class} {info.subclass}".strip())
        return True

    def _handshake(self, port: serial.SerialBase) -> RobotInfo | None:
        for attempt in range(self.sync_attempts):
            if self._stop.is_set():
                return None
            if attempt:
                self._write(arcos.encode_command(Cmd.CLOSE), during_handshake=True)
                self._stop.wait(0.05)
            port.reset_input_buffer()
            self._reader.reset()
            reply: bytes | None = None
            for sync in (0, 1, 2):
                self._write(arcos.encode_command(sync), during_handshake=True)
                reply = self._await(port, _sync_reply(sync))
                if reply is None:
                    self.last_error = f"no SYNC{sync} reply (attempt {attempt + 1}/{self.sync_attempts})"
                    break
            else:
                assert reply is not None  # the loop ran to its end: SYNC2 answered
                return RobotInfo(*arcos.parse_sync2(reply))
        return None

    def _await(self, port: serial.SerialBase, match: Callable[[bytes], bool]) -> bytes | None:
        deadline = self.clock() + self.sync_timeout
        while self.clock() < deadline and not self._stop.is_set():
            for body in self._reader.feed(port.read(port.in_waiting or 1)):
                if match(body):
                    return body
        return None

    def _service(self) -> None:
        port = self._port
        assert port is not None
        try:
            data = port.read(port.in_waiting or 1)
        except (serial.SerialException, OSError) as err:
            self._lose(str(err) if "failed" in str(err) else f"read failed: {err}")
            return
        if data:
            for body in self._reader.feed(data):
                self._packet(body)
        now = self.clock()
        if self._broken:
            self._lose(self.last_error or "write failed")
        elif now - self._last_sip > self.link_timeout:
            self._lose(f"no SIP for {now - self._last_sip:.1f} s")
        elif now - self._last_write > self.pulse_interval:
            self.pulse()

    def _lose(self, reason: str) -> None:
        self.last_error = reason
        self.stats.link_losses += 1
        log.warning("%s: link lost: %s", self.url, reason)
        self._disconnect(goodbye=False)
        if self.on_link:
            self.on_link(False, reason)
        if not self.reconnect:
            self._stop.set()

    def _disconnect(self, goodbye: bool) -> None:
        port = self._port
        if port is None:
            return
        if goodbye and self._connected:
            for packet in (arcos.encode_command(Cmd.STOP), arcos.encode_command(Cmd.ENABLE, 0),
                           arcos.encode_command(Cmd.CLOSE)):
                self._write(packet)
        with self._cond:
            self._connected = False
            self._cond.notify_all()
        with self._write_lock:
            self._port = None
        try:
            port.close()
        except (serial.SerialException, OSError):
            pass

    def _packet(self, body: bytes) -> None:
        if not arcos.is_sip(body):
            self.stats.other_packets += 1
            return
        try:
            sip = arcos.parse_sip(body)
        except arcos.ProtocolError:
            self.stats.bad_sips += 1
            return
        self._last_sip = self.clock()
        state = self._decode(sip)
        if self.on_sip:
            self.on_sip(state)

    def _decode(self, sip: arcos.RawSip) -> RobotState:
        m = self.model
        with self._cond:
            if self._rebase is not None:
                ex, ey, deadline = self._rebase
                if abs(_wrap15(sip.xpos - ex)) < 100 and abs(_wrap15(sip.ypos - ey)) < 100:
                    self._ux.rebase(sip.xpos, ex + _wrap15(sip.xpos - ex))
                    self._uy.rebase(sip.ypos, ey + _wrap15(sip.ypos - ey))
                    self._rebase = None
                elif self.clock() > deadline:
                    self._rebase = None
            ux, uy = self._ux.update(sip.xpos), self._uy.update(sip.ypos)
            ox, oy = ux * m.dist_conv / 1000.0, uy * m.dist_conv / 1000.0
            oth = _wrap(sip.thpos * m.angle_conv)
            fx, fy, fth = self._frame
            c, s = math.cos(fth), math.sin(fth)
            left = sip.lvel * m.vel_conv / 1000.0
            right = sip.rvel * m.vel_conv / 1000.0
            w = math.radians(sip.rotvel / 10.0) if sip.rotvel is not None else (right - left) / m.axle
            for num, rng in sip.sonar.items():
                self._sonar[num] = rng * m.range_conv / 1000.0
            seq = self._state.seq + 1 if self._state else 0
            self._raw_odo = (ox, oy, oth)
            self._state = RobotState(
                x=fx + c * ox - s * oy, y=fy + s * ox + c * oy, theta=_wrap(oth + fth),
                v=(left + right) / 2, w=w, left=left, right=right,
                battery=(sip.battery_x10 / 10.0 if sip.battery_x10 else sip.battery / 10.0),
                stall_left=sip.stall_left, stall_right=sip.stall_right, bumpers=sip.bumpers,
                motors_enabled=sip.motors_enabled, moving=sip.moving, sonar=dict(self._sonar),
                stamp=self._last_sip, seq=seq)
            self.stats.sips += 1
            self._cond.notify_all()
            return self._state

    def _odometric(self) -> tuple[float, float, float]:
        return getattr(self, "_raw_odo", (0.0, 0.0, 0.0))


def _wrap(a: float) -> float:
    return (a + math.pi) % (2 * math.pi) - math.pi


def _clamp16(v: int) -> int:
    return max(-0x7FFF, min(0x7FFF, int(v)))
