"""ARCOS framing: the reference test vectors, argument coding, SIP decoding, line noise."""

from __future__ import annotations

import math
import struct

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from erni.plugins.motion import arcos
from erni.plugins.motion.arcos import Cmd, PacketReader
from erni.sim.robot import ArcosFirmware, SimRobot, SimRobotConfig
from erni.sim.world import World
from tests.motion.conftest import sim_only_because

on_sim_sips = sim_only_because("decodes SIPs made by ERNI's simulated firmware")

VECTORS = [  # /work/shared/reference/arcos.md, "Test vectors"
    ("SYNC0", Cmd.SYNC0, None, "FA FB 03 00 00 00"),
    ("SYNC1", Cmd.SYNC1, None, "FA FB 03 01 00 01"),
    ("SYNC2", Cmd.SYNC2, None, "FA FB 03 02 00 02"),
    ("OPEN 1", Cmd.OPEN, 1, "FA FB 06 01 3B 01 00 02 3B"),
    ("ENABLE 1", Cmd.ENABLE, 1, "FA FB 06 04 3B 01 00 05 3B"),
    ("VEL 200", Cmd.VEL, 200, "FA FB 06 0B 3B C8 00 D3 3B"),
    ("VEL -200", Cmd.VEL, -200, "FA FB 06 0B 1B C8 00 D3 1B"),
    ("RVEL 30", Cmd.RVEL, 30, "FA FB 06 15 3B 1E 00 33 3B"),
    ("ESTOP", Cmd.ESTOP, None, "FA FB 03 37 00 37"),
]


@pytest.mark.parametrize("label,cmd,arg,wire", VECTORS, ids=[v[0] for v in VECTORS])
def test_reference_vectors_encode_exactly(label, cmd, arg, wire):
    assert arcos.encode_command(cmd, arg) == bytes.fromhex(wire)


@pytest.mark.parametrize("label,cmd,arg,wire", VECTORS, ids=[v[0] for v in VECTORS])
def test_reference_vectors_decode_back(label, cmd, arg, wire):
    (body,) = PacketReader().feed(bytes.fromhex(wire))
    assert body[0] == cmd
    assert arcos.decode_args(body) == ([] if arg is None else [arg])


def test_checksum_odd_length_xors_the_last_byte():
    assert arcos.checksum(b"\x01\x02\x03") == (0x0102 ^ 0x03)
    assert arcos.checksum(b"\xff\xff\xff\xff\x01") == ((0xFFFF + 0xFFFF) & 0xFFFF) ^ 0x01


def test_string_argument_and_multiple_ints():
    pkt = arcos.encode_command(Cmd.SAY, b"\x14\x3c\x14\x40")
    (body,) = PacketReader().feed(pkt)
    assert arcos.decode_args(body) == [b"\x14\x3c\x14\x40"]
    (body,) = PacketReader().feed(arcos.encode_ints(Cmd.SIM_SET_POSE, 1500, -2500, 90))
    assert arcos.decode_args(body) == [1500, -2500, 90]


def test_bad_arguments_are_refused_with_a_clear_message():
    with pytest.raises(arcos.ProtocolError, match="out of range"):
        arcos.encode_command(Cmd.VEL, 70000)
    with pytest.raises(arcos.ProtocolError, match="unknown argument type 0x99"):
        arcos.decode_args(b"\x0b\x99\x00")
    with pytest.raises(arcos.ProtocolError, match="expected 0x32 or 0x33"):
        arcos.parse_sip(b"\x20\x00")


def _robot(**state: float) -> SimRobot:
    world = World(wall=[{"a": (1.0, -3.0), "b": (1.0, 3.0)}])
    robot = SimRobot(SimRobotConfig(sonar_cycle=0), world)  # every reading in every SIP
    for k, v in state.items():
        setattr(robot, k, v)
    return robot


@on_sim_sips
@settings(max_examples=60, deadline=None)
@given(x=st.floats(-16.0, 16.0), y=st.floats(-16.0, 16.0), th=st.floats(-3.14, 3.14),
       v=st.floats(-1.5, 1.5), w=st.floats(-3.0, 3.0), energy=st.floats(0, 300000))
def test_simulator_sip_decodes_to_the_robot_state(x, y, th, v, w, energy):
    robot = _robot(x=x, y=y, th=th, v=v, w=w, energy=energy)
    robot.motors_enabled = True
    sip = arcos.parse_sip(ArcosFirmware(robot).sip())
    units = lambda raw: raw - 0x8000 if raw >= 0x4000 else raw  # noqa: E731
    assert units(sip.xpos) == pytest.approx(x * 1000, abs=1)
    assert units(sip.ypos) == pytest.approx(y * 1000, abs=1)
    assert math.remainder(sip.thpos * 0.001534 - th, 2 * math.pi) == pytest.approx(0, abs=0.003)
    assert (sip.lvel + sip.rvel) / 2000 == pytest.approx(v, abs=0.002)
    assert sip.battery_x10 == round(robot.battery * 10)
    assert sip.rotvel == pytest.approx(math.degrees(w) * 10, abs=1)
    assert sip.motors_enabled and sip.moving == robot.moving
    assert len(sip.sonar) == 16


@on_sim_sips
def test_sonar_readings_see_the_wall_from_the_transducers():
    robot = _robot(x=0.0, y=0.0, th=0.0)
    sip = arcos.parse_sip(ArcosFirmware(robot).sip())
    ahead = [sip.sonar[i] for i in (3, 4)]
    # the nearest echo within the beam (+-0.13 rad) of the +-10 degree front transducers, 166 mm ahead
    assert all(r == pytest.approx((1000 - 166) / math.cos(math.radians(10) - 0.13), abs=1) for r in ahead)
    assert sip.sonar[0] == 5000 and sip.sonar[10] == 5000  # side and rear: nothing within range


@on_sim_sips
def test_sip_without_the_optional_tail_and_truncated_sips():
    full = ArcosFirmware(_robot()).sip()
    head_len = 1 + 18 + 1 + 16 * 3
    assert len(full) == head_len + 5 + 2 + 1 + 2 + 2 + 2 + 1 + 1  # ... rotvel, faults, latvel, temperature, charge
    short = arcos.parse_sip(full[:head_len])
    assert short.battery_x10 is None and short.rotvel is None and len(short.sonar) == 16
    partial = arcos.parse_sip(full[:head_len + 6])  # grip..digout and half of nothing more
    assert partial.grip == 0 and partial.battery_x10 is None
    whole = arcos.parse_sip(full)
    assert whole.temperature == -127 and whole.state_of_charge == 100 and whole.lat_vel == 0
    with pytest.raises(arcos.ProtocolError, match="sonar readings"):
        arcos.parse_sip(full[:head_len - 2])
    with pytest.raises(arcos.ProtocolError, match="truncated"):
        arcos.parse_sip(full[:10])


def test_stall_and_bumper_bits():
    sip = arcos.RawSip(False, 0, 0, 0, 0, 0, 120, 0x0001 | 0x0100 | (0b101 << 1) | (0b11 << 9), 0, 1, 0)
    assert sip.stall_left and sip.stall_right
    assert sip.bumpers == 0b101 | (0b11 << 7)


# --- line noise: skipped and counted, never a crash --------------------------------------

packets = st.lists(
    st.tuples(st.integers(0, 255), st.one_of(st.none(), st.integers(-0xFFFF, 0xFFFF))), min_size=1, max_size=12)
noise = st.binary(max_size=40).map(lambda b: bytes(c for c in b if c != 0xFA))


@settings(max_examples=200, deadline=None)
@given(items=packets, junk=st.lists(noise, min_size=13, max_size=13), splits=st.lists(st.integers(1, 50)))
def test_every_packet_survives_noise_between_packets(items, junk, splits):
    wire = bytearray()
    for (cmd, arg), j in zip(items, junk):
        wire += j + arcos.encode_command(cmd, arg)
    reader = PacketReader()
    got = []
    pos = 0
    for n in splits + [len(wire)]:  # arbitrary chunking of the stream
        got += reader.feed(bytes(wire[pos:pos + n]))
        pos += n
    assert [b[0] for b in got] == [cmd for cmd, _ in items]
    assert [arcos.decode_args(b) for b in got] == [[] if a is None else [a] for _, a in items]
    assert reader.stats.packets == len(items)
    assert reader.stats.bytes_skipped == sum(len(j) for j in junk[:len(items)])


@settings(max_examples=200, deadline=None)
@given(items=packets, damage=st.lists(st.tuples(st.integers(0, 2), st.integers(0, 1000)), min_size=12, max_size=12))
def test_bad_checksums_and_truncated_packets_are_dropped_and_counted(items, damage):
    wire = bytearray()
    required = []  # good packets right after a good one: nothing damaged can swallow them
    previous_ok = True
    for (cmd, arg), (kind, where) in zip(items, damage):
        pkt = bytearray(arcos.encode_command(cmd, arg))
        if kind == 1:
            pkt[-1] ^= 0x01  # bad checksum
        elif kind == 2:
            pkt = pkt[:3 + where % (len(pkt) - 3)]  # truncated: cut after the count byte
        elif previous_ok:
            required.append(bytes(pkt[3:-2]))
        previous_ok = kind == 0
        wire += pkt
    reader = PacketReader()
    got = reader.feed(bytes(wire) + arcos.encode_command(Cmd.ESTOP) * 50)  # filler ends any open frame
    rest = iter(got)
    assert all(any(body == want for body in rest) for want in required)  # in order, none lost
    assert got[-1] == bytes([Cmd.ESTOP]) and reader.stats.packets == len(got)
    damaged = sum(1 for _, (kind, _) in zip(items, damage) if kind)
    if damaged:
        assert reader.stats.bad_checksum + reader.stats.bad_count + reader.stats.bytes_skipped > 0


@settings(max_examples=300, deadline=None)
@given(data=st.binary(max_size=600))
def test_arbitrary_bytes_never_crash_and_every_packet_returned_is_valid(data):
    reader = PacketReader()
    for body in reader.feed(data) + reader.feed(bytes(300)):
        assert 1 <= len(body) <= arcos.MAX_COUNT - 2
        if arcos.is_sip(body):
            try:
                arcos.parse_sip(body)
            except arcos.ProtocolError:
                pass
        try:
            arcos.decode_args(body)
        except arcos.ProtocolError:
            pass


def test_sip_struct_layout_is_little_endian():
    body = struct.pack("<BHHhhhBHhHB", 0x32, 0x7FFF, 1, -1, -200, 300, 125, 0, 0, 1, 90) + b"\x00"
    sip = arcos.parse_sip(body)
    assert (sip.xpos, sip.ypos, sip.thpos, sip.lvel, sip.rvel, sip.battery) == (0x7FFF, 1, -1, -200, 300, 125)
    assert sip.compass == 90 and sip.sonar == {}
