"""Simulated ARCOS robots: differential-drive physics and the robot end of the protocol.

Two layers, each usable alone:

- `SimRobot` is the physics: a differential-drive base with velocity and acceleration limits,
  position and heading controllers (MOVE, HEAD), a watchdog, a sonar ring cast against a
  `World`, bumpers and stall, and a battery drained by paper 000's energy model
  (P0 = 8.568 W standing, Pmov = 11.55 v + 14.838 W moving). `step(dt, now)` advances it,
  so any clock can drive it.
- `ArcosFirmware` is the robot end of the ARCOS protocol, sans I/O: `receive(bytes)` handles
  client packets (SYNC, OPEN, VEL, HEAD, MOVE, ... SIM_SET_POSE), `tick(now)` emits SIPs,
  and `take_output()` returns the bytes to put on the wire.

`sim.robot_host.RobotHost` puts robots on TCP ports and ptys.
"""

from __future__ import annotations

import logging
import math
import random
import struct
from collections.abc import Callable
from dataclasses import dataclass, field

from pydantic import BaseModel, ConfigDict, Field

from erni.sim.world import World

log = logging.getLogger("erni.sim.robot")

P0_WATTS = 8.568  # paper 000: power standing still
PMOV_SLOPE = 11.55  # paper 000: W per m/s while moving
PMOV_BASE = 14.838  # paper 000: W while moving, at v -> 0

PIONEER3_SONAR = (90, 50, 30, 10, -10, -30, -50, -90, -90, -130, -150, -170, 170, 150, 130, 90)
AMIGOBOT_SONAR = (90, 41, 15, -15, -41, -90, -145, 145)


class SimRobotConfig(BaseModel):
    """Everything that makes one simulated robot: body, limits, sensors, battery, wire factors."""

    model_config = ConfigDict(frozen=True, extra="forbid")

    name: str = "sim"
    robot_class: str = "Pioneer"
    subclass: str = "p3dx-sim"
    radius: float = Field(0.25, gt=0, description="body radius (m)")
    axle: float = Field(0.33, gt=0, description="wheel separation (m)")
    max_v: float = Field(1.5, gt=0, description="top speed (m/s)")
    accel: float = Field(1.0, gt=0, description="translational acceleration (m/s^2)")
    decel: float = Field(1.0, gt=0, description="translational deceleration (m/s^2)")
    max_rv: float = Field(300.0, gt=0, description="top turn rate (deg/s)")
    rot_accel: float = Field(300.0, gt=0, description="rotational acceleration (deg/s^2)")
    watchdog: float = Field(2.0, gt=0, description="stop after this long without a command (s)")
    sip_period: float = Field(0.1, gt=0, description="SIP period (s)")
    sonar_angles: tuple[float, ...] = PIONEER3_SONAR
    sonar_range: float = Field(5.0, gt=0, description="maximum sonar range (m)")
    battery_full: float = Field(13.0, gt=0, description="voltage when full (V)")
    battery_empty: float = Field(11.0, gt=0, description="voltage when empty (V)")
    battery_wh: float = Field(100.0, gt=0, description="usable energy (Wh)")
    dist_conv: float = Field(1.0, gt=0, description="mm per position unit on the wire")
    vel_conv: float = Field(1.0, gt=0, description="mm/s per velocity unit on the wire")
    line_noise: float = Field(0.0, ge=0, le=1, description="probability a sent packet is damaged")
    garbage_first: int = Field(0, ge=0, description="answer this many SYNC0s with garbage")
    seed: int = 0

    @classmethod
    def amigobot(cls, **kw: object) -> SimRobotConfig:
        """An AmigoBot with old-firmware conversion factors."""
        base = dict(robot_class="AmigoBot", subclass="amigo-sim", radius=0.18, axle=0.28, max_v=0.75,
                    sonar_angles=AMIGOBOT_SONAR, dist_conv=0.5083, vel_conv=0.6154)
        base.update(kw)
        return cls(**base)  # type: ignore[arg-type]


def heading_units(angle: float) -> int:
    """An angle (rad) in ARCOS heading units (4096 per turn, -2048..2047)."""
    return round(_wrap(angle) * 2048 / math.pi) or 0


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
        """Place the robot (teleport) and make odometry agree with the world pose."""
        self.x, self.y, self.th = x, y, _wrap(th)
        self.odo = (0.0, 0.0, 0.0)
        self.stop(emergency=True)
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
        if self.last_command > -math.inf and now - self.last_command > self.config.watchdog:
            self.watchdog_tripped = True
        tv, tw = self._targets()
        if not self.motors_enabled or self.watchdog_tripped:
            tv = tw = 0.0
        self.v = _approach(self.v, tv, self.accel * dt, self.decel * dt)
        self.w = _approach(self.w, tw, self.rot_accel * dt, self.rot_accel * dt)
        self._integrate(dt, tv)
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
                tw = math.copysign(min(self.max_rv, math.sqrt(2 * self.rot_accel * abs(err)), 8 * abs(err)), err)
        return tv, tw

    def _integrate(self, dt: float, tv: float) -> None:
        th2 = self.th + self.w * dt
        if abs(self.w) > 1e-9:
            r = self.v / self.w
            nx = self.x + r * (math.sin(th2) - math.sin(self.th))
            ny = self.y - r * (math.cos(th2) - math.cos(self.th))
        else:
            nx = self.x + self.v * dt * math.cos(self.th)
            ny = self.y + self.v * dt * math.sin(self.th)
        blocked = False
        if abs(self.v) > 1e-9:
            here = self.world.clearance(self.x, self.y, self.others())
            there = self.world.clearance(nx, ny, self.others())
            blocked = there < self.config.radius and there <= here
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

    def sonar(self) -> list[float]:
        """Return each sonar's range (m) from the body surface to the nearest echo."""
        out = []
        others = self.others()
        for deg in self.config.sonar_angles:
            a = self.th + math.radians(deg)
            ox = self.x + self.config.radius * math.cos(a)
            oy = self.y + self.config.radius * math.sin(a)
            best = self.config.sonar_range
            for spread in (-0.13, 0.0, 0.13):
                best = min(best, self.world.ray(ox, oy, a + spread, self.config.sonar_range, others))
            out.append(best)
        return out

    @property
    def battery(self) -> float:
        """Battery voltage (V), falling linearly with the energy drawn."""
        c = self.config
        soc = max(0.0, 1.0 - self.energy / (c.battery_wh * 3600.0))
        return c.battery_empty + (c.battery_full - c.battery_empty) * soc

    @property
    def moving(self) -> bool:
        """True while either velocity is not zero."""
        return abs(self.v) > 1e-4 or abs(self.w) > 1e-4


# --- the robot end of the protocol ---------------------------------------------------------


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


class ArcosFirmware:
    """The robot end of an ARCOS link: handshake, command handling and the SIP stream."""

    def __init__(self, robot: SimRobot) -> None:
        self.robot = robot
        self.state = "sync0"
        self._buf = bytearray()
        self._out = bytearray()
        self._next_sip = 0.0
        self._rng = random.Random(robot.config.seed)
        self._garbage_left = robot.config.garbage_first
        self.counts = {"packets": 0, "bad": 0, "sips": 0, "unknown": 0}
        self.now = 0.0

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
            del buf[:i]
            if len(buf) < 3 or len(buf) < 3 + buf[2]:
                return
            n = buf[2]
            body, check = bytes(buf[3:1 + n]), bytes(buf[1 + n:3 + n])
            if n < 3 or _checksum(body) != int.from_bytes(check, "big"):
                self.counts["bad"] += 1
                del buf[:2]
                continue
            del buf[:3 + n]
            self.counts["packets"] += 1
            self._handle(body[0], _args(body))

    def close(self) -> None:
        """The client went away: stop the robot and wait for a new handshake."""
        self.state = "sync0"
        self.robot.stop()
        self.robot.motors_enabled = False
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

    def _handle(self, cmd: int, args: list[int | bytes]) -> None:
        r = self.robot
        arg = next((a for a in args if isinstance(a, int)), 0)
        if self.state != "open":
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
                c = r.config
                self._send(b"\x02" + b"\x00".join(s.encode() for s in (c.name, c.robot_class, c.subclass)) + b"\x00")
            elif cmd == 1 and self.state == "ready":
                self.state = "open"
                self._next_sip = self.now
                r.touch(self.now)
            elif cmd == 2:
                self.state = "sync0"
            return
        r.touch(self.now)
        c = r.config
        if cmd == 0:  # PULSE
            return
        if cmd == 2:  # CLOSE
            self.close()
        elif cmd == 4:  # ENABLE
            r.motors_enabled = bool(arg)
            if not arg:
                r.stop()
        elif cmd == 5:  # SETA: positive accel, negative decel (mm/s^2)
            if arg > 0:
                r.accel = arg / 1000.0
            elif arg < 0:
                r.decel = -arg / 1000.0
        elif cmd == 6:  # SETV
            r.max_v = max(0.0, arg * c.vel_conv / 1000.0)
        elif cmd == 7:  # SETO
            r.reset_odometry()
        elif cmd == 8:  # MOVE (mm)
            r.move(arg * c.dist_conv / 1000.0)
        elif cmd in (9, 21):  # ROTATE, RVEL (deg/s)
            r.set_rotation(math.radians(arg))
        elif cmd == 10:  # SETRV
            r.max_rv = math.radians(abs(arg))
        elif cmd == 11:  # VEL (mm/s)
            r.set_velocity(arg * c.vel_conv / 1000.0)
        elif cmd == 12:  # HEAD (deg, odometric)
            r.set_heading(math.radians(arg))
        elif cmd == 13:  # DHEAD
            base = r.head_target if r.rot_mode == "head" else r.odometry()[2]
            r.set_heading(base + math.radians(arg))
        elif cmd == 15:  # SAY
            r.said.append(next((a for a in args if isinstance(a, bytes)), b""))
        elif cmd == 23:  # SETRA
            if arg:
                r.rot_accel = math.radians(abs(arg))
        elif cmd == 28:  # SONAR
            r.sonar_on = bool(arg)
        elif cmd == 29:  # STOP
            r.stop()
        elif cmd == 32:  # VEL2: high byte left, low byte right, signed, x20 mm/s
            raw = arg & 0xFFFF
            left, right = struct.unpack("bb", bytes([raw >> 8, raw & 0xFF]))
            r.set_wheels(left * 20 * c.vel_conv / 1000.0, right * 20 * c.vel_conv / 1000.0)
        elif cmd == 55:  # ESTOP
            r.stop(emergency=True)
        elif cmd == 224:  # SIM_SET_POSE x mm, y mm, th deg
            ints = [a for a in args if isinstance(a, int)] + [0, 0, 0]
            r.set_pose(ints[0] / 1000.0, ints[1] / 1000.0, math.radians(ints[2]))
        elif cmd == 225:  # SIM_RESET
            r.set_pose(*r.start)
        elif cmd in (3, 18, 30, 44, 50):
            pass  # POLLING, CONFIG, DIGOUT, BUMPSTALL, HOSTBAUD: accepted, nothing to simulate
        else:
            self.counts["unknown"] += 1

    def tick(self, now: float) -> None:
        """Emit a SIP if one is due."""
        self.now = now
        if self.state != "open" or now < self._next_sip:
            return
        period = self.robot.config.sip_period
        self._next_sip = max(self._next_sip + period, now - period)
        self._send(self.sip())
        self.counts["sips"] += 1

    def sip(self) -> bytes:
        """Return the body of a standard SIP describing the robot now."""
        r, c = self.robot, self.robot.config
        x, y, th = r.odometry()
        half = r.w * c.axle / 2
        lvel = round((r.v - half) * 1000 / c.vel_conv)
        rvel = round((r.v + half) * 1000 / c.vel_conv)
        stall = (1 if r.stall_left else 0) | (0x100 if r.stall_right else 0)
        stall |= ((r.bumpers & 0x7F) << 1) | (((r.bumpers >> 7) & 0x7F) << 9)
        flags = (1 if r.motors_enabled else 0) | (0x2 if r.sonar_on else 0)
        control = heading_units(r.head_target) if r.rot_mode == "head" else heading_units(th)
        body = struct.pack(
            "<BHHhhhBHhHB",
            0x33 if r.moving else 0x32,
            round(x * 1000 / c.dist_conv) & 0x7FFF,
            round(y * 1000 / c.dist_conv) & 0x7FFF,
            max(-2048, min(2047, heading_units(th))),
            lvel, rvel,
            max(0, min(255, round(r.battery * 10))),
            stall, control, flags,
            round((math.degrees(r.th) % 360) / 2) % 180,
        )
        ranges = r.sonar() if r.sonar_on else []
        body += bytes([len(ranges)])
        for i, rng in enumerate(ranges):
            body += struct.pack("<BH", i, min(0xFFFF, round(rng * 1000)))
        body += struct.pack("<BBBBBHBhH", 0, 0, 0, 0, 0, round(r.battery * 10) & 0xFFFF, 0,
                            max(-32768, min(32767, round(math.degrees(r.w) * 10))), 0)
        return body
