"""The batch simulator (erni.sim.swarm) against the robot-by-robot computation it replaces.

The oracle is `SimRobot.sonar_reading` and `SimRobot.step`, each robot seeing the others where
they stood at the start of the round; worlds and teams are random (hypothesis).
"""

from __future__ import annotations

import math
import random

import numpy as np
from hypothesis import HealthCheck, assume, given, settings
from hypothesis import strategies as st

from erni.sim import kinematic
from erni.sim.robot import ArcosFirmware, SimRobot, SimRobotConfig, _packet
from erni.sim.robot_host import RobotHost
from erni.sim.swarm import Swarm
from erni.sim.world import World

coord = st.floats(-6.0, 6.0, allow_nan=False)


@st.composite
def worlds(draw: st.DrawFn) -> World:
    walls = draw(st.lists(st.tuples(coord, coord, coord, coord), max_size=4))
    circles = draw(st.lists(st.tuples(coord, coord, st.floats(0.05, 1.0)), max_size=4))
    polygons = draw(st.lists(st.lists(st.tuples(coord, coord), min_size=3, max_size=5), max_size=2))
    return World.from_dict({
        "bounds": draw(st.sampled_from([None, (-7.0, -7.0, 7.0, 7.0)])),
        "wall": [{"a": [a, b], "b": [c, d]} for a, b, c, d in walls],
        "circle": [{"center": [x, y], "radius": r} for x, y, r in circles],
        "polygon": [{"points": [list(p) for p in pts]} for pts in polygons],
    })


@st.composite
def teams(draw: st.DrawFn) -> tuple[World, list[SimRobot]]:
    world = draw(worlds())
    n = draw(st.integers(1, 8))
    robots = []
    for i in range(n):
        model = draw(st.sampled_from(["p3dx-sh", "amigo"]))
        config = SimRobotConfig.for_model(model, name=f"r{i}", sonar_range=draw(st.floats(0.5, 5.0)))
        near = st.floats(-2.5, 2.5)  # close enough to see and bump into each other
        robot = SimRobot(config, world, draw(near), draw(near), draw(st.floats(-math.pi, math.pi)))
        robot.motors_enabled = True
        robot.set_velocity(draw(st.floats(-1.5, 1.5)))
        robot.set_rotation(draw(st.floats(-3.0, 3.0)))
        robot.v = draw(st.floats(-1.5, 1.5))
        robot.w = draw(st.floats(-3.0, 3.0))
        robots.append(robot)
    return world, robots


def snapshot(robots: list[SimRobot]) -> None:
    """Let every robot see the others where they stand now (the batch's view of a round)."""
    where = [((r.x, r.y), r.config.radius) for r in robots]
    for i, r in enumerate(robots):
        r.others = (lambda i=i: [w for j, w in enumerate(where) if j != i])  # type: ignore[misc]  # bind i


def clone(world: World, robots: list[SimRobot]) -> list[SimRobot]:
    out = []
    for r in robots:
        c = SimRobot(r.config, world, r.x, r.y, r.th)
        c.__dict__.update({k: v for k, v in r.__dict__.items() if k not in ("config", "world", "others")})
        out.append(c)
    return out


@settings(max_examples=80, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(teams(), st.data())
def test_sonar_ranges_equal_the_robot_by_robot_cast_bit_for_bit(team: tuple[World, list[SimRobot]],
                                                                 data: st.DataObject) -> None:
    world, robots = team
    snapshot(robots)
    pairs = [(i, num) for i in range(len(robots)) for num in range(-1, 18)]  # 16 fitted at most; -1, 16, 17 not
    pairs = data.draw(st.permutations(pairs))
    owners, nums = [i for i, _ in pairs], [num for _, num in pairs]
    batch = Swarm(world).sonar(robots, owners, nums)
    for k, (i, num) in enumerate(zip(owners, nums)):
        assert batch[k] == robots[i].sonar_reading(num), (i, num)


@settings(max_examples=80, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(teams(), st.floats(0.005, 0.2))
def test_a_physics_step_equals_the_robot_by_robot_step(team: tuple[World, list[SimRobot]], dt: float) -> None:
    world, robots = team
    reference = clone(world, robots)
    snapshot(reference)
    # A move decided by a clearance within rounding of the robot's radius may go either way.
    probe = clone(world, robots)
    for r, p in zip(reference, probe):
        p.others = r.others
        _, nx, ny, _ = p.propose(dt, 0.0)
        if abs(p.v) > 1e-9:
            here, there = world.clearance(p.x, p.y, p.others()), world.clearance(nx, ny, p.others())
            assume(abs(there - p.config.radius) > 1e-9 and abs(there - here) > 1e-9)
    Swarm(world).step(robots, dt, 0.0)
    for r in reference:
        r.step(dt, 0.0)
    for got, want in zip(robots, reference):
        assert (got.x, got.y, got.th, got.v, got.w) == (want.x, want.y, want.th, want.v, want.w)
        assert (got.bumpers, got.stall_left, got.energy) == (want.bumpers, want.stall_left, want.energy)


def _arcos(cmd: int, arg: int | None = None) -> bytes:
    body = bytes([cmd]) if arg is None else bytes([cmd, 0x3B if arg >= 0 else 0x1B]) + abs(arg).to_bytes(2, "little")
    return _packet(body)


def test_the_hosts_send_the_same_sip_bytes_with_and_without_the_batch() -> None:
    """Two robots near a wall and a pillar, driven through ARCOS: every byte of every SIP is equal."""
    world = World.from_dict({"bounds": [-3, -3, 13, 3], "circle": [{"center": [1.0, 1.0], "radius": 0.3}],
                             "wall": [{"a": [-1, 2], "b": [1, 2]}]})
    streams = []
    now = [0.0]
    for vectorised in (False, True):
        now[0] = 0.0
        host = RobotHost(world, clock=lambda: now[0], vectorised=vectorised)
        try:
            for name in ("a", "b"):
                host.add_robot(SimRobotConfig(name=name), port=0)
            fws: list[ArcosFirmware] = [host.firmware(0), host.firmware(1)]
            host.robots[1].x, host.robots[1].y = 10.0, 0.0  # beyond each other's sonar: the order cannot matter
            rng = random.Random(7)
            out = []
            for fw in fws:
                fw.receive(b"".join([_arcos(0), _arcos(1), _arcos(2), _arcos(1), _arcos(4, 1)]), 0.0)
            for k in range(300):
                now[0] = k * 0.01
                if k % 25 == 0:
                    for fw in fws:
                        fw.receive(_arcos(11, rng.randrange(-400, 600)) + _arcos(21, rng.randrange(-60, 60)), now[0])
                host.advance(0.01, now[0])
                out += [fw.take_output() for fw in fws]
            streams.append(out)
        finally:
            host.stop()
    assert streams[0] == streams[1]
    assert sum(len(b) for b in streams[0]) > 300 * 55 // 10  # SIPs with sonar readings were sent


@settings(max_examples=80, deadline=None)
@given(st.lists(st.tuples(st.integers(-20, 20), st.integers(-20, 20)), max_size=40),
       st.sampled_from([0.0, 1.0, 2.0, 5.0, 7.5, 100.0]), st.sampled_from([1.0, 0.5, 0.1]))
def test_radio_links_are_every_pair_closer_than_the_range(points: list[tuple[int, int]], comm_range: float,
                                                          scale: float) -> None:
    """Kinematic mode's radio graph (k-d tree) against the full distance matrix, ties at the range included."""
    pos = np.array(points, dtype=float).reshape(-1, 2) * scale
    d = kinematic.distances(pos) if len(pos) else np.zeros((0, 0))
    close = (d < comm_range) & ~np.eye(len(pos), dtype=bool)
    assert kinematic.links(pos, comm_range) == {i: set(np.flatnonzero(close[i]).tolist()) for i in range(len(pos))}
