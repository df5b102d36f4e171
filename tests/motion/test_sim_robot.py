"""The simulated robot on an injected clock: limits, controllers, watchdog, bumps, battery, firmware."""

from __future__ import annotations

import logging
import math
import socket

import pytest

from erni.blackboard.testing import wait_until
from erni.plugins.motion import arcos
from erni.plugins.motion.arcos import Cmd, PacketReader
from erni.sim.robot import P0_WATTS, ArcosFirmware, SimRobot, SimRobotConfig
from erni.sim.robot_host import RobotHost
from erni.sim.world import World
from tests.motion.conftest import sim_only_because

pytestmark = sim_only_because("tests ERNI's simulator itself")


def run(robot: SimRobot, seconds: float, dt: float = 0.01, t0: float = 0.0, feed: bool = True) -> float:
    """Step the robot for `seconds` on a synthetic clock; feed the watchdog unless told not to."""
    t = t0
    for _ in range(round(seconds / dt)):
        t += dt
        if feed:
            robot.touch(t)
        robot.step(dt, t)
    return t


def make(**kw: object) -> SimRobot:
    robot = SimRobot(SimRobotConfig(**kw), World())  # type: ignore[arg-type]
    robot.motors_enabled = True
    return robot


def test_velocity_is_reached_through_the_acceleration_limit():
    robot = make(accel=0.5, decel=1.0, max_v=1.0)
    robot.set_velocity(0.4)
    run(robot, 0.4)
    assert robot.v == pytest.approx(0.2, abs=0.01)  # 0.5 m/s^2 for 0.4 s
    run(robot, 1.0)
    assert robot.v == pytest.approx(0.4)
    robot.set_velocity(5.0)
    run(robot, 3.0)
    assert robot.v == pytest.approx(1.0)  # capped by max_v
    robot.stop()
    run(robot, 0.5)
    assert robot.v == pytest.approx(0.5, abs=0.01)  # decelerating at 1 m/s^2


def test_straight_and_arc_motion_integrate_exactly():
    robot = make(accel=100, decel=100)
    robot.set_velocity(0.5)
    run(robot, 2.0, dt=0.001)
    assert (robot.x, robot.y) == pytest.approx((1.0, 0.0), abs=0.005)
    robot.set_pose(0, 0, 0)
    robot.set_velocity(0.5)
    robot.set_rotation(math.radians(90))
    robot.rot_accel = robot.accel = 1e6
    run(robot, 1.0, dt=0.001)  # a quarter circle of radius 0.5/(pi/2)
    r = 0.5 / (math.pi / 2)
    assert (robot.x, robot.y, robot.th) == pytest.approx((r, r, math.pi / 2), abs=0.01)


def test_move_and_head_controllers_stop_on_target():
    robot = make(accel=1.0, decel=1.0)
    robot.move(0.75)
    run(robot, 4.0)
    assert robot.x == pytest.approx(0.75, abs=0.01) and robot.v == 0
    robot.set_heading(math.radians(-120))
    run(robot, 3.0)
    assert math.degrees(robot.th) == pytest.approx(-120, abs=1.0) and robot.w == 0


def test_watchdog_stops_a_robot_without_traffic_and_traffic_resumes_it():
    robot = make(watchdog=0.5, accel=10, decel=10)
    robot.set_velocity(0.3)
    t = run(robot, 0.3)
    assert robot.v == pytest.approx(0.3)
    t = run(robot, 0.6, t0=t, feed=False)  # the client went silent
    assert robot.watchdog_tripped and robot.v == 0.0
    robot.touch(t)  # a PULSE arrives
    run(robot, 0.2, t0=t)
    assert not robot.watchdog_tripped and robot.v == pytest.approx(0.3)


def test_bumping_a_wall_stops_the_robot_sets_stall_and_bumper():
    robot = SimRobot(SimRobotConfig(accel=10, decel=10), World(wall=[{"a": (1, -1), "b": (1, 1)}]))
    robot.motors_enabled = True
    robot.set_velocity(0.5)
    run(robot, 3.0)
    assert robot.x == pytest.approx(1 - robot.config.radius, abs=0.01)
    assert robot.stall_left and robot.stall_right and robot.bumpers & 0x01
    robot.set_velocity(-0.2)  # backing off frees it
    run(robot, 0.5)
    assert not robot.stall_left and robot.bumpers == 0 and robot.x < 0.7


def test_battery_follows_the_energy_model_of_paper_000():
    robot = make(accel=100, decel=100, battery_wh=10.0)
    run(robot, 100.0, dt=0.05)
    assert robot.energy == pytest.approx(P0_WATTS * 100, rel=1e-6)
    standing = robot.energy
    robot.set_velocity(0.5)
    run(robot, 100.0, dt=0.05)
    assert robot.energy - standing == pytest.approx((11.55 * 0.5 + 14.838) * 100, rel=0.01)
    soc = 1 - robot.energy / (10.0 * 3600)
    assert robot.battery == pytest.approx(11.0 + 2.0 * soc)


def _session(robot: SimRobot) -> tuple[ArcosFirmware, PacketReader]:
    fw = ArcosFirmware(robot)
    reader = PacketReader()
    for sync in (0, 1, 2):
        fw.receive(arcos.encode_command(sync), 0.0)
    replies = reader.feed(fw.take_output())
    assert [b[0] for b in replies] == [0, 1, 2]
    assert arcos.parse_sync2(replies[2]) == ("sim", "Pioneer", robot.config.subclass)
    fw.receive(arcos.encode_command(Cmd.OPEN, 1) + arcos.encode_command(Cmd.ENABLE, 1), 0.0)
    return fw, reader


def test_firmware_handshake_from_the_reference_vectors_then_sips_on_schedule():
    robot = SimRobot(SimRobotConfig(sip_period=0.1))
    fw = ArcosFirmware(robot)
    reader = PacketReader()
    for wire, reply in [("FA FB 03 00 00 00", b"\x00"), ("FA FB 03 01 00 01", b"\x01")]:
        fw.receive(bytes.fromhex(wire), 0.0)
        assert reader.feed(fw.take_output()) == [reply]
    fw.receive(bytes.fromhex("FA FB 03 02 00 02"), 0.0)
    assert reader.feed(fw.take_output())[0][0] == 2
    fw.receive(bytes.fromhex("FA FB 06 01 3B 01 00 02 3B") + bytes.fromhex("FA FB 06 04 3B 01 00 05 3B"), 0.0)
    assert robot.motors_enabled and fw.state == "open"
    for i in range(10):
        fw.tick(i * 0.05)
    sips = reader.feed(fw.take_output())
    assert len(sips) == 5 and all(arcos.is_sip(b) for b in sips)


def test_firmware_commands_reach_the_physics():
    robot = SimRobot(SimRobotConfig(accel=100, decel=100))
    fw, reader = _session(robot)
    fw.receive(bytes.fromhex("FA FB 06 0B 3B C8 00 D3 3B"), 0.1)  # VEL 200
    fw.receive(bytes.fromhex("FA FB 06 15 3B 1E 00 33 3B"), 0.1)  # RVEL 30
    assert robot.target_v == pytest.approx(0.2) and robot.target_w == pytest.approx(math.radians(30))
    fw.receive(arcos.encode_command(Cmd.VEL2, (10 << 8) | (20 & 0xFF)), 0.1)
    assert robot.trans_mode == "wheels" and robot.wheels == pytest.approx((0.2, 0.4))
    fw.receive(arcos.encode_command(Cmd.VEL2, ((-5 & 0xFF) << 8 | 5) - 0x10000), 0.1)
    assert robot.wheels == pytest.approx((-0.1, 0.1))
    fw.receive(bytes.fromhex("FA FB 03 37 00 37"), 0.1)  # ESTOP
    assert robot.v == 0 and robot.target_v == 0
    odometry = robot.odometry()
    fw.receive(arcos.encode_sim_set_pose(2500, -1000, 90), 0.2)
    assert (robot.x, robot.y, robot.th) == pytest.approx((2.5, -1.0, math.pi / 2))
    assert robot.odometry() == pytest.approx(odometry)  # the true pose moved, odometry did not
    fw.receive(arcos.encode_command(Cmd.SAY, b"\x0a\x3c"), 0.2)
    assert robot.said == [b"\x0a\x3c"]
    fw.receive(arcos.encode_command(Cmd.SETO), 0.2)
    assert robot.odometry() == pytest.approx((0, 0, 0))
    fw.receive(arcos.encode_command(Cmd.SONAR, 0), 0.2)
    fw.tick(1.0)
    (sip,) = reader.feed(fw.take_output())
    assert arcos.parse_sip(sip).sonar == {}
    fw.receive(arcos.encode_command(Cmd.CLOSE), 0.3)
    assert fw.state == "sync0" and not robot.motors_enabled


def test_garbage_first_and_line_noise_options_damage_the_wire():
    robot = SimRobot(SimRobotConfig(garbage_first=1, line_noise=0.5, seed=3))
    fw = ArcosFirmware(robot)
    reader = PacketReader()
    fw.receive(arcos.encode_command(0), 0.0)
    assert reader.feed(fw.take_output()) == []  # the first SYNC0 is answered with garbage
    assert reader.stats.bytes_skipped > 0


def test_host_serves_several_robots_on_consecutive_ports_and_they_see_each_other():
    world = World(robot=[{"name": "a", "x": 0, "y": 0}, {"name": "b", "x": 1.0, "y": 0}])
    host = RobotHost(world)
    try:
        a = host.add_robot(SimRobotConfig(name="a"))
        host.add_robot(SimRobotConfig(name="b"))
        assert host.url(0) != host.url(1) and host.url(0).startswith("socket://127.0.0.1:")
        front = a.sonar()[3]  # robot b stands 1 m ahead: 1 - 0.166 (the transducer) - 0.25 (b's body)
        assert front == pytest.approx(0.584, abs=0.03)
    finally:
        host.stop()


def test_host_runs_on_an_injected_clock_without_its_thread():
    now = [100.0]
    host = RobotHost(physics_hz=50, clock=lambda: now[0])
    try:
        robot = host.add_robot(SimRobotConfig(accel=100, decel=100, sip_period=0.1))
        client = socket.create_connection(("127.0.0.1", int(host.url().rsplit(":", 1)[1])))
        reader = PacketReader()
        host.run_once(0.1)  # accept
        for sync in (0, 1, 2):
            client.sendall(arcos.encode_command(sync))
            wait_until(lambda: (host.run_once(0.01), reader.feed(_recv(client)))[1], timeout=2)
        client.sendall(arcos.encode_command(Cmd.OPEN) + arcos.encode_command(Cmd.ENABLE, 1)
                       + arcos.encode_command(Cmd.VEL, 500))
        wait_until(lambda: (host.run_once(0.01), robot.target_v == 0.5)[1], timeout=2)
        reader.feed(_recv(client))
        for _ in range(50):  # one simulated second in 20 ms steps, as fast as the CPU goes
            now[0] += 0.02
            host.run_once(0)
        assert robot.x == pytest.approx(0.5, abs=1e-6)
        sips = [b for b in reader.feed(_recv(client)) if arcos.is_sip(b)]
        assert 10 <= len(sips) <= 11  # a 0.1 s SIP period on the injected clock
        client.close()
    finally:
        host.stop()


def _recv(sock: socket.socket) -> bytes:
    sock.setblocking(False)
    try:
        return sock.recv(65536)
    except BlockingIOError:
        return b""


def _open(robot: SimRobot) -> tuple[ArcosFirmware, PacketReader]:
    fw = ArcosFirmware(robot)
    for cmd in (0, 1, 2, 1):
        fw.receive(arcos.encode_command(cmd), 0.0)
    reader = PacketReader()
    reader.feed(fw.take_output())
    return fw, reader


def _sonar_per_sip(fw: ArcosFirmware, reader: PacketReader, seconds: float, dt: float = 0.005) -> list[dict[int, int]]:
    out = []
    for i in range(1, round(seconds / dt) + 1):
        fw.tick(i * dt)
        out += [arcos.parse_sip(b).sonar for b in reader.feed(fw.take_output()) if arcos.is_sip(b)]
    return out


def test_sonar_fires_one_transducer_per_bank_every_cycle_as_real_firmware():
    robot = SimRobot(SimRobotConfig(sip_period=0.1, sonar_cycle=0.04))  # 16 transducers: two banks of 8
    fw, reader = _open(robot)
    sips = _sonar_per_sip(fw, reader, 1.0)
    assert 9 <= len(sips) <= 11
    counts = [len(s) for s in sips[1:]]
    assert all(4 <= n <= 6 for n in counts)  # 2.5 firings of 2 banks per 100 ms SIP
    seen: set[int] = set()
    for s in sips[:4]:
        seen |= set(s)
    assert seen == set(range(16))  # the whole ring within 8 x 40 ms
    first = sorted(sips[1])
    assert all(n < 8 for n in first[: len(first) // 2]) and all(n >= 8 for n in first[len(first) // 2:])
    every = SimRobot(SimRobotConfig(sip_period=0.1, sonar_cycle=0))  # 0: the whole ring in every SIP
    fw0, reader0 = _open(every)
    assert all(len(s) == 16 for s in _sonar_per_sip(fw0, reader0, 0.3))


def test_polling_sets_the_firing_sequence_and_sonar_off_empties_the_sips():
    robot = SimRobot(SimRobotConfig.for_model("amigo", sip_period=0.1, sonar_cycle=0.04))  # one bank of 8
    fw, reader = _open(robot)
    fw.receive(arcos.encode_command(Cmd.POLLING, bytes([1, 4, 5, 8])), 0.0)  # sonar numbers from 1
    seen = set().union(*_sonar_per_sip(fw, reader, 0.6))
    assert seen == {0, 3, 4, 7}
    fw.receive(arcos.encode_command(Cmd.SONAR, 0), 0.6)
    assert all(s == {} for s in _sonar_per_sip(fw, reader, 0.3)[1:])


def test_ranges_are_measured_from_each_transducer_and_in_range_units():
    world = World(wall=[{"a": (1.0, -3.0), "b": (1.0, 3.0)}])
    amigo = SimRobot(SimRobotConfig.for_model("amigo"), world)
    cone = 0.13  # the echo comes from the nearest point within the beam (+-0.13 rad)
    assert amigo.sonar_reading(2) == pytest.approx((1.0 - 0.150) / math.cos(math.radians(15) - cone), abs=0.002)
    assert amigo.sonar_reading(0) == 5.0 and amigo.sonar_reading(8) is None
    p2 = SimRobot(SimRobotConfig.for_model("p2dx", sonar_cycle=0), world)  # RangeConvFactor 0.268
    sip = arcos.parse_sip(ArcosFirmware(p2).sip())
    assert sip.sonar[3] * 0.268 == pytest.approx((1.0 - 0.166) / math.cos(math.radians(10) - cone) * 1000, abs=1)
    power = SimRobot(SimRobotConfig.for_model("powerbot-sh", sonar_cycle=0), world)
    assert 7 not in arcos.parse_sip(ArcosFirmware(power).sip()).sonar  # no transducer in socket 7


def test_sim_set_pose_moves_the_true_pose_and_sim_reset_goes_back_to_the_start():
    robot = SimRobot(SimRobotConfig(accel=100, decel=100), World(), x=1.0, y=1.0)
    robot.start = (1.0, 1.0, 0.0)
    robot.odo = (1.0, 1.0, 0.0)  # odometry starts at zero where the robot stands
    robot.motors_enabled = True
    robot.move(0.5)
    run(robot, 2.0)
    assert robot.odometry() == pytest.approx((0.5, 0.0, 0.0), abs=1e-6)
    fw, reader = _open(robot)
    fw.receive(arcos.encode_sim_set_pose(-3000, 4000, 180), 1.0)
    assert (robot.x, robot.y, abs(robot.th)) == pytest.approx((-3.0, 4.0, math.pi))
    assert robot.odometry() == pytest.approx((0.5, 0.0, 0.0), abs=1e-6)
    robot.move(0.5)  # driving on: odometry and the world agree on the distance
    run(robot, 2.0)
    assert robot.odometry()[0] == pytest.approx(1.0, abs=1e-6) and robot.x == pytest.approx(-3.5, abs=1e-6)
    fw.receive(arcos.encode_command(Cmd.SIM_RESET), 5.0)
    assert (robot.x, robot.y, robot.th) == (1.0, 1.0, 0.0)


def test_debug_log_tells_clients_commands_and_unknown_packets(caplog):
    host = RobotHost(physics_hz=50)
    try:
        host.add_robot(SimRobotConfig(name="r1", sip_period=0.05))
        host.start()
        with caplog.at_level(logging.DEBUG, logger="erni.sim.robot"):
            client = socket.create_connection(("127.0.0.1", int(host.url().rsplit(":", 1)[1])))
            client.sendall(b"".join(arcos.encode_command(c) for c in (0, 1, 2)))
            wait_until(lambda: any("handshake done" in r.getMessage() for r in caplog.records), timeout=3)
            client.sendall(arcos.encode_command(Cmd.OPEN) + arcos.encode_command(Cmd.VEL, 200)
                           + arcos.encode_command(99, 7) + b"\xfa\xfb\x06\x0b\x3b\xc8\x00\x00\x00")
            wait_until(lambda: any("unknown command 99" in r.getMessage() for r in caplog.records), timeout=3)
            client.close()
            wait_until(lambda: any("client disconnected" in r.getMessage() for r in caplog.records), timeout=3)
        text = "\n".join(r.getMessage() for r in caplog.records)
        assert "r1 (socket://127.0.0.1:" in text and "client 127.0.0.1:" in text and "connected" in text
        assert "handshake done: r1 Pioneer p3dx-sh" in text and "VEL 200" in text
        assert "bad packet dropped" in text and "unknown command 99 ignored: 63 3b 07 00" in text
        assert "1 unknown commands" in text
    finally:
        host.stop()
