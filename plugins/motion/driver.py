"""The ARCOS robot driver: any pyserial URL, handshake, reader thread, watchdog pulse, reconnects.

`ArcosDriver(url, model)` opens `/dev/ttyUSB0`, `socket://host:8101` (MobileSim, AMRISim, the
built-in simulator) or any other pyserial URL. One thread, `arcos-<name>`, owns the port: it
connects as ARIA does (SYNC0/1/2 with retries; the model from the SYNC2 subtype; OPEN; CONFIG,
whose reply gives firmware, serial number, top speeds and current accelerations; HOSTBAUD to
38400 on a serial line when the firmware allows it; ENABLE; SETV/SETRV/SETA/SETRA so the robot
brakes as the planner assumes), turns bytes into packets and SIPs into `RobotState` (SI units,
15-bit positions unwrapped), sends PULSE when the link is idle, and reconnects when the link
drops. Damaged data from the robot (garbage, bad checksums, truncated SIPs, impossible sonar
counts) is counted per kind in `damage`, logged at most once per 10 s per kind, and carried in
each `RobotState`. Commands may be sent from any thread.
"""

from __future__ import annotations

import logging
import math
import pkgutil
import threading
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field, replace
from importlib.metadata import entry_points
from typing import Any

import serial

from erni.blackboard.clock import monotonic
from erni.blackboard.errors import NetworkError
from erni.plugins.motion import arcos
from erni.plugins.motion.arcos import Cmd
from erni.plugins.motion.damage import LineDamage
from erni.plugins.motion.opening import LinkOpening
from erni.plugins.motion.opening import RobotInfo as RobotInfo
from erni.plugins.motion.opening import waiting as waiting
from erni.plugins.motion.robots import DEFAULT_LIMITS, ModelSpec, RobotModel, model_spec

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
    """The URL schemes a driver can open: pyserial's own (socket://, rfc2217://, loop:// ...), those
    registered through the `erni.serial_handlers` entry points, and ros2:// (a ROS 2 base, ros2_base.py)."""
    import serial.urlhandler

    builtin = [m.name.removeprefix("protocol_") for m in pkgutil.iter_modules(serial.urlhandler.__path__)
               if m.name.startswith("protocol_")]
    return sorted(set(builtin) | set(register_url_handlers()) | {"ros2"})


class LinkError(NetworkError, ConnectionError):
    """The robot could not be reached or did not complete the ARCOS handshake."""


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
    sim_pose: tuple[float, float, float] | None = None  # a simulator's true pose (m, m, rad), from SIMSTAT
    sim_stamp: float = -math.inf  # when that SIMSTAT arrived
    damage: Mapping[str, int] = field(default_factory=dict)  # damaged data from the robot so far, per kind

    @property
    def stalled(self) -> bool:
        """True when either wheel is stalled."""
        return self.stall_left or self.stall_right


@dataclass
class DriverStats:
    """Counters of one driver: traffic, damage seen on the line, links made and lost."""

    sips: int = 0
    reads: int = 0
    bad_sips: int = 0
    other_packets: int = 0
    bad_packets: int = 0
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
    """One ARCOS robot on one pyserial URL; thread-safe commands, callbacks from the reader thread.

    `model` is 'auto' (the model the robot names in SYNC2), a model name, a table with a `base`
    and overrides, or a RobotModel. After each handshake `model` is the model in use, its
    planner limits filled in from the configuration, the robot's CONFIG reply and the ARCOS
    defaults, and sent to the robot (SETV, SETRV, SETA, SETRA).
    """

    def __init__(self, url: str, model: str | Mapping[str, Any] | RobotModel | ModelSpec | None = None, *,
                 name: str = "robot", baudrate: int = 9600, sync_timeout: float = 0.5, sync_attempts: int = 5,
                 pulse_interval: float = 0.5, link_timeout: float = 1.0, reconnect: bool = True,
                 reconnect_delay: float = 0.5, enable_motors: bool = True, config_timeout: float = 1.0,
                 switch_baud: bool = True, send_limits: bool = True,
                 on_sip: Callable[[RobotState], None] | None = None,
                 on_link: Callable[[bool, str], None] | None = None,
                 clock: Callable[[], float] = monotonic) -> None:
        if not url or not isinstance(url, str):
            raise LinkError(f"url: expected a serial device or pyserial URL, got {url!r}")
        self.url = url
        self.spec = model_spec(model if model is not None else "auto")
        self.model = fill_limits(self.spec.resolve()[0], None)
        self.name = name
        self.baudrate = baudrate
        self.sync_timeout = sync_timeout
        self.sync_attempts = sync_attempts
        self.pulse_interval = pulse_interval
        self.link_timeout = link_timeout
        self.reconnect = reconnect
        self.reconnect_delay = reconnect_delay
        self.enable_motors = enable_motors
        self.config_timeout = config_timeout
        self.switch_baud = switch_baud
        self.send_limits = send_limits
        self.on_sip = on_sip
        self.on_link = on_link
        self.clock = clock
        self.info = RobotInfo()
        self.robot_config: arcos.RobotConfig | None = None
        self.battery_info: arcos.BatteryInfo | None = None
        self.line_baud: int | None = None  # the serial rate in use on a serial line
        self.stats = DriverStats()
        self.sip_interval = 0.1  # seconds between SIPs, averaged
        self.read_timeout = max(0.005, min(0.1, pulse_interval / 4, link_timeout / 4))
        self._reader = arcos.PacketReader()
        self.stats.reader = self._reader.stats
        self.damage = LineDamage(f"{name} ({url})", log, clock=clock)
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
        self._frame = (0.0, 0.0, 0.0)  # map pose of the odometric origin (odometry re-localisation)
        self._raw_odo = (0.0, 0.0, 0.0)
        self._sonar: dict[int, float] = {}
        self._sim_pose: tuple[float, float, float] | None = None
        self._sim_stamp = -math.inf
        self.last_error = ""

    # --- life cycle ---------------------------------------------------------------------

    def open(self, wait: bool = True, timeout: float | None = None) -> ArcosDriver:
        """Start the reader thread; with wait=True, block until connected or raise LinkError."""
        if self._thread is None:
            self._stop.clear()
            self._thread = threading.Thread(target=self._run, name=f"arcos-{self.name}", daemon=True)
            self._thread.start()
        if wait:
            limit = timeout if timeout is not None else \
                self.sync_timeout * 3 * self.sync_attempts + self.config_timeout + 3.0
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

    @property
    def is_simulator(self) -> bool:
        """The robot's CONFIG reply says it is a simulator (serial number SIM: MobileSim, AMRISim, ERNI)."""
        return self.robot_config is not None and self.robot_config.simulator

    def wait_for(self, predicate: Callable[[RobotState], bool], timeout: float) -> RobotState | None:
        """Block until a SIP satisfies `predicate`; return that state, or None on timeout."""
        with self._cond:
            ok = self._cond.wait_for(lambda: self._state is not None and predicate(self._state), timeout)
            return self._state if ok else None

    def wait_for_sip(self, after: int = -1, timeout: float = 2.0) -> RobotState | None:
        """Block until a SIP newer than sequence number `after` arrives."""
        return self.wait_for(lambda s: s.seq > after, timeout)

    # --- commands (never converted: mm, mm/s, degrees and deg/s on every ARCOS robot) ----

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
        """Translate at v (m/s): VEL in mm/s."""
        return self.command(Cmd.VEL, _clamp16(round(v * 1000)))

    def rvel(self, deg_s: float) -> bool:
        """Rotate at deg_s (deg/s, positive counter-clockwise)."""
        return self.command(Cmd.RVEL, _clamp16(round(deg_s)))

    def vel2(self, left: float, right: float) -> bool:
        """Drive the wheels at left/right (m/s): VEL2 in units of Vel2Divisor mm/s."""
        unit = self.model.vel2_divisor / 1000.0
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
        """Travel `distance` (m) straight ahead (negative: back): MOVE in mm."""
        return self.command(Cmd.MOVE, _clamp16(round(distance * 1000)))

    def setv(self, v: float) -> bool:
        """Set the robot's top translational speed (m/s): SETV in mm/s."""
        return self.command(Cmd.SETV, _clamp16(round(v * 1000)))

    def setrv(self, deg_s: float) -> bool:
        """Set the robot's top turn rate (deg/s)."""
        return self.command(Cmd.SETRV, _clamp16(round(deg_s)))

    def seta(self, accel: float) -> bool:
        """Set acceleration (m/s^2, positive) or deceleration (negative): SETA in mm/s^2."""
        return self.command(Cmd.SETA, _clamp16(round(accel * 1000)))

    def setra(self, accel: float) -> bool:
        """Set rotational acceleration (deg/s^2, positive) or deceleration (negative)."""
        return self.command(Cmd.SETRA, _clamp16(round(accel)))

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

    def sim_stat(self) -> bool:
        """Ask a simulator for one SIMSTAT packet (its true pose); real robots ignore it."""
        return self.command(Cmd.SIM_STAT, 1)

    def sim_set_pose(self, x: float, y: float, heading_deg: float) -> bool:
        """Move a simulated robot's true pose to (x, y) m, heading (deg), and re-base odometry there.

        The simulator leaves its odometry alone (a real robot's encoders would not see a hand
        lifting it), so the map pose of the odometric frame is re-based on the new pose, and a
        SIMSTAT is requested: `state.sim_pose` confirms where the simulator put the robot.
        """
        if not self._write(arcos.encode_sim_set_pose(round(x * 1000), round(y * 1000), round(heading_deg))):
            return False
        self.relocalise(x, y, math.radians(heading_deg))
        return self.sim_stat()

    def relocalise(self, x: float, y: float, theta: float) -> None:
        """Declare that the robot is now at map pose (x, y, theta rad): odometry is re-based."""
        with self._cond:
            s = self._state
            ox, oy, oth = self._raw_odo if s is not None else (0.0, 0.0, 0.0)
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
            # the reader wakes on data; the timeout only paces the link and pulse checks between SIPs
            port = serial.serial_for_url(self.url, baudrate=self.baudrate, timeout=self.read_timeout,
                                         write_timeout=1.0)
        except (serial.SerialException, OSError, ValueError) as err:
            self.last_error = f"cannot open {self.url}: {err}"
            self.stats.handshake_failures += 1
            return False
        self._port = port
        try:
            ok = self._start_session(port)
        except (serial.SerialException, OSError) as err:
            ok = False
            self.last_error = f"link error during handshake: {err}"
        if not ok:
            self.stats.handshake_failures += 1
            self._disconnect(goodbye=False)
            return False
        self._last_sip = self.clock()
        self._broken = False
        with self._cond:
            self._connected = True
            self._cond.notify_all()
        self.stats.connects += 1
        info, cfg, m = self.info, self.robot_config, self.model
        log.info("%s: connected to %r, %s %s%s; model %s (DistConv %g, VelConv %g), limits %.2f m/s %g deg/s, "
                 "accel %.2f decel %.2f m/s2, rot %g/%g deg/s2", self.url, info.name, info.robot_class,
                 info.subclass, f", firmware {cfg.firmware}, serial {cfg.serial}" if cfg else ", no CONFIG reply",
                 m.name, m.dist_conv, m.vel_conv, m.limit("max_v"), m.limit("max_rv"), m.limit("accel"),
                 m.limit("decel"), m.limit("rot_accel"), m.limit("rot_decel"))
        if self.on_link:
            self.on_link(True, f"connected to {info.robot_class} {info.subclass}".strip())
        return True

    def _start_session(self, port: serial.SerialBase) -> bool:
        """Handshake, OPEN, CONFIG, HOSTBAUD, ENABLE and the limits: everything before the link is up."""
        opening = LinkOpening(self.url, port, self._reader, lambda packet: self._write(packet, during_handshake=True),
                              self._stop, self.clock)
        info = opening.handshake(self.sync_attempts, self.sync_timeout)
        self.last_error = opening.last_error or self.last_error
        if info is None:
            return False
        self.info = info
        model, warnings = self.spec.resolve(info.subclass)
        for w in warnings:
            log.warning("%s: %s", self.url, w)
        self._ux, self._uy = _Unwrapper(), _Unwrapper()
        self._write(arcos.encode_command(Cmd.OPEN), during_handshake=True)
        self.robot_config = opening.request_config(self.config_timeout, self._packet)
        if self.robot_config is None:
            log.info("%s: no CONFIG reply within %.1f s; using the model's values", self.url, self.config_timeout)
        elif self.robot_config.subclass and info.subclass and self.robot_config.subclass != info.subclass:
            log.warning("%s: SYNC2 names subtype %r but CONFIG %r", self.url, info.subclass,
                        self.robot_config.subclass)
        self.line_baud = port.baudrate if isinstance(port, serial.Serial) else None
        if (self.switch_baud and isinstance(port, serial.Serial) and self.robot_config is not None
                and self.robot_config.can_switch_baud and model.switch_baud > port.baudrate):
            opening.switch_baud(model.switch_baud)
            self.line_baud = port.baudrate
        if self.enable_motors:
            self._write(arcos.encode_command(Cmd.ENABLE, 1), during_handshake=True)
        self.model = fill_limits(model, self.robot_config)
        if self.send_limits:
            m = self.model
            for cmd, value in ((Cmd.SETV, m.limit("max_v") * 1000), (Cmd.SETRV, m.limit("max_rv")),
                               (Cmd.SETA, m.limit("accel") * 1000), (Cmd.SETA, -m.limit("decel") * 1000),
                               (Cmd.SETRA, m.limit("rot_accel")), (Cmd.SETRA, -m.limit("rot_decel"))):
                self._write(arcos.encode_command(cmd, _clamp16(round(value))), during_handshake=True)
        self._write(arcos.encode_command(Cmd.BATTERYINFO, 1), during_handshake=True)
        return True

    def _service(self) -> None:
        port = self._port
        assert port is not None
        try:
            data = port.read(waiting(port) or 1)
            self.stats.reads += 1
        except (serial.SerialException, OSError) as err:
            self._lose(str(err) if "failed" in str(err) else f"read failed: {err}")
            return
        if data:
            rs = self._reader.stats
            before = (rs.bytes_skipped, rs.bad_checksum, rs.bad_count)
            for body in self._reader.feed(data):
                self._packet(body)
            if (rs.bytes_skipped, rs.bad_checksum, rs.bad_count) != before:
                self.damage.note("garbage_bytes", rs.bytes_skipped - before[0])
                self.damage.note("bad_checksum", rs.bad_checksum - before[1])
                self.damage.note("bad_length", rs.bad_count - before[2])
        self.damage.flush()
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
        kind = body[0]
        try:
            if arcos.is_sip(body):
                sip = arcos.parse_sip(body)
            elif kind == arcos.SIMSTAT_REPLY:
                self._simstat(arcos.parse_simstat(body))
                return
            elif kind == arcos.BATTERY_REPLY:
                self.battery_info = arcos.parse_battery_info(body)
                return
            elif kind == arcos.CONFIG_REPLY:
                self.robot_config = arcos.parse_config(body)
                return
            else:
                self.stats.other_packets += 1
                return
        except arcos.ProtocolError as err:
            if arcos.is_sip(body):
                self.stats.bad_sips += 1
            else:
                self.stats.bad_packets += 1
            self.damage.note(err.kind, 1, f"packet 0x{kind:02X}: {err}")
            return
        now = self.clock()
        if self.stats.sips:
            self.sip_interval += 0.1 * (min(now - self._last_sip, 1.0) - self.sip_interval)
        self._last_sip = now
        state = self._decode(sip)
        if self.on_sip:
            self.on_sip(state)

    def _simstat(self, stat: arcos.SimStat) -> None:
        with self._cond:
            self._sim_pose = (stat.x / 1000.0, stat.y / 1000.0, _wrap(math.radians(stat.th)))
            self._sim_stamp = self.clock()
            if self._state is not None:
                self._state = replace(self._state, sim_pose=self._sim_pose, sim_stamp=self._sim_stamp)
            self._cond.notify_all()

    def _decode(self, sip: arcos.RawSip) -> RobotState:
        m = self.model
        with self._cond:
            ux, uy = self._ux.update(sip.xpos), self._uy.update(sip.ypos)
            ox, oy = ux * m.dist_conv / 1000.0, uy * m.dist_conv / 1000.0
            oth = _wrap(sip.thpos * m.angle_conv)
            fx, fy, fth = self._frame
            c, s = math.cos(fth), math.sin(fth)
            left = sip.lvel * m.vel_conv / 1000.0
            right = sip.rvel * m.vel_conv / 1000.0
            w = math.radians(sip.rotvel / 10.0) if sip.rotvel is not None else (right - left) / 2 * m.diff_conv
            for num, rng in sip.sonar.items():
                self._sonar[num] = rng * m.range_conv / 1000.0
            seq = self._state.seq + 1 if self._state else 0
            self._raw_odo = (ox, oy, oth)
            moving = sip.moving or sip.lvel != 0 or sip.rvel != 0 or bool(sip.rotvel)
            self._state = RobotState(
                x=fx + c * ox - s * oy, y=fy + s * ox + c * oy, theta=_wrap(oth + fth),
                v=(left + right) / 2, w=w, left=left, right=right,
                battery=(sip.battery_x10 / 10.0 if sip.battery_x10 else sip.battery / 10.0),
                stall_left=sip.stall_left, stall_right=sip.stall_right, bumpers=sip.bumpers,
                motors_enabled=sip.motors_enabled, moving=moving, sonar=dict(self._sonar),
                stamp=self._last_sip, seq=seq, sim_pose=self._sim_pose, sim_stamp=self._sim_stamp,
                damage=self.damage.totals)
            self.stats.sips += 1
            self._cond.notify_all()
            return self._state


def fill_limits(model: RobotModel, config: arcos.RobotConfig | None) -> RobotModel:
    """The model with every planner limit set: configured, else the robot's current, else the ARCOS default,
    never above the robot's top (CONFIG's *Top fields, else the model's published absolute maxima)."""
    values: dict[str, float] = {}
    for name, current, top, scale in (("max_v", "trans_vel_max", "trans_vel_top", 1000.0),
                                      ("max_rv", "rot_vel_max", "rot_vel_top", 1.0),
                                      ("accel", "trans_accel", "trans_accel_top", 1000.0),
                                      ("decel", "trans_decel", "trans_accel_top", 1000.0),
                                      ("rot_accel", "rot_accel", "rot_accel_top", 1.0),
                                      ("rot_decel", "rot_decel", "rot_accel_top", 1.0)):
        value = getattr(model, name)
        reported = getattr(config, current) if config is not None else None
        if value is None and reported:
            value = reported / scale
        if value is None:
            value = DEFAULT_LIMITS[name]
        ceiling = getattr(config, top) if config is not None else None
        if ceiling:
            value = min(value, ceiling / scale)
        elif name == "max_v":
            value = min(value, model.top_v)
        elif name == "max_rv":
            value = min(value, model.top_rv)
        values[name] = float(value)
    return model.model_copy(update=values)


def _wrap(a: float) -> float:
    return (a + math.pi) % (2 * math.pi) - math.pi


def _clamp16(v: int) -> int:
    return max(-0x7FFF, min(0x7FFF, int(v)))
