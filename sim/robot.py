"""Simulated ARCOS robots: differential-drive physics and the robot end of the protocol.

Two layers, each usable alone:

- `SimRobot` is the physics: a differential-drive base with velocity and acceleration limits,
  position and heading controllers (MOVE, HEAD), a watchdog, a sonar ring of transducers at
  their published positions cast against a `World`, bumpers and stall, and a battery drained
  by paper 000's energy model (P0 = 8.568 W standing, Pmov = 11.55 v + 14.838 W moving).
  `step(dt, now)` advances it, so any clock can drive it.
- `ArcosFirmware` is the robot end of the ARCOS protocol, sans I/O, as real firmware and the
  MobileSim/AMRISim simulators speak it: `receive(bytes)` handles client packets (SYNC, OPEN,
  CONFIG, VEL, HEAD, MOVE, ... SIM_SET_POSE, SIM_STAT, BATTERYINFO), `tick(now)` emits SIPs
  (each carrying the sonar readings fired since the last one), and `take_output()` returns the
  bytes to put on the wire. Commands are in the firmware's units (mm, mm/s, degrees), never
  scaled; only what the robot reports is in the model's wire units (DistConvFactor, ...).

`SimRobotConfig.for_model("amigo")` builds a robot from the published model table, so ARIA or
any other client finds the subtype it knows (`p3dx-sh`, `amigo`, ...).
`sim.robot_host.RobotHost` puts robots on TCP ports and ptys.
"""

from __future__ import annotations

import logging
import math
import random
import struct
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

from pydantic import ConfigDict, Field

from erni.blackboard.errors import ConfigError
from erni.blackboard.objects import Model
from erni.plugins.motion.robots import MODELS, Transducer, lookup
from erni.sim.world import World

log = logging.getLogger("erni.sim.robot")

P0_WATTS = 8.568  # paper 000: power standing still
PMOV_SLOPE = 11.55  # paper 000: W per m/s while moving
PMOV_BASE = 14.838  # paper 000: W while moving, at v -> 0

SERIAL = "SIM"
"""The serial number simulators give in CONFIG (MobileSim and AMRISim do too): clients may move them."""
FIRMWARE = "ERNI-S1.0"

COMMAND_NAMES = {0: "PULSE", 1: "OPEN", 2: "CLOSE", 3: "POLLING", 4: "ENABLE", 5: "SETA", 6: "SETV", 7: "SETO",
                 8: "MOVE", 9: "ROTATE", 10: "SETRV", 11: "VEL", 12: "HEAD", 13: "DHEAD", 15: "SAY", 18: "CONFIG",
                 19: "ENCODER", 21: "RVEL", 23: "SETRA", 28: "SONAR", 29: "STOP", 30: "DIGOUT", 32: "VEL2",
                 40: "IOREQUEST", 44: "BUMPSTALL", 50: "HOSTBAUD", 55: "ESTOP", 62: "BATTERYINFO",
                 224: "SIM_SET_POSE", 225: "SIM_RESET", 236: "SIM_CTRL", 237: "SIM_STAT", 238: "SIM_MESSAGE",
                 239: "SIM_EXIT"}

_P3DX = MODELS["p3dx-sh"]
PIONEER3_SONAR: tuple[Transducer | None, ...] = _P3DX.sonar
AMIGOBOT_SONAR: tuple[Transducer | None, ...] = MODELS["amigo"].sonar


class SimRobotConfig(Model):
    """Everything that makes one simulated robot: body, limits, sensors, battery, wire factors."""

    model_config = ConfigDict(frozen=True, extra="forbid")

    name: str = "sim"
    robot_class: str = "Pioneer"
    subclass: str = Field(_P3DX.subclass, description="subtype named in SYNC2 and CONFIG")
    radius: float = Field(0.25, gt=0, description="body radius (m)")
    axle: float = Field(0.33, gt=0, description="wheel separation (m)")
    max_v: float = Field(1.5, gt=0, description="top speed at start (m/s, SETV changes it)")
    accel: float = Field(1.0, gt=0, description="translational acceleration (m/s^2)")
    decel: float = Field(1.0, gt=0, description="translational deceleration (m/s^2)")
    max_rv: float = Field(300.0, gt=0, description="top turn rate at start (deg/s)")
    rot_accel: float = Field(300.0, gt=0, description="rotational acceleration (deg/s^2)")
    rot_decel: float | None = Field(None, gt=0, description="rotational deceleration (deg/s^2); default rot_accel")
    top_v: float = Field(2.2, gt=0, description="highest SETV accepted (m/s), CONFIG TransVelTop")
    top_rv: float = Field(500.0, gt=0, description="highest SETRV accepted (deg/s), CONFIG RotVelTop")
    top_accel: float = Field(2.0, gt=0, description="highest SETA accepted (m/s^2), CONFIG TransAccTop")
    top_rot_accel: float = Field(500.0, gt=0, description="highest SETRA accepted (deg/s^2), CONFIG RotAccTop")
    watchdog: float = Field(2.0, gt=0, description="stop after this long without a command (s)")
    sip_period: float = Field(0.1, gt=0, description="SIP period (s)")
    sonar: tuple[Transducer | None, ...] = Field(PIONEER3_SONAR, description="transducer poses (m, m, deg)")
    sonar_cycle: float = Field(0.04, ge=0, description="firing period of one transducer per bank of 8 (s); "
                               "0: every transducer in every SIP")
    sonar_range: float = Field(5.0, gt=0, description="maximum sonar range (m)")
    battery_full: float = Field(13.0, gt=0, description="voltage when full (V)")
    battery_empty: float = Field(11.0, gt=0, description="voltage when empty (V)")
    battery_wh: float = Field(100.0, gt=0, description="usable energy (Wh)")
    dist_conv: float = Field(1.0, gt=0, description="mm per position unit on the wire")
    vel_conv: float = Field(1.0, gt=0, description="mm/s per velocity unit on the wire")
    angle_conv: float = Field(0.001534, gt=0, description="rad per heading unit on the wire")
    range_conv: float = Field(1.0, gt=0, description="mm per sonar range unit on the wire")
    vel2_divisor: float = Field(20.0, gt=0, description="mm/s per VEL2 wheel unit")
    line_noise: float = Field(0.0, ge=0, le=1, description="probability a sent packet is damaged")
    garbage_first: int = Field(0, ge=0, description="answer this many SYNC0s with garbage")
    answer_config: bool = Field(True, description="reply to CONFIG (old firmware does not)")
    seed: int = 0

    @classmethod
    def for_model(cls, model: str, **kw: Any) -> SimRobotConfig:
        """A robot of a published model (`p3dx-sh`, `amigo`, `p3at-sh`, ... or `pioneer3`, `amigobot`)."""
        m = lookup(model)
        if m is None:
            raise ConfigError(f"model: unknown robot model {model!r}; expected one of {', '.join(MODELS)} "
                              "(or pioneer3, amigobot)")
        base: dict[str, Any] = dict(
            robot_class=m.robot_class, subclass=m.subclass, radius=m.radius, axle=m.track, sonar=m.sonar,
            dist_conv=m.dist_conv, vel_conv=m.vel_conv, angle_conv=m.angle_conv, range_conv=m.range_conv,
            vel2_divisor=m.vel2_divisor, top_v=m.top_v, top_rv=m.top_rv, max_v=min(1.5, m.top_v),
            max_rv=min(300.0, m.top_rv))
        base.update(kw)
        return cls(**base)

    @classmethod
    def amigobot(cls, **kw: Any) -> SimRobotConfig:
        """An AmigoBot with its original controller (subtype `amigo`: DistConv 0.5083, VelConv 0.6154)."""
        return cls.for_model("amigo", **{"max_v": 0.75, **kw})


def _wrap(a: float) -> float:
    return (a + math.pi) % (2 * math.pi) - math.pi


def _approach(value: float, target: float, up: float, down: float) -> float:
    """Move value toward target, by at most `up` when speeding up and `down` when slowing."""
    if value * target >= 0 and abs(target) >= abs(value):
        step = up
    else:
        step = down
    if target > value:
        return min(target, value + step)
    return max(target, value - step)


@dataclass
class SimRobot:
    """One differential-drive robot in a world; all state in SI units, heading in radians."""

    config: SimRobotConfig
    world: World = field(default_factory=World)
    x: float = 0.0
    y: float = 0.0
    th: float = 0.0

    def __post_init__(self) -> None:
        self.v = 0.0
        self.w = 0.0
        self.odo = (0.0, 0.0, 0.0)  # world pose of the odometric origin
        self.motors_enabled = False
        self.sonar_on = True
        self.trans_mode = "vel"  # vel | pos | wheels
        self.rot_mode = "vel"  # vel | head
        self.target_v = 0.0
        self.target_w = 0.0
        self.wheels = (0.0, 0.0)
        self.move_left = 0.0
        self.head_target = 0.0  # odometric heading (rad)
        self.max_v = self.config.max_v
        self.accel = self.config.accel
        self.decel = self.config.decel
        self.max_rv = math.radians(self.config.max_rv)
        self.rot_accel = math.radians(self.config.rot_accel)
        self.rot_decel = math.radians(self.config.rot_decel or self.config.rot_accel)
        self.last_command = -math.inf
        self.watchdog_tripped = False
        self.stall_left = self.stall_right = False
        self.bumpers = 0
        self.energy = 0.0  # J drawn since start
        self.said: list[bytes] = []
        self.others: Callable[[], list[tuple[tuple[float, float], float]]] = lambda: []
        self.start = (self.x, self.y, self.th)

    # --- commands (SI units) ------------------------------------------------------------

    def touch(self, now: float) -> None:
        """Note client traffic: feeds the watchdog."""
        self.last_command = now
        self.watchdog_tripped = False

    def set_velocity(self, v: float) -> None:
        """Translate at v (m/s), capped by max_v."""
        self.trans_mode = "vel"
        self.target_v = max(-self.max_v, min(self.max_v, v))
        if self.rot_mode == "wheels":
            self.rot_mode = "vel"

    def set_rotation(self, w: float) -> None:
        """Rotate at w (rad/s), capped by max_rv."""
        if self.trans_mode == "wheels":
            self.trans_mode, self.target_v = "vel", 0.0
        self.rot_mode = "vel"
        self.target_w = max(-self.max_rv, min(self.max_rv, w))

    def set_wheels(self, left: float, right: float) -> None:
        """Drive the wheels at left/right (m/s)."""
        self.trans_mode = self.rot_mode = "wheels"
        self.wheels = (left, right)

    def move(self, distance: float) -> None:
        """Travel `distance` (m) straight, then stop."""
        self.trans_mode = "pos"
        self.move_left = distance

    def set_heading(self, heading: float) -> None:
        """Turn to an odometric heading (rad)."""
        if self.trans_mode == "wheels":
            self.trans_mode, self.target_v = "vel", 0.0
        self.rot_mode = "head"
        self.head_target = _wrap(heading)

    def stop(self, emergency: bool = False) -> None:
        """Stop translating and rotating; an emergency stop is instantaneous."""
        self.trans_mode = self.rot_mode = "vel"
        self.target_v = self.target_w = 0.0
        if emergency:
            self.v = self.w = 0.0

    def set_pose(self, x: float, y: float, th: float) -> None:
        """Place the robot by hand and make odometry read the world pose again (as at start)."""
        self.x, self.y, self.th = x, y, _wrap(th)
        self.odo = (0.0, 0.0, 0.0)
        self.stop(emergency=True)
        self.stall_left = self.stall_right = False
        self.bumpers = 0

    def set_true_pose(self, x: float, y: float, th: float) -> None:
        """Move the robot's true pose, leaving odometry untouched (SIM_SET_POSE): the encoders never turned."""
        ox, oy, oth = self.odometry()
        self.x, self.y, self.th = x, y, _wrap(th)
        origin_th = _wrap(self.th - oth)
        c, s = math.cos(origin_th), math.sin(origin_th)
        self.odo = (x - (c * ox - s * oy), y - (s * ox + c * oy), origin_th)
        self.stall_left = self.stall_right = False
        self.bumpers = 0

    def reset_odometry(self) -> None:
        """Make the current pose the odometric origin (SETO)."""
        self.odo = (self.x, self.y, self.th)

    def odometry(self) -> tuple[float, float, float]:
        """Return the pose in the odometric frame (m, m, rad)."""
        ox, oy, oth = self.odo
        dx, dy = self.x - ox, self.y - oy
        c, s = math.cos(-oth), math.sin(-oth)
        return c * dx - s * dy, s * dx + c * dy, _wrap(self.th - oth)

    # --- physics ------------------------------------------------------------------------

    def step(self, dt: float, now: float) -> None:
        """Advance the robot by dt seconds; `now` is the clock the watchdog compares against."""
        if dt <= 0:
            return
        tv, nx, ny, th2 = self.propose(dt, now)
        blocked = False
        if abs(self.v) > 1e-9:
            here = self.world.clearance(self.x, self.y, self.others())
            there = self.world.clearance(nx, ny, self.others())
            blocked = self.blocked(here, there)
        self.commit(dt, tv, nx, ny, th2, blocked)

    # The step in three parts, so a host can test every robot's move against the world and
    # the other robots at once (`erni.sim.swarm`): propose -> clearances -> blocked -> commit.

    def propose(self, dt: float, now: float) -> tuple[float, float, float, float]:
        """Update the velocities for dt; return (target v, proposed x, y, heading) before collisions."""
        if self.last_command > -math.inf and now - self.last_command > self.config.watchdog:
            self.watchdog_tripped = True
        tv, tw = self._targets()
        if not self.motors_enabled or self.watchdog_tripped:
            tv = tw = 0.0
        self.v = _approach(self.v, tv, self.accel * dt, self.decel * dt)
        self.w = _approach(self.w, tw, self.rot_accel * dt, self.rot_decel * dt)
        th2 = self.th + self.w * dt
        if abs(self.w) > 1e-9:
            r = self.v / self.w
            nx = self.x + r * (math.sin(th2) - math.sin(self.th))
            ny = self.y - r * (math.cos(th2) - math.cos(self.th))
        else:
            nx = self.x + self.v * dt * math.cos(self.th)
            ny = self.y + self.v * dt * math.sin(self.th)
        return tv, nx, ny, th2

    def blocked(self, here: float, there: float) -> bool:
        """Whether a move from clearance `here` to clearance `there` (m) runs into something."""
        return there < self.config.radius and there <= here

    def commit(self, dt: float, tv: float, nx: float, ny: float, th2: float, blocked: bool) -> None:
        """Finish the step: move to (nx, ny) unless blocked (then bump and stall), turn, draw energy."""
        self._integrate(tv, nx, ny, th2, blocked)
        speed = (abs(self.v - self.w * self.config.axle / 2) + abs(self.v + self.w * self.config.axle / 2)) / 2
        power = P0_WATTS if speed < 1e-3 else PMOV_SLOPE * speed + PMOV_BASE
        self.energy += power * dt

    def _targets(self) -> tuple[float, float]:
        if self.trans_mode == "wheels":
            left, right = self.wheels
            return (left + right) / 2, (right - left) / self.config.axle
        tv = self.target_v
        if self.trans_mode == "pos":
            left = self.move_left
            if left == 0:
                self.trans_mode, self.target_v, tv = "vel", 0.0, 0.0
            else:  # brake along the stopping curve, creeping the last millimetres
                tv = math.copysign(min(self.max_v, math.sqrt(2 * self.decel * abs(left)) + 0.01), left)
        tw = self.target_w
        if self.rot_mode == "head":
            err = _wrap(self.head_target - self.odometry()[2])
            if abs(err) < math.radians(0.3):
                tw = 0.0
            else:
                tw = math.copysign(min(self.max_rv, math.sqrt(2 * self.rot_decel * abs(err)), 8 * abs(err)), err)
        return tv, tw

    def _integrate(self, tv: float, nx: float, ny: float, th2: float, blocked: bool) -> None:
        if blocked:
            self.v = 0.0
            bit = 0x01 if tv >= 0 else 0x80
            self.bumpers |= bit
            self.stall_left = self.stall_right = True
        else:
            if self.trans_mode == "pos":
                step = math.hypot(nx - self.x, ny - self.y)
                if step >= abs(self.move_left) > 0:  # the position controller lands on the target
                    k = abs(self.move_left) / step
                    nx, ny = self.x + (nx - self.x) * k, self.y + (ny - self.y) * k
                    self.trans_mode, self.target_v, self.v, self.move_left = "vel", 0.0, 0.0, 0.0
                else:
                    self.move_left -= math.copysign(step, self.move_left)
            self.x, self.y = nx, ny
            self.stall_left = self.stall_right = False
            if abs(self.v) > 1e-6:
                self.bumpers = 0
        self.th = _wrap(th2)

    # --- sensors ------------------------------------------------------------------------

    def sonar_reading(self, num: int, others: list[tuple[tuple[float, float], float]] | None = None) -> float | None:
        """Range (m) from transducer `num` to the nearest echo within its cone; None if it is not fitted."""
        pose = self.config.sonar[num] if 0 <= num < len(self.config.sonar) else None
        if pose is None:
            return None
        sx, sy, deg = pose
        c, s = math.cos(self.th), math.sin(self.th)
        ox, oy = self.x + c * sx - s * sy, self.y + s * sx + c * sy
        a = self.th + math.radians(deg)
        rng = self.config.sonar_range
        others = self.others() if others is None else others
        best = rng
        for spread in (-0.13, 0.0, 0.13):
            best = min(best, self.world.ray(ox, oy, a + spread, rng, others))
        return best

    def sonar(self) -> list[float | None]:
        """Every transducer's range (m), by sonar number (None where none is fitted)."""
        others = self.others()
        return [self.sonar_reading(i, others) for i in range(len(self.config.sonar))]

    @property
    def state_of_charge(self) -> float:
        """Fraction of the battery's energy left (0..1)."""
        return max(0.0, 1.0 - self.energy / (self.config.battery_wh * 3600.0))

    @property
    def battery(self) -> float:
        """Battery voltage (V), falling linearly with the energy drawn."""
        c = self.config
        return c.battery_empty + (c.battery_full - c.battery_empty) * self.state_of_charge

    @property
    def moving(self) -> bool:
        """True while either velocity is not zero."""
        return abs(self.v) > 1e-4 or abs(self.w) > 1e-4


# --- the robot end of the protocol ---------------------------------------------------------


def next_on_grid(tick: float, now: float, period: float) -> float:
    """The first time after `now` on the grid of `period` through `tick`: a schedule that skips
    the ticks a stall missed and keeps its phase."""
    return tick + (math.floor((now - tick) / period) + 1) * period


def _checksum(body: bytes) -> int:
    s = 0
    for i in range(0, len(body) - 1, 2):
        s = (s + (body[i] << 8 | body[i + 1])) & 0xFFFF
    return s ^ body[-1] if len(body) % 2 else s


def _packet(body: bytes) -> bytes:
    return b"\xfa\xfb" + bytes([len(body) + 2]) + body + _checksum(body).to_bytes(2, "big")


def _args(body: bytes) -> list[int | bytes]:
    out: list[int | bytes] = []
    i = 1
    while i < len(body):
        t = body[i]
        if t in (0x3B, 0x1B) and i + 3 <= len(body):
            n = body[i + 1] | body[i + 2] << 8
            out.append(n if t == 0x3B else -n)
            i += 3
        elif t == 0x2B and i + 2 <= len(body):
            n = body[i + 1]
            out.append(bytes(body[i + 2:i + 2 + n]))
            i += 3 + n
        else:
            break
    return out


def _u16(value: float) -> bytes:
    return struct.pack("<H", max(0, min(0xFFFF, round(value))))


def _u8(value: float) -> bytes:
    return bytes([max(0, min(255, round(value)))])


def _cstr(text: str) -> bytes:
    return text.encode("latin-1", "replace") + b"\x00"


@dataclass(frozen=True)
class _Command:
    """One client command as the firmware's handlers see it: the packet's body, its arguments and the
    first integer among them (0 when there is none)."""
    body: bytes
    args: list[int | bytes]
    arg: int

    @property
    def text(self) -> bytes:
        """The first string argument (empty when there is none)."""
        return next((a for a in self.args if isinstance(a, bytes)), b"")


class ArcosFirmware:
    """The robot end of an ARCOS link: handshake, command handling and the SIP stream."""

    def __init__(self, robot: SimRobot, label: str = "") -> None:
        self.robot = robot
        self.label = label or robot.config.name
        self.state = "sync0"
        self._buf = bytearray()
        self._out = bytearray()
        self._next_sip = 0.0
        self._sip_anchor = True
        self._rng = random.Random(robot.config.seed)
        self._garbage_left = robot.config.garbage_first
        self.counts = {"packets": 0, "bad": 0, "sips": 0, "skipped": 0, "unknown": 0}  # skipped: SIP slots a late tick missed
        self.now = 0.0
        self.host_baud = 0  # HOSTBAUD code last asked for (0 = 9600)
        self.simstat = False  # SIM_STAT 2: a SIMSTAT after every SIP
        self.battery_info = False  # BATTERYINFO 2: a battery packet after every SIP
        n = len(robot.config.sonar)
        self.banks = max(1, (n + 7) // 8)
        self.polling: list[list[int]] = [[i for i in range(b * 8, min(n, b * 8 + 8))] for b in range(self.banks)]
        self._fired: dict[int, float] = {}
        self._next_fire = 0.0
        self._fire_index = 0
        self.said_messages: list[str] = []

    @property
    def tops(self) -> tuple[float, float, float, float]:
        """The highest speed (m/s), turn rate (deg/s), acceleration (m/s^2) and rotational acceleration
        (deg/s^2) the firmware accepts: the configured tops, raised to the robot's own starting values."""
        c = self.robot.config
        return (max(c.top_v, c.max_v), max(c.top_rv, c.max_rv), max(c.top_accel, c.accel, c.decel),
                max(c.top_rot_accel, c.rot_accel, c.rot_decel or 0.0))

    def receive(self, data: bytes, now: float) -> None:
        """Consume bytes from the client, handling every complete packet."""
        self.now = now
        buf = self._buf
        buf += data
        while True:
            i = buf.find(b"\xfa\xfb")
            if i < 0:
                del buf[:max(0, len(buf) - 1)]
                return
            if i:
                log.debug("%s: %d bytes of line noise skipped", self.label, i)
            del buf[:i]
            if len(buf) < 3 or len(buf) < 3 + buf[2]:
                return
            n = buf[2]
            body, check = bytes(buf[3:1 + n]), bytes(buf[1 + n:3 + n])
            if n < 3 or _checksum(body) != int.from_bytes(check, "big"):
                self.counts["bad"] += 1
                log.debug("%s: bad packet dropped (count %d, checksum %s)", self.label, n, check.hex())
                del buf[:2]
                continue
            del buf[:3 + n]
            self.counts["packets"] += 1
            self._handle(body)

    def close(self) -> None:
        """The client went away: stop the robot and wait for a new handshake."""
        self.state = "sync0"
        self.robot.stop()
        self.robot.motors_enabled = False
        self.simstat = self.battery_info = False
        self._buf.clear()

    def _send(self, body: bytes) -> None:
        pkt = _packet(body)
        if self.robot.config.line_noise and self._rng.random() < self.robot.config.line_noise:
            kind = self._rng.randrange(3)
            if kind == 0:
                pkt = bytes(self._rng.randrange(256) for _ in range(self._rng.randrange(1, 12))) + pkt
            elif kind == 1:
                pkt = pkt[:-1] + bytes([pkt[-1] ^ 0x5A])
            else:
                pkt = pkt[:self._rng.randrange(3, len(pkt))]
        self._out += pkt

    def take_output(self) -> bytes:
        """Return and clear the bytes waiting to go to the client."""
        out = bytes(self._out)
        self._out.clear()
        return out

    def _handle(self, body: bytes) -> None:
        cmd = body[0]
        args = _args(body) if cmd != 224 else []
        arg = next((a for a in args if isinstance(a, int)), 0)
        if self.state != "open":
            self._handshake(cmd)
            return
        self.robot.touch(self.now)
        if cmd == 0:  # PULSE
            return
        log.debug("%s: %s %s", self.label, COMMAND_NAMES.get(cmd, f"command {cmd}"),
                  " ".join(repr(a) for a in args) if cmd != 224 else body[1:].hex())
        if cmd in _ACCEPTED:
            return  # accepted, nothing to simulate
        handler = _COMMANDS.get(cmd)
        if handler is None:
            self._unknown(body, "unknown command")
        else:
            handler(self, _Command(body, args, arg))

    def _close_cmd(self, c: _Command) -> None:  # CLOSE
        log.debug("%s: client closed the connection", self.label)
        self.close()

    def _polling_cmd(self, c: _Command) -> None:  # POLLING: the firing sequence, as sonar numbers 1..32
        self._set_polling(c.text)

    def _enable_cmd(self, c: _Command) -> None:  # ENABLE
        self.robot.motors_enabled = bool(c.arg)
        if not c.arg:
            self.robot.stop()

    def _seta_cmd(self, c: _Command) -> None:  # SETA: positive accel, negative decel (mm/s^2)
        if c.arg > 0:
            self.robot.accel = min(c.arg / 1000.0, self.tops[2])
        elif c.arg < 0:
            self.robot.decel = min(-c.arg / 1000.0, self.tops[2])

    def _setv_cmd(self, c: _Command) -> None:  # SETV (mm/s)
        self.robot.max_v = max(0.0, min(c.arg / 1000.0, self.tops[0]))

    def _seto_cmd(self, c: _Command) -> None:  # SETO
        self.robot.reset_odometry()

    def _move_cmd(self, c: _Command) -> None:  # MOVE (mm)
        self.robot.move(c.arg / 1000.0)

    def _rotate_cmd(self, c: _Command) -> None:  # ROTATE, RVEL (deg/s)
        self.robot.set_rotation(math.radians(c.arg))

    def _setrv_cmd(self, c: _Command) -> None:  # SETRV (deg/s)
        self.robot.max_rv = math.radians(min(abs(c.arg), self.tops[1]))

    def _vel_cmd(self, c: _Command) -> None:  # VEL (mm/s)
        self.robot.set_velocity(c.arg / 1000.0)

    def _head_cmd(self, c: _Command) -> None:  # HEAD (deg, odometric)
        self.robot.set_heading(math.radians(c.arg))

    def _dhead_cmd(self, c: _Command) -> None:  # DHEAD
        r = self.robot
        base = r.head_target if r.rot_mode == "head" else r.odometry()[2]
        r.set_heading(base + math.radians(c.arg))

    def _say_cmd(self, c: _Command) -> None:  # SAY
        self.robot.said.append(c.text)

    def _config_cmd(self, c: _Command) -> None:  # CONFIG
        if self.robot.config.answer_config:
            self._send(self.config_packet())
        else:
            self._unknown(c.body, "CONFIG not answered by this robot:")

    def _setra_cmd(self, c: _Command) -> None:  # SETRA: positive accel, negative decel (deg/s^2)
        if c.arg > 0:
            self.robot.rot_accel = math.radians(min(c.arg, self.tops[3]))
        elif c.arg < 0:
            self.robot.rot_decel = math.radians(min(-c.arg, self.tops[3]))

    def _sonar_cmd(self, c: _Command) -> None:  # SONAR
        self.robot.sonar_on = bool(c.arg)

    def _stop_cmd(self, c: _Command) -> None:  # STOP
        self.robot.stop()

    def _vel2_cmd(self, c: _Command) -> None:  # VEL2: high byte left, low byte right, signed, x Vel2Divisor mm/s
        raw = c.arg & 0xFFFF
        left, right = struct.unpack("bb", bytes([raw >> 8, raw & 0xFF]))
        divisor = self.robot.config.vel2_divisor
        self.robot.set_wheels(left * divisor / 1000.0, right * divisor / 1000.0)

    def _hostbaud_cmd(self, c: _Command) -> None:  # HOSTBAUD: on a serial line the rate changes after this packet
        self.host_baud = c.arg
        log.debug("%s: host serial rate code %d", self.label, c.arg)

    def _estop_cmd(self, c: _Command) -> None:  # ESTOP
        self.robot.stop(emergency=True)

    def _batteryinfo_cmd(self, c: _Command) -> None:  # BATTERYINFO: 0 stop, 1 one packet, 2 one after every SIP
        self.battery_info = c.arg == 2
        if c.arg in (1, 2):
            self._send(self.battery_packet())

    def _set_pose_cmd(self, c: _Command) -> None:  # SIM_SET_POSE: type byte, x mm, y mm, th deg, 32-bit little-endian
        if len(c.body) < 14:
            self._unknown(c.body, "SIM_SET_POSE too short")
            return
        x, y, th = struct.unpack_from("<iii", c.body, 2)
        log.debug("%s: true pose set to %d mm, %d mm, %d deg; odometry untouched", self.label, x, y, th)
        self.robot.set_true_pose(x / 1000.0, y / 1000.0, math.radians(th))

    def _reset_cmd(self, c: _Command) -> None:  # SIM_RESET: back to the start, odometry reading it
        self.robot.set_pose(*self.robot.start)

    def _simstat_cmd(self, c: _Command) -> None:  # SIM_STAT: 0 stop, 1 one packet now, 2 one after every SIP from now on
        self.simstat = c.arg == 2
        if c.arg == 1:
            self._send(self.simstat_packet())

    def _message_cmd(self, c: _Command) -> None:  # SIM_MESSAGE
        text = c.text.decode("latin-1")
        self.said_messages.append(text)
        log.info("%s: message from the client: %s", self.label, text)

    def _unknown(self, body: bytes, why: str) -> None:
        self.counts["unknown"] += 1
        log.debug("%s: %s %d ignored: %s", self.label, why, body[0], body.hex(" "))

    def _handshake(self, cmd: int) -> None:
        c = self.robot.config
        if cmd == 0:
            if self._garbage_left:
                self._garbage_left -= 1
                self._out += bytes(self._rng.randrange(256) for _ in range(7))
                return
            self.state = "sync1"
            self._send(b"\x00")
        elif cmd == 1 and self.state == "sync1":
            self.state = "sync2"
            self._send(b"\x01")
        elif cmd == 2 and self.state == "sync2":
            self.state = "ready"
            self._send(b"\x02" + _cstr(c.name) + _cstr(c.robot_class) + _cstr(c.subclass))
            log.debug("%s: handshake done: %s %s %s", self.label, c.name, c.robot_class, c.subclass)
        elif cmd == 1 and self.state == "ready":
            self.state = "open"
            self._next_sip = self.now
            self._sip_anchor = True
            self._next_fire = self.now
            self.robot.touch(self.now)
            log.debug("%s: OPEN: streaming SIPs every %.0f ms", self.label, c.sip_period * 1000)
        elif cmd == 2:
            self.state = "sync0"
        else:
            log.debug("%s: command %d during the handshake (state %s) ignored", self.label, cmd, self.state)

    def _set_polling(self, sequence: bytes) -> None:
        n = len(self.robot.config.sonar)
        order = [b - 1 for b in sequence if 1 <= b <= n]
        banks: list[list[int]] = [[] for _ in range(self.banks)]
        for num in order:
            banks[num // 8].append(num)
        self.polling = banks
        log.debug("%s: sonar polling sequence %s", self.label, order)

    def config_packet(self) -> bytes:
        """The CONFIG reply (ID 0x20), fields in the order ARCOS gives them."""
        r, c = self.robot, self.robot.config
        front = any(t is not None and abs(t[2]) <= 90 for t in c.sonar[:8])
        rear = any(t is not None for t in c.sonar[8:16])
        h, b = _u16, _u8
        return b"".join([
            b"\x20", _cstr(c.robot_class), _cstr(c.subclass), _cstr(SERIAL), b(0),
            h(self.tops[1]), h(self.tops[0] * 1000), h(self.tops[3]), h(self.tops[2] * 1000), h(500),
            _cstr(c.name), b(c.sip_period * 1000), b(self.host_baud), b(0), h(0), h(front), b(rear),
            h((c.battery_empty + 0.5) * 10), h(0), h(c.watchdog * 1000), b(1), h(0), h(0), h(0), h(0),
            h(math.degrees(r.max_rv)), h(r.max_v * 1000), h(math.degrees(r.rot_accel)),
            h(math.degrees(r.rot_decel)), h(0), h(0), h(0), h(r.accel * 1000), h(r.decel * 1000), h(0), h(0), h(0),
            b(0), b(0), b(0), b(c.sonar_cycle * 1000), b(2), b(0), struct.pack("<h", 0), b(0), b(0), h(0),
            h(c.battery_empty * 10), _cstr(FIRMWARE), h(0), h(0), b(0), h(0), h(0), h(0), h(0), h(0), h(0),
        ])

    def simstat_packet(self) -> bytes:
        """SIMSTAT (ID 0x62) as the simulators send it: the true pose, not odometry."""
        r = self.robot
        period = round(self.robot.config.sip_period * 1000)
        return (b"\x62" + b"\x00\x00" + struct.pack("<IHHH", 0, period, period, period)
                + struct.pack("<iiii", round(r.x * 1000), round(r.y * 1000), 0, round(math.degrees(r.th)))
                + struct.pack("<iiii", 0, 0, 0, -1) + struct.pack("<iii", 0, 0, 0))

    def battery_packet(self) -> bytes:
        """BATTERYINFO reply (ID 0xFA): one battery, five bytes: three flag bytes, relative and absolute charge."""
        soc = round(self.robot.state_of_charge * 100)
        return bytes([0xFA, 1, 5, 0, 0, 0, soc, soc])

    def tick(self, now: float, fire: bool = True, slack: float = 0.0, grid: float | None = None) -> None:
        """Fire the sonar due (unless the host fired it already) and emit a SIP if one is due.

        A host that ticks on a grid of physics steps passes half its step as `slack` and the
        tick's time on its grid as `grid`: a SIP goes at the tick nearest its time, on a schedule
        that starts at the grid time of the tick that sent the first one, so a tick late by less
        than half a step does not move a SIP to another tick and the stream keeps its period, as a
        real robot's does; with no slack a SIP goes at the first tick at or after its time."""
        self.now = now
        if self.state != "open":
            return
        if fire:
            self._fire(now)
        if now < self._next_sip - slack:
            return
        period = self.robot.config.sip_period
        if self._sip_anchor and slack > 0:  # the first SIP after OPEN: the schedule starts at this tick
            self._next_sip = (now if grid is None else grid) + period
        else:  # the next time on the schedule after this tick's reach: SIPs a stall missed are skipped
            due = self._next_sip
            self._next_sip = next_on_grid(due, now + slack, period)
            self.counts["skipped"] += max(0, round((self._next_sip - due) / period) - 1)
        self._sip_anchor = False
        self._send(self.sip())
        self.counts["sips"] += 1
        if self.simstat:
            self._send(self.simstat_packet())
        if self.battery_info:
            self._send(self.battery_packet())

    def _fire(self, now: float) -> None:
        due = self.due_firings(now)
        if due:
            r = self.robot
            others = r.others()
            self.record_firings(due, [r.sonar_reading(num, others) for num in due])

    def due_firings(self, now: float) -> list[int]:
        """The transducers (sonar numbers, in firing order) due by `now`; advances the firing cycle."""
        r, c = self.robot, self.robot.config
        if self.state != "open" or not r.sonar_on or c.sonar_cycle <= 0 or not c.sonar:
            return []
        due: list[int] = []
        fired = 0
        while now >= self._next_fire and fired < 64:
            for bank in self.polling:
                if bank:
                    due.append(bank[self._fire_index % len(bank)])
            self._fire_index += 1
            self._next_fire += c.sonar_cycle
            fired += 1
        if now >= self._next_fire:  # far behind (a stalled clock): skip ahead, never burst
            self._next_fire = now + c.sonar_cycle
        return due

    def record_firings(self, nums: list[int], ranges: list[float | None]) -> None:
        """Keep the ranges (m) the transducers `nums` measured for the next SIP (None: not fitted)."""
        for num, rng in zip(nums, ranges):
            if rng is not None:
                self._fired[num] = rng

    def sip(self) -> bytes:
        """Return the body of a standard SIP describing the robot now."""
        r, c = self.robot, self.robot.config
        x, y, th = r.odometry()
        half = r.w * c.axle / 2
        lvel = round((r.v - half) * 1000 / c.vel_conv)
        rvel = round((r.v + half) * 1000 / c.vel_conv)
        stall = (1 if r.stall_left else 0) | (0x100 if r.stall_right else 0)
        stall |= ((r.bumpers & 0x7F) << 1) | (((r.bumpers >> 7) & 0x7F) << 9)
        flags = (1 if r.motors_enabled else 0) | (0x1E if r.sonar_on else 0)
        def heading(a: float) -> int:
            return max(-2048, min(2047, round(_wrap(a) / c.angle_conv)))

        control = heading(r.head_target) if r.rot_mode == "head" else heading(th)
        body = struct.pack(
            "<BHHhhhBHhHB",
            0x33 if r.moving else 0x32,
            round(x * 1000 / c.dist_conv) & 0x7FFF,
            round(y * 1000 / c.dist_conv) & 0x7FFF,
            heading(th),
            max(-32768, min(32767, lvel)), max(-32768, min(32767, rvel)),
            max(0, min(255, round(r.battery * 10))),
            stall, control, flags,
            round((math.degrees(r.th) % 360) / 2) % 180,
        )
        if not r.sonar_on:
            readings: dict[int, float] = {}
        elif c.sonar_cycle > 0:
            readings, self._fired = self._fired, {}
        else:
            readings = {i: rng for i, rng in enumerate(r.sonar()) if rng is not None}
        body += bytes([len(readings)])
        for num in sorted(readings):
            body += struct.pack("<BH", num, min(0xFFFF, round(readings[num] * 1000 / c.range_conv)))
        body += struct.pack("<BBBBBHBhHhbB", 0, 0, 0, 0, 0, round(r.battery * 10) & 0xFFFF, 0,
                            max(-32768, min(32767, round(math.degrees(r.w) * 10))), 0, 0, -127,
                            round(r.state_of_charge * 100))
        return body


_F = ArcosFirmware
_COMMANDS: dict[int, Callable[[ArcosFirmware, _Command], None]] = {
    2: _F._close_cmd, 3: _F._polling_cmd, 4: _F._enable_cmd, 5: _F._seta_cmd, 6: _F._setv_cmd, 7: _F._seto_cmd,
    8: _F._move_cmd, 9: _F._rotate_cmd, 21: _F._rotate_cmd, 10: _F._setrv_cmd, 11: _F._vel_cmd, 12: _F._head_cmd,
    13: _F._dhead_cmd, 15: _F._say_cmd, 18: _F._config_cmd, 23: _F._setra_cmd, 28: _F._sonar_cmd, 29: _F._stop_cmd,
    32: _F._vel2_cmd, 50: _F._hostbaud_cmd, 55: _F._estop_cmd, 62: _F._batteryinfo_cmd, 224: _F._set_pose_cmd,
    225: _F._reset_cmd, 237: _F._simstat_cmd, 238: _F._message_cmd,
}
"""The firmware's handler of each client command it simulates, by command number."""
_ACCEPTED = frozenset({19, 30, 40, 44, 236})  # ENCODER, DIGOUT, IOREQUEST, BUMPSTALL, SIM_CTRL: nothing to simulate
