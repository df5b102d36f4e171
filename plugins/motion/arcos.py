"""The ARCOS / P2OS wire protocol, client side: framing, checksums, commands and SIP decoding.

Sans-I/O: `encode_command` turns a command into bytes, `PacketReader` turns any byte stream
(line noise included) into checksummed packets and counts what it had to skip, and
`parse_sip` decodes a server information packet into raw integer fields; `parse_config`,
`parse_simstat` and `parse_battery_info` decode the CONFIG (0x20), SIMSTAT (0x62) and battery
(0xFA) replies. Unit conversion (mm, rad, m/s) of what the robot reports lives in the driver
with the robot model's conversion factors; commands are never converted (VEL is mm/s, MOVE is
mm, HEAD is degrees on every ARCOS robot and simulator).
"""

from __future__ import annotations

import enum
import struct
from dataclasses import dataclass, field

from erni.blackboard.errors import ErniError

HEADER = b"\xfa\xfb"
MAX_COUNT = 249  # the count byte: ID + args + checksum; real robots stay below ~200

ARG_INT = 0x3B  # a positive 16-bit integer follows
ARG_NINT = 0x1B  # the absolute value of a negative 16-bit integer follows
ARG_STR = 0x2B  # a length byte, the characters, a NUL


class Cmd(enum.IntEnum):
    """ARCOS client command numbers (the packet ID byte)."""

    PULSE = 0
    SYNC0 = 0
    OPEN = 1
    SYNC1 = 1
    CLOSE = 2
    SYNC2 = 2
    POLLING = 3
    ENABLE = 4
    SETA = 5
    SETV = 6
    SETO = 7
    MOVE = 8
    ROTATE = 9
    SETRV = 10
    VEL = 11
    HEAD = 12
    DHEAD = 13
    SAY = 15
    CONFIG = 18
    ENCODER = 19
    RVEL = 21
    SETRA = 23
    SONAR = 28
    STOP = 29
    DIGOUT = 30
    VEL2 = 32
    IOREQUEST = 40
    BUMPSTALL = 44
    HOSTBAUD = 50
    ESTOP = 55
    BATTERYINFO = 62
    SIM_SET_POSE = 224
    SIM_RESET = 225
    SIM_CTRL = 236
    SIM_STAT = 237
    SIM_MESSAGE = 238
    SIM_EXIT = 239


SIP_STOPPED = 0x32
SIP_MOVING = 0x33
CONFIG_REPLY = 0x20
SIMSTAT_REPLY = 0x62
BATTERY_REPLY = 0xFA

BAUD_CODES = {9600: 0, 19200: 1, 38400: 2, 57600: 3, 115200: 4}
"""HOSTBAUD argument (and CONFIG's HostBaud field) for each serial rate."""


class ProtocolError(ErniError, ValueError):
    """A packet or argument does not fit the ARCOS wire format; `kind` names the damage for counting."""

    kind = "bad_packet"


class TruncatedSip(ProtocolError):
    """A SIP shorter than its fixed fields."""

    kind = "truncated_sip"


class BadSonarCount(ProtocolError):
    """A SIP that announces more sonar readings than it carries (a count of 255 in a short SIP)."""

    kind = "bad_sonar_count"


def checksum(body: bytes) -> int:
    """Return the ARCOS checksum of `body` (ID byte through last argument byte)."""
    total = 0
    n = len(body)
    for i in range(0, n - 1, 2):
        total = (total + ((body[i] << 8) | body[i + 1])) & 0xFFFF
    if n % 2:
        total ^= body[-1]
    return total


def frame(body: bytes) -> bytes:
    """Wrap `body` (ID byte + arguments) into a complete packet with header, count and checksum."""
    if not body:
        raise ProtocolError("packet body is empty; expected at least the ID byte")
    count = len(body) + 2
    if count > MAX_COUNT:
        raise ProtocolError(f"packet body of {len(body)} bytes is too long; expected <= {MAX_COUNT - 2}")
    return HEADER + bytes([count]) + body + struct.pack(">H", checksum(body))


def int_arg(value: int) -> bytes:
    """Encode a signed integer argument (`0x3B` + little-endian value or `0x1B` + magnitude)."""
    value = int(value)
    if not -0xFFFF <= value <= 0xFFFF:
        raise ProtocolError(f"integer argument {value} out of range; expected -65535..65535")
    if value >= 0:
        return bytes([ARG_INT]) + struct.pack("<H", value)
    return bytes([ARG_NINT]) + struct.pack("<H", -value)


def str_arg(text: bytes | str) -> bytes:
    """Encode a string argument (`0x2B`, length byte, characters, NUL)."""
    data = text.encode("latin-1") if isinstance(text, str) else bytes(text)
    if len(data) > 200:
        raise ProtocolError(f"string argument of {len(data)} bytes too long; expected <= 200")
    return bytes([ARG_STR, len(data)]) + data + b"\x00"


def encode_command(cmd: int, arg: int | bytes | str | None = None) -> bytes:
    """Return the packet for command `cmd` with no argument, an integer or a string argument."""
    if not 0 <= int(cmd) <= 255:
        raise ProtocolError(f"command number {cmd} out of range; expected 0..255")
    if arg is None:
        body = bytes([int(cmd)])
    elif isinstance(arg, (bytes, str)):
        body = bytes([int(cmd)]) + str_arg(arg)
    else:
        body = bytes([int(cmd)]) + int_arg(arg)
    return frame(body)


def encode_ints(cmd: int, *values: int) -> bytes:
    """Return a packet carrying several typed integer arguments."""
    return frame(bytes([int(cmd)]) + b"".join(int_arg(v) for v in values))


def encode_sim_set_pose(x_mm: int, y_mm: int, th_deg: int) -> bytes:
    """SIM_SET_POSE as MobileSim, AMRISim and ARIA's ArSimUtil put it on the wire.

    One argument-type byte (0, ignored by the simulators) and three signed 32-bit little-endian
    integers: x (mm), y (mm), heading (deg). The simulator moves the robot's true pose there;
    its odometry is left alone.
    """
    for label, value in (("x", x_mm), ("y", y_mm), ("heading", th_deg)):
        if not -0x80000000 <= int(value) <= 0x7FFFFFFF:
            raise ProtocolError(f"SIM_SET_POSE {label} {value} out of range; expected a 32-bit integer")
    return frame(bytes([Cmd.SIM_SET_POSE, 0]) + struct.pack("<iii", int(x_mm), int(y_mm), int(th_deg)))


def decode_sim_set_pose(body: bytes) -> tuple[int, int, int]:
    """The (x mm, y mm, heading deg) of a SIM_SET_POSE body; raise ProtocolError if it is short."""
    if len(body) < 14 or body[0] != Cmd.SIM_SET_POSE:
        raise ProtocolError(f"SIM_SET_POSE body of {len(body)} bytes; expected the ID, a type byte and 12 bytes")
    x, y, th = struct.unpack_from("<iii", body, 2)
    return x, y, th


def decode_args(body: bytes) -> list[int | bytes]:
    """Decode the typed arguments after the ID byte; raise ProtocolError on a malformed one."""
    args: list[int | bytes] = []
    i = 1
    while i < len(body):
        kind = body[i]
        if kind in (ARG_INT, ARG_NINT):
            if i + 3 > len(body):
                raise ProtocolError(f"integer argument truncated at byte {i}")
            value = body[i + 1] | (body[i + 2] << 8)
            args.append(value if kind == ARG_INT else -value)
            i += 3
        elif kind == ARG_STR:
            if i + 2 > len(body) or i + 2 + body[i + 1] > len(body):
                raise ProtocolError(f"string argument truncated at byte {i}")
            n = body[i + 1]
            args.append(bytes(body[i + 2:i + 2 + n]))
            i += 2 + n
            if i < len(body) and body[i] == 0:
                i += 1
        else:
            raise ProtocolError(f"unknown argument type 0x{kind:02X} at byte {i}; expected 0x3B, 0x1B or 0x2B")
    return args


@dataclass
class ReaderStats:
    """What a PacketReader has seen: good packets and everything it skipped."""

    packets: int = 0
    bytes_skipped: int = 0
    bad_checksum: int = 0
    bad_count: int = 0

    @property
    def errors(self) -> int:
        """Packets or bytes that had to be dropped."""
        return self.bad_checksum + self.bad_count + (1 if self.bytes_skipped else 0)


class PacketReader:
    """Turns a byte stream into packet bodies (ID + args); skips and counts anything malformed."""

    def __init__(self) -> None:
        self._buf = bytearray()
        self.stats = ReaderStats()

    def feed(self, data: bytes) -> list[bytes]:
        """Add bytes from the wire; return every complete, checksum-valid packet body found."""
        self._buf += data
        out: list[bytes] = []
        buf = self._buf
        while True:
            start = buf.find(HEADER)
            if start < 0:
                keep = 1 if buf[-1:] == b"\xfa" else 0
                self.stats.bytes_skipped += len(buf) - keep
                del buf[:len(buf) - keep]
                break
            if start:
                self.stats.bytes_skipped += start
                del buf[:start]
            if len(buf) < 3:
                break
            count = buf[2]
            if count < 3 or count > MAX_COUNT:
                self.stats.bad_count += 1
                del buf[:2]  # resynchronise on the next header
                continue
            if len(buf) < 3 + count:
                break
            body = bytes(buf[3:1 + count])
            (check,) = struct.unpack(">H", buf[1 + count:3 + count])
            if checksum(body) != check:
                self.stats.bad_checksum += 1
                del buf[:2]  # a header inside the bad packet may start a good one
                continue
            del buf[:3 + count]
            self.stats.packets += 1
            out.append(body)
        return out

    def reset(self) -> None:
        """Drop any partial packet (after a reconnect)."""
        self._buf.clear()


@dataclass
class RawSip:
    """A decoded standard SIP in wire units (before conversion factors)."""

    moving: bool
    xpos: int
    ypos: int
    thpos: int
    lvel: int
    rvel: int
    battery: int
    stall_bumpers: int
    control: int
    flags: int
    compass: int
    sonar: dict[int, int] = field(default_factory=dict)
    grip: int | None = None
    anport: int | None = None
    analog: int | None = None
    digin: int | None = None
    digout: int | None = None
    battery_x10: int | None = None
    charge_stage: int | None = None
    rotvel: int | None = None
    fault_flags: int | None = None
    lat_vel: int | None = None
    temperature: int | None = None
    state_of_charge: int | None = None

    @property
    def stall_left(self) -> bool:
        """Left wheel stalled (bit 0)."""
        return bool(self.stall_bumpers & 0x0001)

    @property
    def stall_right(self) -> bool:
        """Right wheel stalled (bit 8)."""
        return bool(self.stall_bumpers & 0x0100)

    @property
    def bumpers(self) -> int:
        """Front bumpers in bits 0-6, rear bumpers in bits 7-13."""
        return ((self.stall_bumpers >> 1) & 0x7F) | (((self.stall_bumpers >> 9) & 0x7F) << 7)

    @property
    def motors_enabled(self) -> bool:
        """Motors are enabled (FLAGS bit 0)."""
        return bool(self.flags & 0x0001)


_SIP_HEAD = struct.Struct("<HHhhhBHhHB")  # xpos ypos thpos lvel rvel battery stallbump control flags compass
_TAIL = [("grip", "B"), ("anport", "B"), ("analog", "B"), ("digin", "B"), ("digout", "B"),
         ("battery_x10", "H"), ("charge_stage", "B"), ("rotvel", "h"), ("fault_flags", "H"), ("lat_vel", "h"),
         ("temperature", "b"), ("state_of_charge", "B")]


def is_sip(body: bytes) -> bool:
    """True for a standard SIP (ID 0x32 stopped or 0x33 moving)."""
    return bool(body) and body[0] in (SIP_STOPPED, SIP_MOVING)


def parse_sip(body: bytes) -> RawSip:
    """Decode a standard SIP body (ID byte first); raise ProtocolError if it is truncated."""
    if not is_sip(body):
        raise ProtocolError(f"packet ID 0x{body[0]:02X} is not a SIP; expected 0x32 or 0x33")
    need = 1 + _SIP_HEAD.size + 1
    if len(body) < need:
        raise TruncatedSip(f"SIP of {len(body)} bytes truncated; expected at least {need}")
    fields = _SIP_HEAD.unpack_from(body, 1)
    i = 1 + _SIP_HEAD.size
    count = body[i]
    i += 1
    if len(body) < i + 3 * count:
        raise BadSonarCount(f"SIP announces {count} sonar readings but only {(len(body) - i) // 3} fit")
    sonar = {}
    for _ in range(count):
        num, rng = struct.unpack_from("<BH", body, i)
        sonar[num] = rng
        i += 3
    xpos, ypos, thpos, lvel, rvel, battery, stall_bumpers, control, flags, compass = fields
    sip = RawSip(body[0] == SIP_MOVING, xpos, ypos, thpos, lvel, rvel, battery, stall_bumpers, control, flags,
                 compass, sonar=sonar)
    for name, fmt in _TAIL:
        size = struct.calcsize(fmt)
        if len(body) < i + size:
            break
        (value,) = struct.unpack_from("<" + fmt, body, i)
        setattr(sip, name, value)
        i += size
    return sip


def parse_sync2(body: bytes) -> tuple[str, str, str]:
    """Return (name, class, subclass) from a SYNC2 reply; missing strings are empty."""
    parts = bytes(body[1:]).split(b"\x00")
    names = [p.decode("latin-1", "replace") for p in parts[:3]]
    while len(names) < 3:
        names.append("")
    return names[0], names[1], names[2]


class _Cursor:
    """Reads the fields of a server packet in order; `None` once the packet has run out."""

    def __init__(self, body: bytes) -> None:
        self.body, self.i = body, 1

    def take(self, fmt: str) -> int | str | None:
        if fmt == "z":  # a NUL-terminated string
            if self.i >= len(self.body):
                return None
            end = self.body.find(b"\x00", self.i)
            end = len(self.body) if end < 0 else end
            text = bytes(self.body[self.i:end]).decode("latin-1")
            self.i = end + 1
            return text
        size = struct.calcsize(fmt)
        if self.i + size > len(self.body):
            return None
        (value,) = struct.unpack_from("<" + fmt, self.body, self.i)
        self.i += size
        return int(value)


CONFIG_FIELDS: tuple[tuple[str, str], ...] = (
    ("robot_class", "z"), ("subclass", "z"), ("serial", "z"), ("four_mots", "B"), ("rot_vel_top", "H"),
    ("trans_vel_top", "H"), ("rot_accel_top", "H"), ("trans_accel_top", "H"), ("pwm_max", "H"), ("name", "z"),
    ("sip_cycle", "B"), ("host_baud", "B"), ("aux1_baud", "B"), ("has_gripper", "H"), ("front_sonar", "H"),
    ("rear_sonar", "B"), ("low_battery", "H"), ("rev_count", "H"), ("watchdog", "H"), ("normal_mpacs", "B"),
    ("stall_val", "H"), ("stall_count", "H"), ("joy_vel", "H"), ("joy_rot_vel", "H"), ("rot_vel_max", "H"),
    ("trans_vel_max", "H"), ("rot_accel", "H"), ("rot_decel", "H"), ("rot_kp", "H"), ("rot_kv", "H"),
    ("rot_ki", "H"), ("trans_accel", "H"), ("trans_decel", "H"), ("trans_kp", "H"), ("trans_kv", "H"),
    ("trans_ki", "H"), ("front_bumps", "B"), ("rear_bumps", "B"), ("has_charger", "B"), ("sonar_cycle", "B"),
    ("autobaud", "B"), ("has_gyro", "B"), ("drift_factor", "h"), ("aux2_baud", "B"), ("aux3_baud", "B"),
    ("ticks_mm", "H"), ("shutdown_volts", "H"), ("firmware", "z"), ("gyro_cw", "H"), ("gyro_ccw", "H"),
    ("kinematics_delay", "B"), ("lat_vel_top", "H"), ("lat_accel_top", "H"), ("lat_vel_max", "H"),
    ("lat_accel", "H"), ("lat_decel", "H"), ("charge_threshold", "H"),
)
"""The CONFIG reply (ID 0x20) in wire order: strings NUL-terminated, integers little-endian, speeds in
mm/s and deg/s, accelerations in mm/s^2 and deg/s^2, SipCycle and Watchdog in ms, HostBaud a
HOSTBAUD code. Later firmware appends more; what a robot leaves off stays unknown."""


@dataclass
class RobotConfig:
    """A decoded CONFIG reply; fields the robot did not send are None."""

    robot_class: str | None = None
    subclass: str | None = None
    serial: str | None = None
    four_mots: int | None = None
    rot_vel_top: int | None = None
    trans_vel_top: int | None = None
    rot_accel_top: int | None = None
    trans_accel_top: int | None = None
    pwm_max: int | None = None
    name: str | None = None
    sip_cycle: int | None = None
    host_baud: int | None = None
    aux1_baud: int | None = None
    has_gripper: int | None = None
    front_sonar: int | None = None
    rear_sonar: int | None = None
    low_battery: int | None = None
    rev_count: int | None = None
    watchdog: int | None = None
    normal_mpacs: int | None = None
    stall_val: int | None = None
    stall_count: int | None = None
    joy_vel: int | None = None
    joy_rot_vel: int | None = None
    rot_vel_max: int | None = None
    trans_vel_max: int | None = None
    rot_accel: int | None = None
    rot_decel: int | None = None
    rot_kp: int | None = None
    rot_kv: int | None = None
    rot_ki: int | None = None
    trans_accel: int | None = None
    trans_decel: int | None = None
    trans_kp: int | None = None
    trans_kv: int | None = None
    trans_ki: int | None = None
    front_bumps: int | None = None
    rear_bumps: int | None = None
    has_charger: int | None = None
    sonar_cycle: int | None = None
    autobaud: int | None = None
    has_gyro: int | None = None
    drift_factor: int | None = None
    aux2_baud: int | None = None
    aux3_baud: int | None = None
    ticks_mm: int | None = None
    shutdown_volts: int | None = None
    firmware: str | None = None
    gyro_cw: int | None = None
    gyro_ccw: int | None = None
    kinematics_delay: int | None = None
    lat_vel_top: int | None = None
    lat_accel_top: int | None = None
    lat_vel_max: int | None = None
    lat_accel: int | None = None
    lat_decel: int | None = None
    charge_threshold: int | None = None

    @property
    def simulator(self) -> bool:
        """MobileSim, AMRISim and ERNI's simulator give the serial number `SIM`."""
        return self.serial == "SIM"

    @property
    def can_switch_baud(self) -> bool:
        """The firmware accepts HOSTBAUD (AutoBaud = 2)."""
        return self.autobaud == 2


def parse_config(body: bytes) -> RobotConfig:
    """Decode a CONFIG reply body (ID 0x20 first); raise ProtocolError if it is not one."""
    if not body or body[0] != CONFIG_REPLY:
        raise ProtocolError(f"packet ID 0x{body[0] if body else 0:02X} is not a CONFIG reply; expected 0x20")
    cursor = _Cursor(body)
    config = RobotConfig()
    for name, fmt in CONFIG_FIELDS:
        value = cursor.take(fmt)
        if value is None:
            break
        setattr(config, name, value)
    if config.robot_class is None or config.serial is None:
        raise ProtocolError(f"CONFIG reply of {len(body)} bytes truncated; expected at least class, subclass "
                            "and serial number")
    return config


@dataclass(frozen=True)
class SimStat:
    """A simulator's SIMSTAT reply (ID 0x62): the robot's true pose and the simulation's timing."""

    flags: int
    sim_interval: int  # ms of simulated time per update
    real_interval: int  # ms of real time per update
    last_interval: int  # ms the last update took
    x: int  # true pose: mm, mm, mm, deg
    y: int
    z: int
    th: int


def parse_simstat(body: bytes) -> SimStat:
    """Decode a SIMSTAT body: two (empty) strings, flags u32, three u16 intervals, x y z th i32."""
    if not body or body[0] != SIMSTAT_REPLY:
        raise ProtocolError(f"packet ID 0x{body[0] if body else 0:02X} is not SIMSTAT; expected 0x62")
    cursor = _Cursor(body)
    cursor.take("z")
    cursor.take("z")
    values = [cursor.take(f) for f in ("I", "H", "H", "H", "i", "i", "i", "i")]
    if any(v is None for v in values):
        raise ProtocolError(f"SIMSTAT of {len(body)} bytes truncated; expected flags, timing and the true pose")
    return SimStat(*(int(v) for v in values if v is not None))


@dataclass(frozen=True)
class BatteryInfo:
    """A BATTERYINFO reply (ID 0xFA): per battery, flag bytes and states of charge (%)."""

    batteries: tuple[tuple[int, ...], ...]

    @property
    def relative_soc(self) -> list[int]:
        """Relative state of charge (%) of each battery that reports one (the 4th byte)."""
        return [b[3] for b in self.batteries if len(b) > 3]


def parse_battery_info(body: bytes) -> BatteryInfo:
    """Decode a BATTERYINFO body: battery count, bytes per battery, then the bytes of each battery."""
    if len(body) < 3 or body[0] != BATTERY_REPLY:
        raise ProtocolError("not a BATTERYINFO reply; expected ID 0xFA, a count and a size")
    count, size = body[1], body[2]
    if len(body) < 3 + count * size:
        raise ProtocolError(f"BATTERYINFO announces {count} batteries of {size} bytes but has {len(body) - 3}")
    return BatteryInfo(tuple(tuple(body[3 + i * size:3 + (i + 1) * size]) for i in range(count)))
