"""The ARCOS driver through real bytes: TCP and pty to the simulated firmware, noise, link loss."""

from __future__ import annotations

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
from erni.plugins.motion.robots import RobotModel, resolve_model
from erni.sim.robot import SimRobotConfig
from erni.sim.robot_host import RobotHost
from erni.sim.world import World
from tests.motion.conftest import REAL_URL, sim_only


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
def test_sip_round_trip_through_tcp_and_pty(make_host, drivers, pty):
    host = make_host(World(wall=[{"a": (1.5, -2), "b": (1.5, 2)}]), pty=pty)
    d = drivers(host.url()).open()
    assert d.info.name == "sim" and d.info.subclass == "p3dx-sim"
    s = d.wait_for_sip()
    front = (s.sonar[3] + s.sonar[4]) / 2
    assert front == pytest.approx((1.5 - 0.25) / math.cos(math.radians(10)), abs=0.06)
    d.sim_set_pose(-0.5, 0.25, 45)
    s = d.wait_for(lambda s: abs(s.x + 0.5) < 1e-3, 2.0)
    assert s is not None and s.y == pytest.approx(0.25, abs=1e-3)
    assert math.degrees(s.theta) == pytest.approx(45, abs=0.2)
    d.rvel(90)
    s = d.wait_for(lambda s: math.degrees(s.w) > 85, 2.0)
    assert s is not None and s.right > s.left
    robot = host.robots[0]
    assert robot.th == pytest.approx(s.theta, abs=0.3)


def test_teleport_beyond_the_15_bit_range_and_driving_across_the_wrap(make_host, drivers):
    host = make_host()
    d = drivers(host.url()).open()
    d.sim_set_pose(16.2, -25.0, 0)
    assert d.wait_for(lambda s: abs(s.x - 16.2) < 1e-3 and abs(s.y + 25.0) < 1e-3, 2.0)
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


@sim_only
def test_robot_that_first_answers_with_garbage_is_retried(make_host, drivers):
    host = make_host(garbage_first=2)
    d = drivers(host.url()).open()
    assert d.connected and d.stats.reader.bytes_skipped > 0
    assert "SYNC0" in d.last_error or d.last_error == ""  # failures were explained as they happened


@sim_only
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


@sim_only
def test_line_noise_is_skipped_and_counted_and_the_robot_still_obeys(make_host, drivers):
    host = make_host(line_noise=0.3, seed=7)
    d = drivers(host.url(), sync_attempts=10).open()
    d.vel(0.4)
    assert d.wait_for(lambda s: s.v > 0.35, 3.0)
    wait_until(lambda: d.stats.sips > 40, timeout=5)
    st = d.stats.reader
    assert st.bad_checksum + st.bad_count + st.bytes_skipped + d.stats.bad_sips > 0
    assert d.connected


@sim_only
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


@sim_only
def test_silent_robot_means_link_lost(make_host, drivers):
    host = make_host()
    d = drivers(host.url(), link_timeout=0.2, reconnect_delay=0.05, sync_attempts=1)
    d.open()
    host.firmware(0).state = "muted"  # stops streaming SIPs and answering syncs, keeps the socket
    wait_until(lambda: not d.connected and d.stats.link_losses == 1, timeout=3)
    assert "no SIP" in d.last_error or "SYNC" in d.last_error
    assert not d.vel(0.1) and d.stats.dropped_commands >= 1


def test_watchdog_stops_a_robot_whose_client_died(robot_url, make_host):
    url = robot_url if REAL_URL else make_host(watchdog=0.3).url()
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


def test_amigobot_conversion_factors_round_trip(drivers):
    host = RobotHost()
    try:
        host.add_robot(SimRobotConfig.amigobot(sip_period=0.02, accel=3, decel=3))
        host.start()
        d = drivers(host.url(), model=resolve_model("amigobot")).open()
        d.vel(0.3)
        s = d.wait_for(lambda s: s.v > 0.29, 3.0)
        assert s is not None and s.v == pytest.approx(host.robots[0].v, abs=0.01)
        d.sim_set_pose(1.0, 2.0, 0)
        assert d.wait_for(lambda s: abs(s.x - 1.0) < 0.005 and abs(s.y - 2.0) < 0.005, 2.0)
        assert len(d.state.sonar) == 8
    finally:
        d.close()
        host.stop()


def test_models_resolve_by_name_or_table():
    assert resolve_model("P3-DX").name == "pioneer3"
    custom = resolve_model({"base": "amigobot", "dist_conv": 0.5})
    assert custom.dist_conv == 0.5 and custom.vel_conv == 0.6154
    assert isinstance(resolve_model(RobotModel()), RobotModel)
    with pytest.raises(Exception, match="unknown robot model 'roomba'"):
        resolve_model("roomba")


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


@sim_only
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


@sim_only
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


def test_relocalise_rebases_odometry_for_robots_that_cannot_be_teleported(make_host, drivers):
    host = make_host()
    d = drivers(host.url()).open()
    d.wait_for_sip()
    d.relocalise(5.0, 2.0, math.pi / 2)  # the robot is declared to stand at (5, 2) facing +y
    assert (d.state.x, d.state.y) == pytest.approx((5.0, 2.0))
    d.move(0.3)  # straight ahead in its own frame is +y on the map
    s = d.wait_for(lambda s: s.y > 2.29 and not s.moving, 3.0)
    assert s is not None and s.x == pytest.approx(5.0, abs=0.01) and s.y == pytest.approx(2.3, abs=0.01)
    assert math.degrees(s.theta) == pytest.approx(90, abs=0.5)
    assert host.robots[0].x == pytest.approx(0.3, abs=0.01)  # the simulated robot never jumped
