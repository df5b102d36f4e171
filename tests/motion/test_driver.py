"""The ARCOS driver through real bytes: TCP and pty to the simulated firmware, noise, link loss,
the model chosen from SYNC2, CONFIG, HOSTBAUD and the limits sent at connect."""

from __future__ import annotations

import logging
import math
import socket
import threading
import time

import pytest
import serial
from hypothesis import given, settings
from hypothesis import strategies as st

from erni.blackboard.testing import wait_until
from erni.plugins.motion import arcos
from erni.plugins.motion.arcos import Cmd
from erni.plugins.motion.driver import ArcosDriver, LinkError, _Unwrapper
from erni.plugins.motion.robots import MODELS, RobotModel, lookup, model_spec, resolve_model
from erni.sim.robot import SimRobotConfig
from erni.sim.robot_host import RobotHost
from erni.sim.world import World
from tests.motion.conftest import REAL_URL, sim_only_because, skip_on_simulators_without_watchdog


@pytest.fixture
def drivers():
    made: list[ArcosDriver] = []

    def make(url: str, **kw) -> ArcosDriver:
        kw.setdefault("sync_timeout", 0.3)
        d = ArcosDriver(url, **kw)
        made.append(d)
        return d

    yield make
    for d in made:
        d.close()


def test_handshake_and_sip_round_trip(robot_url, drivers):
    d = drivers(robot_url).open()
    assert d.connected and d.info.robot_class
    s = d.wait_for(lambda s: s.motors_enabled, 2.0)  # ENABLE may land after the first SIP
    assert s is not None and 8 < s.battery < 16
    d.vel(0.3)
    moving = d.wait_for(lambda s: s.v > 0.25, 3.0)
    assert moving is not None and moving.moving
    d.stop()
    assert d.wait_for(lambda s: abs(s.v) < 0.005 and not s.moving, 3.0)
    assert d.stats.reader.bad_checksum == 0 and d.stats.sips > 5


@pytest.mark.parametrize("pty", [False, True], ids=["tcp", "pty"])
@sim_only_because("serves the robot on a pty and checks it against the simulated robot's walls and true pose")
def test_sip_round_trip_through_tcp_and_pty(make_host, drivers, pty):
    host = make_host(World(wall=[{"a": (1.5, -2), "b": (1.5, 2)}]), pty=pty)
    d = drivers(host.url()).open()
    assert d.info.name == "sim" and d.info.subclass == "p3dx-sh" and d.model.name == "p3dx-sh"
    s = d.wait_for(lambda s: 3 in s.sonar and 4 in s.sonar, 2.0)  # the ring is fired a few at a time
    assert s is not None
    front = (s.sonar[3] + s.sonar[4]) / 2
    assert front == pytest.approx((1.5 - 0.166) / math.cos(math.radians(10)), abs=0.02)
    robot = host.robots[0]
    odometry = robot.odometry()
    d.sim_set_pose(-0.5, 0.25, 45)  # moves the robot itself; its odometry stays, ours is re-based
    s = d.wait_for(lambda s: s.sim_pose is not None and abs(s.sim_pose[0] + 0.5) < 1e-3, 2.0)
    assert s is not None and s.sim_pose == pytest.approx((-0.5, 0.25, math.radians(45)), abs=1e-3)
    assert (s.x, s.y, math.degrees(s.theta)) == pytest.approx((-0.5, 0.25, 45), abs=0.01)
    assert (robot.x, robot.y) == pytest.approx((-0.5, 0.25)) and robot.odometry() == pytest.approx(odometry)
    d.rvel(90)
    s = d.wait_for(lambda s: math.degrees(s.w) > 85, 2.0)
    assert s is not None and s.right > s.left
    assert robot.th == pytest.approx(s.theta, abs=0.3)


@sim_only_because("puts the simulated robot 16 m out by the simulator's hand")
def test_teleport_beyond_the_15_bit_range_and_driving_across_the_wrap(make_host, drivers):
    host = make_host()
    d = drivers(host.url()).open()
    with host._lock:  # the simulator's hand puts the robot there, odometry reading it
        host.robots[0].set_pose(16.2, -5.0, 0.0)
    assert d.wait_for(lambda s: abs(s.x - 16.2) < 1e-3 and abs(s.y + 5.0) < 1e-3, 2.0)
    d.vel(1.0)  # x crosses 16.383 m, where the 15-bit wire value wraps
    s = d.wait_for(lambda s: s.x > 16.6, 3.0)
    assert s is not None and s.x == pytest.approx(host.robots[0].x, abs=0.1)


def test_unwrapper_follows_small_deltas_across_the_wrap():
    u = _Unwrapper()
    assert u.update(0x7FF0) == -16
    assert u.update(0x0005) == 5
    assert u.update(0x3FFF) == 0x3FFF
    assert u.update(0x4100) == 0x4100  # continues past 16.383 m
    assert u.update(0x7FFF) == 0x7FFF


@sim_only_because("needs a robot that answers SYNC0 with garbage")
def test_robot_that_first_answers_with_garbage_is_retried(make_host, drivers):
    host = make_host(garbage_first=2)
    d = drivers(host.url()).open()
    assert d.connected and d.stats.reader.bytes_skipped > 0
    assert "SYNC0" in d.last_error or d.last_error == ""  # failures were explained as they happened


@sim_only_because("talks to a silent socket instead of the robot")
def test_handshake_failure_gives_a_clear_error(drivers):
    silent = socket.socket()
    silent.bind(("127.0.0.1", 0))
    silent.listen(1)
    port = silent.getsockname()[1]
    try:
        d = drivers(f"socket://127.0.0.1:{port}", sync_attempts=2, sync_timeout=0.1, reconnect=False)
        with pytest.raises(LinkError, match=rf"socket://127.0.0.1:{port}: cannot connect.*no SYNC0 reply"):
            d.open()
    finally:
        silent.close()


def test_bad_urls_are_refused_clearly(drivers):
    with pytest.raises(LinkError, match="expected a serial device or pyserial URL"):
        ArcosDriver("")
    d = drivers("nosuch://x", reconnect=False)
    with pytest.raises(LinkError, match="cannot open nosuch://x"):
        d.open(timeout=2)


@sim_only_because("needs a simulated line that damages packets")
def test_line_noise_is_skipped_and_counted_and_the_robot_still_obeys(make_host, drivers):
    host = make_host(line_noise=0.3, seed=7)
    d = drivers(host.url(), sync_attempts=10).open()
    d.vel(0.4)
    assert d.wait_for(lambda s: s.v > 0.35, 3.0)
    wait_until(lambda: d.stats.sips > 40, timeout=5)
    st = d.stats.reader
    assert st.bad_checksum + st.bad_count + st.bytes_skipped + d.stats.bad_sips > 0
    assert d.connected


@sim_only_because("drops the robot's end of the link")
def test_link_drop_is_noticed_and_the_driver_reconnects(make_host, drivers):
    host = make_host()
    events: list[tuple[bool, str]] = []
    d = drivers(host.url(), link_timeout=0.3, reconnect_delay=0.05,
                on_link=lambda up, why: events.append((up, why))).open()
    ep = host.endpoints[0]
    with host._lock:  # the server drops the TCP connection, as a crashed simulator would
        host._drop(ep)
    wait_until(lambda: d.stats.link_losses >= 1 and d.stats.connects >= 2 and d.connected, timeout=5)
    assert events[0][0] and not events[1][0] and events[-1][0]
    assert d.vel(0.2)
    assert d.wait_for(lambda s: s.v > 0.15, 2.0)


@sim_only_because("mutes the simulated firmware")
def test_silent_robot_means_link_lost(make_host, drivers):
    host = make_host()
    d = drivers(host.url(), link_timeout=0.2, reconnect_delay=0.05, sync_attempts=1)
    d.open()
    host.firmware(0).state = "muted"  # stops streaming SIPs and answering syncs, keeps the socket
    wait_until(lambda: not d.connected and d.stats.link_losses == 1, timeout=3)
    assert "no SIP" in d.last_error or "SYNC" in d.last_error
    assert not d.vel(0.1) and d.stats.dropped_commands >= 1


def test_watchdog_stops_a_robot_whose_client_died(robot_url, request, real_robot):
    skip_on_simulators_without_watchdog(real_robot)
    url = robot_url if REAL_URL else request.getfixturevalue("make_host")(watchdog=0.3).url()
    port = serial.serial_for_url(url, timeout=0.05)  # a bare client: handshake, VEL, then silence
    reader = arcos.PacketReader()
    try:
        for sync in (0, 1, 2):
            port.write(arcos.encode_command(sync))
            deadline = time.monotonic() + 1.0
            while time.monotonic() < deadline and not any(b[0] == sync for b in reader.feed(port.read(64))):
                pass
        port.write(arcos.encode_command(Cmd.OPEN) + arcos.encode_command(Cmd.ENABLE, 1))
        port.write(arcos.encode_command(Cmd.VEL, 150))
        moving = stopped = False
        deadline = time.monotonic() + (6.0 if REAL_URL else 3.0)
        while time.monotonic() < deadline and not stopped:
            for body in reader.feed(port.read(256)):
                if arcos.is_sip(body):
                    sip = arcos.parse_sip(body)
                    moving = moving or sip.lvel > 100
                    stopped = moving and sip.lvel == 0 and sip.rvel == 0
        assert moving and stopped
        port.write(arcos.encode_command(Cmd.PULSE))  # traffic returns: the robot resumes
        resumed = False
        deadline = time.monotonic() + 2.0
        while time.monotonic() < deadline and not resumed:
            resumed = any(arcos.is_sip(b) and arcos.parse_sip(b).lvel > 100 for b in reader.feed(port.read(256)))
        assert resumed
        port.write(arcos.encode_command(Cmd.STOP) + arcos.encode_command(Cmd.CLOSE))
    finally:
        port.close()


@sim_only_because("compares the driver's view with the simulated robot's true motion")
@pytest.mark.parametrize("model", ["amigo", "p3dx", "p2dx"])
def test_commands_are_unscaled_and_reports_use_the_models_factors(sim_hosts, drivers, model):
    host = RobotHost(physics_hz=200)
    sim_hosts.append(host)
    robot = host.add_robot(SimRobotConfig.for_model(model, sip_period=0.02, accel=3, decel=3, sonar_cycle=0))
    host.start()
    d = drivers(host.url()).open()  # model auto: taken from SYNC2
    assert d.model.name == model and d.model.dist_conv == MODELS[model].dist_conv
    d.vel(0.3)  # VEL 300 mm/s, whatever VelConvFactor is
    assert d.wait_for(lambda s: s.v > 0.29, 3.0)
    wait_until(lambda: robot.v == pytest.approx(0.3), timeout=2)
    assert robot.target_v == pytest.approx(0.3)
    assert d.wait_for_sip(d.state.seq).v == pytest.approx(0.3, abs=0.002)  # LVEL/RVEL x VelConvFactor
    d.stop()
    assert d.wait_for(lambda s: not s.moving, 3.0)
    x0, true0 = d.state.x, robot.x
    d.move(0.5)  # MOVE 500 mm
    s = d.wait_for(lambda s: s.x > x0 + 0.49 and not s.moving, 4.0)
    assert s is not None and robot.x - true0 == pytest.approx(0.5, abs=0.002)
    assert s.x - x0 == pytest.approx(0.5, abs=0.003)  # the SIP's position units, converted back
    readings = [r for r in d.state.sonar.values()]
    assert len(readings) == sum(t is not None for t in MODELS[model].sonar) and all(r == pytest.approx(5.0, abs=0.001) for r in readings)


@sim_only_because("serves an old-firmware Pioneer from the simulator")
def test_configured_model_that_disagrees_with_the_robot_is_used_and_warned_about(sim_hosts, drivers, caplog):
    host = RobotHost(physics_hz=200)
    sim_hosts.append(host)
    robot = host.add_robot(SimRobotConfig.for_model("p3dx", sip_period=0.02))  # DistConvFactor 0.485
    host.start()
    with caplog.at_level(logging.WARNING, logger="erni.motion.driver"):
        d = drivers(host.url(), model="pioneer3").open()  # the configuration says factors 1.0
    assert d.model.name == "p3dx-sh"
    warning = next(r.getMessage() for r in caplog.records if "disagrees" in r.getMessage())
    assert "subtype 'p3dx'" in warning and "dist_conv 1 (robot's subtype: 0.485)" in warning
    d.move(0.4)
    s = d.wait_for(lambda s: s.x > 0.1 and not s.moving, 4.0)
    assert robot.x == pytest.approx(0.4, abs=0.003)
    assert s is not None and s.x == pytest.approx(0.4 / 0.485, abs=0.01)  # as configured, and warned


def test_models_are_the_published_ones_and_resolve_by_subtype_alias_or_table():
    aria = {  # subtype: DistConvFactor, VelConvFactor, RangeConvFactor, DiffConvFactor (ARIA's robot tables)
        "p3dx-sh": (1.0, 1.0, 1.0, 0.0056), "p3at-sh": (1.0, 1.0, 1.0, 0.0034), "p3dx": (0.485, 1.0, 1.0, 0.0056),
        "p3at": (0.465, 1.0, 1.0, 0.0034), "amigo": (0.5083, 0.6154, 1.0, 0.011), "amigo-sh": (1.0, 1.0, 1.0, 0.011),
        "p2dx": (0.84, 1.0, 0.268, 0.0056), "p2at": (1.32, 1.0, 0.268, 0.0034), "peoplebot-sh": (1.0, 1.0, 1.0, 0.006),
        "powerbot": (0.5813, 1.0, 1.0, 0.00373), "powerbot-sh": (1.0, 1.0, 1.0, 0.00373), "seekur": (1.0, 1.0, 1.0, 0.0056),
    }
    for name, factors in aria.items():
        m = MODELS[name]
        assert (m.dist_conv, m.vel_conv, m.range_conv, m.diff_conv) == factors, name
        assert m.subclass == name and m.robot_class == "Pioneer" and m.angle_conv == 0.001534
    assert MODELS["p3dx-sh"].sonar[3] == (0.166, 0.027, 10.0) and len(MODELS["p3dx-sh"].sonar) == 16
    assert MODELS["amigo"].sonar[6] == (-0.14, -0.058, -145.0) and len(MODELS["amigo"].sonar) == 8
    assert len(MODELS["peoplebot-sh"].sonar) == 32 and MODELS["powerbot-sh"].sonar[7] is None
    assert lookup("pioneer3") is MODELS["p3dx-sh"] and lookup("AmigoBot") is MODELS["amigo"]
    assert lookup("P3DX-SH-LMS1XX") is MODELS["p3dx-sh"] and lookup("p3-dx-sh") is MODELS["p3dx-sh"]
    assert lookup("roomba") is None
    custom = resolve_model({"base": "amigobot", "dist_conv": 0.5})
    assert custom.dist_conv == 0.5 and custom.vel_conv == 0.6154 and custom.name == "amigo+custom"
    assert isinstance(resolve_model(RobotModel()), RobotModel)
    with pytest.raises(Exception, match="unknown robot model 'roomba'"):
        resolve_model("roomba")
    with pytest.raises(Exception, match="dist_conv"):
        model_spec({"base": "auto", "dist_conv": -1})
    auto = model_spec({"decel": 0.4})  # a table without base follows the robot, then overrides
    model, warnings = auto.resolve("amigo")
    assert model.dist_conv == 0.5083 and model.decel == 0.4 and warnings == []
    model, warnings = auto.resolve("marsrover")
    assert model.dist_conv == 1.0 and "not in the model table" in warnings[0]


@sim_only_because("reads the limits back from the simulated robot")
def test_config_is_read_and_the_planners_limits_are_sent(make_host, drivers):
    host = make_host(accel=0.8, rot_accel=150.0, max_v=1.2, top_v=1.8)
    robot = host.robots[0]
    d = drivers(host.url(), model={"max_v": 5.0, "decel": 0.4, "rot_decel": 90.0}).open()
    cfg = d.robot_config
    assert cfg is not None and cfg.serial == "SIM" and cfg.firmware and cfg.subclass == "p3dx-sh"
    assert cfg.trans_vel_top == 1800 and cfg.trans_accel == 800 and cfg.sip_cycle == 20
    m = d.model
    assert m.max_v == 1.8  # asked for 5 m/s: clamped to the robot's TransVelTop
    assert (m.accel, m.decel, m.rot_accel, m.rot_decel) == (0.8, 0.4, 150.0, 90.0)  # unset ones: the robot's own
    wait_until(lambda: robot.decel == pytest.approx(0.4), timeout=2)  # SETA -400 arrived
    assert robot.max_v == pytest.approx(1.8) and robot.accel == pytest.approx(0.8)
    assert robot.rot_decel == pytest.approx(math.radians(90)) and robot.max_rv == pytest.approx(math.radians(m.max_rv))


@sim_only_because("serves a robot that ignores CONFIG")
def test_a_robot_that_does_not_answer_config_is_driven_with_the_models_limits(make_host, drivers):
    host = make_host(answer_config=False)
    d = drivers(host.url(), config_timeout=0.3).open()
    assert d.robot_config is None and d.connected
    assert d.model.limit("max_v") == 0.75 and d.model.limit("decel") == 0.3  # the ARCOS defaults
    wait_until(lambda: host.robots[0].decel == pytest.approx(0.3), timeout=2)


@sim_only_because("switches the baud rate of the simulator's pty")
def test_hostbaud_switches_a_serial_line_to_38400_and_never_a_tcp_link(make_host, drivers):
    pty = make_host(pty=True)
    d = drivers(pty.url()).open()
    assert pty.firmware(0).host_baud == 2 and d.line_baud == 38400  # HOSTBAUD 2, then our side too
    assert d.wait_for_sip(d.state.seq if d.state else -1) is not None  # still talking after the switch
    tcp = make_host()
    t = drivers(tcp.url()).open()
    assert tcp.firmware(0).host_baud == 0 and t.line_baud is None


@sim_only_because("counts the packets the simulated firmware received")
def test_commands_from_many_threads_arrive_whole(make_host, drivers):
    host = make_host()
    d = drivers(host.url()).open()
    fw = host.firmware(0)
    before = fw.counts["packets"]

    def spam() -> None:
        for _ in range(50):
            d.say(b"\x01\x40")

    threads = [threading.Thread(target=spam, name=f"spam-{i}") for i in range(4)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    wait_until(lambda: len(host.robots[0].said) == 200, timeout=3)
    assert fw.counts["bad"] == 0 and fw.counts["packets"] - before >= 200


@sim_only_because("reads the limits back from the simulated robot")
def test_position_heading_and_limit_commands_through_the_wire(make_host, drivers):
    host = make_host(accel=2.0, decel=2.0)
    robot = host.robots[0]
    d = drivers(host.url()).open()
    d.head(90)
    assert d.wait_for(lambda s: abs(math.degrees(s.theta) - 90) < 1 and not s.moving, 3.0)
    d.dhead(-45)
    assert d.wait_for(lambda s: abs(math.degrees(s.theta) - 45) < 1 and not s.moving, 3.0)
    d.move(0.4)
    s = d.wait_for(lambda s: math.hypot(s.x, s.y) > 0.39 and not s.moving, 3.0)
    assert s is not None and math.hypot(s.x, s.y) == pytest.approx(0.4, abs=0.01)
    d.seto()
    assert d.wait_for(lambda s: abs(s.x) < 1e-3 and abs(s.y) < 1e-3 and abs(s.theta) < 0.01, 2.0)
    d.setv(0.25)
    d.seta(0.5)
    d.vel(1.0)
    s = d.wait_for(lambda s: s.v > 0.24, 3.0)
    assert s is not None and robot.max_v == pytest.approx(0.25) and robot.accel == pytest.approx(0.5)
    d.estop()
    assert d.wait_for(lambda s: s.v == 0 and s.seq > 0, 1.0)
    d.sonar(False)
    wait_until(lambda: not robot.sonar_on, timeout=2)
    d.vel2(-0.2, 0.2)
    assert d.wait_for(lambda s: s.left < -0.15 and s.right > 0.15, 2.0)


@sim_only_because("shortens the simulated watchdog to 0.3 s")
def test_idle_driver_pulses_so_the_watchdog_never_trips(make_host, drivers):
    host = make_host(watchdog=0.3)
    d = drivers(host.url(), pulse_interval=0.1).open()
    d.vel(0.2)
    first = d.wait_for(lambda s: s.v > 0.15, 2.0)
    assert first is not None
    later = d.wait_for(lambda s: s.stamp > first.stamp + 1.0, 3.0)  # three watchdog periods later
    assert later is not None and later.v > 0.15 and not host.robots[0].watchdog_tripped


@settings(max_examples=300, deadline=None)
@given(bodies=st.lists(st.binary(min_size=1, max_size=120), max_size=8), junk=st.binary(max_size=64))
def test_valid_frames_with_garbage_contents_never_crash_the_decoder(bodies, junk):
    d = ArcosDriver("loop://", name="fuzz")  # never opened: bytes are pushed by hand
    wire = junk + b"".join(arcos.frame(bytes([0x32 + (b[0] & 1)]) + b[1:]) for b in bodies)
    for body in d._reader.feed(wire):
        d._packet(body)
    assert d.stats.sips + d.stats.bad_sips + d.stats.other_packets == d.stats.reader.packets
    assert d.stats.sips == 0 or d.state is not None


@settings(max_examples=200, deadline=None)
@given(bodies=st.lists(st.binary(min_size=1, max_size=120), min_size=1, max_size=8))
def test_any_sip_makes_a_state_of_finite_numbers_that_a_pose_takes(bodies):
    """ARCOS carries integers, and the driver scales them by the model's finite factors: whatever SIP
    bytes a robot (or line noise) sends, the state holds only finite numbers, so its Pose validates."""
    from erni.plugins.motion import pose_of

    d = ArcosDriver("loop://", name="fuzz")
    for body in d._reader.feed(b"".join(arcos.frame(bytes([0x32 + (b[0] & 1)]) + b[1:]) for b in bodies)):
        d._packet(body)
        if d.state is not None:
            pose_of("fuzz", d.state)  # a ValidationError here would be a NaN or an infinity


def test_relocalise_rebases_odometry_for_robots_that_cannot_be_teleported(robot_url, sim_hosts, drivers):
    d = drivers(robot_url).open()
    d.wait_for_sip()
    true0 = sim_hosts[0].robots[0].x if sim_hosts else None
    d.relocalise(5.0, 2.0, math.pi / 2)  # the robot is declared to stand at (5, 2) facing +y
    assert (d.state.x, d.state.y) == pytest.approx((5.0, 2.0))
    d.move(0.3)  # straight ahead in its own frame is +y on the map
    s = d.wait_for(lambda s: s.y > 2.29 and not s.moving, 6.0)
    assert s is not None and s.x == pytest.approx(5.0, abs=0.02) and s.y == pytest.approx(2.3, abs=0.02)
    assert math.degrees(s.theta) == pytest.approx(90, abs=1.5)
    if true0 is not None:
        assert sim_hosts[0].robots[0].x == pytest.approx(true0 + 0.3, abs=0.01)  # the robot never jumped


def test_the_reader_takes_a_sip_in_a_few_reads_over_a_socket(robot_url, drivers):
    """pyserial's socket:// says only 0 or 1 byte is waiting; reading what the kernel holds takes a
    SIP (tens of bytes) in one or two reads instead of one read per byte."""
    d = drivers(robot_url).open()
    wait_until(lambda: d.stats.sips > 5, timeout=5)
    reads, sips = d.stats.reads, d.stats.sips
    wait_until(lambda: d.stats.sips > sips + 40, timeout=10)
    per_sip = (d.stats.reads - reads) / (d.stats.sips - sips)
    assert per_sip < 4, f"{per_sip:.1f} reads per SIP"
