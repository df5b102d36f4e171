"""Wire facts pinned as bytes, taken from the outside implementations (ARIA, AMRISim) rather than from us.

The client packets below were captured between ARIA (AriaCoda b0d02e0, its ArRobot and
ArSimUtil) and a robot; the server packets between AMRISim 0.9 (reedhedges/AMRISim 26e07b9,
`-r p3dx-sh`) and a client. The driver must write exactly what ARIA writes, the decoders must
read exactly what AMRISim sends, and the simulated firmware must answer as AMRISim does, so the
driver and ERNI's simulator can never agree with each other against the protocol.
"""

from __future__ import annotations

import struct

import pytest

from erni.plugins.motion import arcos
from erni.plugins.motion.arcos import Cmd, PacketReader
from erni.plugins.motion.driver import ArcosDriver
from erni.plugins.motion.robots import MODELS, model_spec
from erni.sim.robot import FIRMWARE, ArcosFirmware, SimRobot, SimRobotConfig
from tests.motion.conftest import sim_only_because

# --- what ARIA writes ---------------------------------------------------------------------

ARIA_SIM_SET_POSE = "FA FB 10 E0 00 D0 07 00 00 18 FC FF FF 5A 00 00 00 23 02"
"""ArSimUtil::setSimTruePose(ArPose(2000, -1000, 90)): type byte 0, then x, y, th as int32 little-endian."""

ARIA_AMIGO = [  # ArRobot on an AmigoBot (subtype amigo: DistConv 0.5083, VelConv 0.6154): nothing is scaled
    ("setVel(300)", Cmd.VEL, 300, "FA FB 06 0B 3B 2C 01 37 3C"),
    ("move(1000)", Cmd.MOVE, 1000, "FA FB 06 08 3B E8 03 F0 3E"),
    ("SETV 1000", Cmd.SETV, 1000, "FA FB 06 06 3B E8 03 EE 3E"),
    ("SETA -1000 (decel)", Cmd.SETA, -1000, "FA FB 06 05 1B E8 03 ED 1E"),
]
ARIA_REQUESTS = [  # sent by ArRobot and ArSimUtil while connecting
    ("CONFIG 1", Cmd.CONFIG, 1, "FA FB 06 12 3B 01 00 13 3B"),
    ("BATTERYINFO 1", Cmd.BATTERYINFO, 1, "FA FB 06 3E 3B 01 00 3F 3B"),
    ("SIM_STAT 2", Cmd.SIM_STAT, 2, "FA FB 06 ED 3B 02 00 EF 3B"),
    ("HOSTBAUD 2 (38400)", Cmd.HOSTBAUD, 2, "FA FB 06 32 3B 02 00 34 3B"),
]


def test_sim_set_pose_is_one_type_byte_and_three_little_endian_int32():
    assert arcos.encode_sim_set_pose(2000, -1000, 90) == bytes.fromhex(ARIA_SIM_SET_POSE)
    (body,) = PacketReader().feed(bytes.fromhex(ARIA_SIM_SET_POSE))
    assert arcos.decode_sim_set_pose(body) == (2000, -1000, 90)
    far = arcos.encode_sim_set_pose(-400881712, 70000, -450)  # beyond 16 bits: still exact
    assert arcos.decode_sim_set_pose(PacketReader().feed(far)[0]) == (-400881712, 70000, -450)
    with pytest.raises(arcos.ProtocolError, match="32-bit"):
        arcos.encode_sim_set_pose(2**31, 0, 0)


@pytest.mark.parametrize("label,cmd,arg,wire", ARIA_AMIGO + ARIA_REQUESTS, ids=[v[0] for v in ARIA_AMIGO + ARIA_REQUESTS])
def test_commands_encode_as_aria_sends_them(label, cmd, arg, wire):
    assert arcos.encode_command(cmd, arg) == bytes.fromhex(wire)


class _Recorder:
    """Stands in for the serial port of a connected driver and keeps what it is given."""

    def __init__(self) -> None:
        self.data = bytearray()

    def write(self, data: bytes) -> int:
        self.data += data
        return len(data)


def _connected(model: str) -> tuple[ArcosDriver, _Recorder]:
    driver = ArcosDriver("loop://", model, name="wire")
    port = _Recorder()
    driver._port, driver._connected = port, True  # type: ignore[assignment]  # bytes only, no robot
    return driver, port


@pytest.mark.parametrize("model", ["amigo", "p3dx", "p2at", "p3dx-sh"])
def test_the_driver_writes_the_same_bytes_as_aria_whatever_the_conversion_factors(model):
    driver, port = _connected(model)
    assert driver.model.dist_conv == MODELS[model].dist_conv
    driver.vel(0.3)
    driver.move(1.0)
    driver.setv(1.0)
    driver.seta(-1.0)
    driver.sim_set_pose(2.0, -1.0, 90)
    wire = b"".join(bytes.fromhex(w) for *_, w in ARIA_AMIGO) + bytes.fromhex(ARIA_SIM_SET_POSE)
    assert bytes(port.data).startswith(wire)
    assert bytes(port.data[len(wire):]) == arcos.encode_command(Cmd.SIM_STAT, 1)  # then ask where it went


def test_vel2_is_in_vel2_divisor_units_only():
    driver, port = _connected("amigo")
    driver.vel2(-0.2, 0.4)  # left -10, right +20 units of 20 mm/s: high byte left, low byte right
    assert bytes(port.data) == arcos.encode_command(Cmd.VEL2, ((-10 & 0xFF) << 8 | 20) - 0x10000)


# --- what the robot sends -----------------------------------------------------------------

AMRISIM_SYNC2 = (
    "FA FB 1B 02 41 4D 52 49 53 69 6D 00 50 69 6F 6E 65 65 72 00 70 33 64 78 2D 73 68 00 5F 52")
AMRISIM_SIP = (  # a robot standing at the origin, motors on, all 16 sonar at 5 m, then the long tail
    "FA FB 56 32 00 00 00 00 00 00 00 00 00 00 82 00 00 00 00 1F 00 00 10 00 88 13 01 88 13 02 88 13 03 88 13 04 "
    "88 13 05 88 13 06 88 13 07 88 13 08 88 13 09 88 13 0A 88 13 0B 88 13 0C 88 13 0D 88 13 0E 88 13 0F 88 13 00 "
    "00 00 FF FF 82 00 00 00 00 00 00 00 00 81 00 E8 2B")
AMRISIM_CONFIG = (
    "FA FB 7C 20 50 69 6F 6E 65 65 72 00 70 33 64 78 2D 73 68 00 53 49 4D 00 00 0F 27 0F 27 0F 27 0F 27 90 01 41 "
    "4D 52 49 53 69 6D 00 64 00 00 00 00 01 00 01 00 00 00 00 D0 07 00 00 00 00 00 00 00 00 00 96 00 B8 0B 64 00 "
    "64 00 00 00 00 00 00 00 2C 01 2C 01 00 00 00 00 00 00 00 00 00 00 02 00 00 00 00 00 00 00 00 00 53 2E 30 00 "
    "00 00 00 00 00 0F 27 0F 27 00 00 00 00 00 00 00 00 77 85")
AMRISIM_SIMSTAT = (  # true pose (0, 0, 0), odometry error simulated (flag bit 2) with its three error terms
    "FA FB 3B 62 00 00 04 00 00 00 64 00 64 00 65 00 00 00 00 00 00 00 00 00 00 00 00 00 00 00 00 00 00 00 00 00 "
    "00 00 00 00 00 00 00 00 FF FF FF FF ED 41 08 04 5E 5F 59 FC 2A 69 FF FF 6F FB")


def _one(wire: str) -> bytes:
    (body,) = PacketReader().feed(bytes.fromhex(wire))
    return body


def test_amrisims_sync2_names_a_real_subtype():
    assert arcos.parse_sync2(_one(AMRISIM_SYNC2)) == ("AMRISim", "Pioneer", "p3dx-sh")
    assert model_spec("auto").resolve("p3dx-sh")[0] is MODELS["p3dx-sh"]


def test_amrisims_sip_decodes():
    sip = arcos.parse_sip(_one(AMRISIM_SIP))
    assert not sip.moving and (sip.xpos, sip.ypos, sip.thpos, sip.lvel, sip.rvel) == (0, 0, 0, 0, 0)
    assert sip.battery == 130 and sip.motors_enabled and sip.flags == 0x1F
    assert sip.sonar == {i: 5000 for i in range(16)}
    assert (sip.digin, sip.digout, sip.battery_x10, sip.rotvel, sip.fault_flags) == (0xFF, 0xFF, 130, 0, 0)
    assert (sip.lat_vel, sip.temperature, sip.state_of_charge) == (0, -127, 0)


def test_amrisims_config_reply_decodes_field_by_field():
    cfg = arcos.parse_config(_one(AMRISIM_CONFIG))
    assert (cfg.robot_class, cfg.subclass, cfg.serial, cfg.name, cfg.firmware) == (
        "Pioneer", "p3dx-sh", "SIM", "AMRISim", "S.0")
    assert (cfg.rot_vel_top, cfg.trans_vel_top, cfg.rot_accel_top, cfg.trans_accel_top) == (9999,) * 4
    assert (cfg.rot_vel_max, cfg.trans_vel_max, cfg.rot_accel, cfg.rot_decel) == (150, 3000, 100, 100)
    assert (cfg.trans_accel, cfg.trans_decel, cfg.sip_cycle, cfg.watchdog) == (300, 300, 100, 2000)
    assert (cfg.front_sonar, cfg.rear_sonar, cfg.autobaud, cfg.lat_vel_top, cfg.charge_threshold) == (1, 1, 2, 9999, 0)
    assert cfg.simulator and cfg.can_switch_baud


def test_amrisims_simstat_decodes():
    stat = arcos.parse_simstat(_one(AMRISIM_SIMSTAT))
    assert stat.flags == 0x04 and (stat.sim_interval, stat.real_interval, stat.last_interval) == (100, 100, 101)
    assert (stat.x, stat.y, stat.z, stat.th) == (0, 0, 0, 0)


@sim_only_because("compares the simulated firmware with AMRISim")
def test_the_simulators_replies_have_amrisims_layout():
    fw, reader = _session(SimRobotConfig(name="AMRISim", sonar_cycle=0))
    fw.receive(arcos.encode_command(Cmd.CONFIG, 1) + arcos.encode_command(Cmd.SIM_STAT, 1), 0.0)
    fw.tick(1.0)
    ours = {b[0]: b for b in reader.feed(fw.take_output())}
    theirs = {b[0]: b for b in (_one(AMRISIM_CONFIG), _one(AMRISIM_SIMSTAT), _one(AMRISIM_SIP))}
    assert len(ours[0x62]) == len(theirs[0x62]) and ours[0x62][:3] == theirs[0x62][:3]
    # the same fields one after the other: only the firmware strings differ in length
    assert len(ours[0x20]) - len(FIRMWARE) == len(theirs[0x20]) - len("S.0")
    assert ours[0x20][1:21] == theirs[0x20][1:21]  # class, subtype, serial number
    assert ours[0x32][:13] == theirs[0x32][:13]  # a robot standing at the origin reads the same
    assert len(ours[0x32]) == len(theirs[0x32])


def _sync2(name: str, cls: str, sub: str) -> bytes:
    return arcos.frame(b"\x02" + name.encode() + b"\x00" + cls.encode() + b"\x00" + sub.encode() + b"\x00")


@sim_only_because("checks the simulated firmware's replies")
@pytest.mark.parametrize("model", sorted(MODELS))
def test_the_simulator_names_each_model_by_the_subtype_aria_knows(model):
    robot = SimRobot(SimRobotConfig.for_model(model, name="robot1"))
    fw = ArcosFirmware(robot)
    for sync in (0, 1, 2):
        fw.receive(arcos.encode_command(sync), 0.0)
    replies = fw.take_output()
    assert replies.endswith(_sync2("robot1", "Pioneer", model))  # never a made-up "-sim" subtype
    spec_model, warnings = model_spec("auto").resolve(model)
    assert spec_model is MODELS[model] and warnings == []


def test_sync2_bytes_of_a_p3dx_sh():
    assert _sync2("robot1", "Pioneer", "p3dx-sh").hex(" ").upper() == (
        "FA FB 1A 02 72 6F 62 6F 74 31 00 50 69 6F 6E 65 65 72 00 70 33 64 78 2D 73 68 00 13 A2")


def _session(config: SimRobotConfig) -> tuple[ArcosFirmware, PacketReader]:
    fw = ArcosFirmware(SimRobot(config))
    for sync in (0, 1, 2):
        fw.receive(arcos.encode_command(sync), 0.0)
    fw.receive(arcos.encode_command(Cmd.OPEN), 0.0)
    reader = PacketReader()
    reader.feed(fw.take_output())
    return fw, reader


@sim_only_because("checks the simulated firmware's replies")
def test_the_simulators_config_reply_reads_as_aria_reads_it():
    fw, reader = _session(SimRobotConfig.for_model("amigo", name="robot1", max_v=0.75, accel=0.4, decel=0.6))
    fw.receive(bytes.fromhex(ARIA_REQUESTS[0][3]), 0.0)
    (body,) = reader.feed(fw.take_output())
    assert body[:1] == b"\x20"
    assert body[1:30] == b"Pioneer\x00amigo\x00SIM\x00\x00" + struct.pack("<HHHHH", 300, 1000, 500, 2000, 500)
    cfg = arcos.parse_config(body)
    assert (cfg.robot_class, cfg.subclass, cfg.serial, cfg.name) == ("Pioneer", "amigo", "SIM", "robot1")
    assert (cfg.trans_vel_top, cfg.rot_vel_top, cfg.trans_vel_max) == (1000, 300, 750)
    assert (cfg.trans_accel, cfg.trans_decel, cfg.sip_cycle, cfg.watchdog, cfg.autobaud) == (400, 600, 100, 2000, 2)
    assert cfg.simulator and cfg.can_switch_baud and cfg.firmware == "ERNI-S1.0" and cfg.charge_threshold == 0


@sim_only_because("checks the simulated firmware's replies")
def test_the_simulators_simstat_and_battery_replies():
    fw, reader = _session(SimRobotConfig(sip_period=0.1))
    fw.receive(bytes.fromhex(ARIA_SIM_SET_POSE), 0.1)
    fw.receive(arcos.encode_command(Cmd.SIM_STAT, 1), 0.1)
    (body,) = reader.feed(fw.take_output())
    assert body[:3] == b"\x62\x00\x00" and len(body) == 3 + 4 + 6 + 16 + 16 + 12
    stat = arcos.parse_simstat(body)
    assert (stat.x, stat.y, stat.z, stat.th) == (2000, -1000, 0, 90) and stat.sim_interval == 100
    fw.receive(arcos.encode_command(Cmd.BATTERYINFO, 1), 0.2)
    (body,) = reader.feed(fw.take_output())
    assert body == bytes([0xFA, 1, 5, 0, 0, 0, 100, 100])
    assert arcos.parse_battery_info(body).relative_soc == [100]
    fw.receive(arcos.encode_command(Cmd.SIM_STAT, 2), 0.2)  # continuous: one after every SIP
    fw.tick(0.3)
    kinds = [b[0] for b in reader.feed(fw.take_output())]
    assert kinds == [0x32, 0x62]


def test_truncated_server_packets_are_refused_clearly():
    with pytest.raises(arcos.ProtocolError, match="not a CONFIG reply"):
        arcos.parse_config(b"\x32\x00")
    with pytest.raises(arcos.ProtocolError, match="truncated"):
        arcos.parse_config(b"\x20Pioneer\x00")
    with pytest.raises(arcos.ProtocolError, match="SIMSTAT of 9 bytes truncated"):
        arcos.parse_simstat(b"\x62\x00\x00" + bytes(6))
    with pytest.raises(arcos.ProtocolError, match="announces 2 batteries"):
        arcos.parse_battery_info(bytes([0xFA, 2, 5, 1, 2, 3]))
    short = arcos.parse_config(b"\x20Pioneer\x00p3dx\x00SIM\x00")  # old firmware stops early: the rest is unknown
    assert short.serial == "SIM" and short.rot_vel_top is None and short.firmware is None
