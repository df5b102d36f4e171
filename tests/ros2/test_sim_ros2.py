"""`erni sim --ros2` as a ROS 2 user runs it: the simulated team's control node shows every robot to ROS 2.

A subprocess runs `erni sim --ros2` with two robots; the test reads the ROS 2 endpoint it prints and
connects ROBOTIS' zenoh-ros2-sdk (an independent rmw_zenoh client) to it with the printed
ZENOH_CONFIG_OVERRIDE, as a ROS 2 client would: both robots' odometry arrives, at the poses `erni watch`
shows, and a Twist on /robot1/cmd_vel drives robot1 (a task from the control node through the team's
transport and the simulated radio) while robot2 stays put.
"""

from __future__ import annotations

import json
import math
import os
import random
import re
import signal
import socket
import struct
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

pytest.importorskip("zenoh")
pytest.importorskip("zenoh_ros2_sdk")

from zenoh_ros2_sdk import ROS2Publisher, ROS2Subscriber, message_registry  # noqa: E402
from zenoh_ros2_sdk.session import ZenohSession  # noqa: E402

from erni import ros2_messages as messages  # noqa: E402
from erni.blackboard.testing import wait_until  # noqa: E402
from tests.sim.test_sim_cli import SimProcess, processes_mentioning  # noqa: E402

ROOT = Path(__file__).resolve().parents[2]


@pytest.fixture
def sim(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Iterator[Any]:
    """`erni sim` subprocesses in this test's runtime directory and ROS 2 domain; killed at the end."""
    runtime = tmp_path / "runtime"
    runtime.mkdir(mode=0o700)
    monkeypatch.setenv("XDG_RUNTIME_DIR", str(runtime))  # the team file `erni watch` finds the team by
    for var in ("ERNI_IDENTITY", "ERNI_TEAM_KEY", "ZENOH_CONFIG_OVERRIDE"):
        monkeypatch.delenv(var, raising=False)
    # a domain of this test's own: a router another program runs on rmw_zenohd's port (which the control
    # node joins) carries no other team's /robot1/odom into this one's
    monkeypatch.setenv("ROS_DOMAIN_ID", str(random.randrange(100, 233)))
    started: list[SimProcess] = []

    def start(*args: str) -> SimProcess:
        p = SimProcess(tmp_path / "run", *args)
        started.append(p)
        return p

    yield start
    for p in started:
        p.cleanup()


@pytest.fixture
def sdk(definitions: Path, monkeypatch: pytest.MonkeyPatch) -> Iterator[Any]:
    """`connect(port, override)`: the SDK's shared session, connected to the router on 127.0.0.1:`port`, or
    configured by ZENOH_CONFIG_OVERRIDE = `override` (which replaces that address); its registry reads
    `definitions` offline."""
    monkeypatch.setenv("ZENOH_ROS2_SDK_CACHE", str(definitions / "no-cache"))
    message_registry._registry = None
    message_registry.get_registry(str(definitions))
    ZenohSession._instance = None

    def connect(port: int, override: str = "") -> Any:
        monkeypatch.setenv("ZENOH_CONFIG_OVERRIDE", override)
        return ZenohSession.get_instance("127.0.0.1", port)

    yield connect
    if ZenohSession._instance is not None:
        ZenohSession._instance.close()
    ZenohSession._instance = None
    message_registry._registry = None


def watched_poses(names: set[str]) -> dict[str, dict[str, Any]]:
    """The newest Pose of each robot in `names` as `erni watch --json` shows them (it finds the sim's team
    through the team file, without --via)."""
    out = subprocess.run([sys.executable, "-m", "erni", "watch", "--json", "--seconds", "3"], cwd=ROOT,
                         capture_output=True, text=True, timeout=60)
    assert out.returncode == 0, out.stderr
    poses: dict[str, dict[str, Any]] = {}
    for line in out.stdout.splitlines():
        event = json.loads(line)
        if event["type"] == "Pose" and event["data"]["robot"] in names:
            poses[event["data"]["robot"]] = event["data"]
    assert set(poses) == names, out.stdout[-2000:]
    return poses


def at_rest(odom: list[Any], samples: int = 3) -> bool:
    """Whether the last `samples` odometry messages in `odom` show the robot still: no speed, and one
    position (within a millimetre)."""
    last = odom[-samples:]
    if len(last) < samples:
        return False
    xs, ys = [m.pose.pose.position.x for m in last], [m.pose.pose.position.y for m in last]
    return (all(abs(m.twist.twist.linear.x) < 0.01 for m in last)
            and max(xs) - min(xs) < 0.001 and max(ys) - min(ys) < 0.001)


def yaw(odom: Any) -> float:
    q = odom.pose.pose.orientation
    return 2 * math.atan2(q.z, q.w)


def test_erni_sim_ros2_shows_every_robot_to_a_ros2_client_and_takes_cmd_vel(sim: Any, sdk: Any) -> None:
    domain = int(os.environ["ROS_DOMAIN_ID"])
    p = sim("--robots", "2", "--ros2", "--control-port", "0")
    p.wait_for("Ctrl-C stops the team", timeout=120)
    up = time.monotonic()
    startup = float(p.wait_for("team up in", timeout=1).split("team up in")[1].split()[0])
    line = p.wait_for("ROS 2 (domain", timeout=1)
    assert line.startswith(f"ROS 2 (domain {domain}): /robot1/odom ... /robot2/odom, /tf"), line
    endpoint = re.search(r"listening on (tcp/127\.0\.0\.1:\d+)$", line)
    assert endpoint, line
    hint = p.wait_for("ZENOH_CONFIG_OVERRIDE=", timeout=1)
    override = hint.split("ZENOH_CONFIG_OVERRIDE=", 1)[1].strip().strip("'")
    assert override == f'connect/endpoints=["{endpoint.group(1)}"]', hint
    assert "joins the router at tcp/127.0.0.1:7447 whenever one runs there (ros2 run rmw_zenoh_cpp rmw_zenohd)" \
        in p.wait_for("joins the router", timeout=1)

    sdk(1, override)  # port 1: only the override reaches the team
    odom: dict[str, list[Any]] = {"robot1": [], "robot2": []}
    subs = [ROS2Subscriber(f"/{name}/odom", messages.ODOMETRY, got.append, domain_id=domain)
            for name, got in odom.items()]
    teleop = ROS2Publisher("/robot1/cmd_vel", messages.TWIST, domain_id=domain)
    try:
        wait_until(lambda: odom["robot1"] and odom["robot2"], timeout=max(startup, 10.0),
                   message="no odometry of both robots from the printed endpoint")
        first = time.monotonic() - up
        # the robots stand still at their start poses: what ROS 2 gets is what erni watch shows
        poses = watched_poses({"robot1", "robot2"})
        for name, got in odom.items():
            last, pose = got[-1], poses[name]
            position = last.pose.pose.position
            assert last.child_frame_id == f"{name}/base_link"  # its world frame is the plugin's `frame` setting
            assert abs(position.x - pose["x"]) < 0.01 and abs(position.y - pose["y"]) < 0.01, (name, position, pose)
            assert abs(math.remainder(yaw(last) - pose["theta"], math.tau)) < 0.01, (name, yaw(last), pose)
        assert abs(odom["robot1"][-1].pose.pose.position.x - (-0.75)) < 0.05  # the line layout, 1.5 m apart
        assert abs(odom["robot2"][-1].pose.pose.position.x - 0.75) < 0.05

        start1 = odom["robot1"][-1].pose.pose.position
        start2 = odom["robot2"][-1].pose.pose.position
        driving = threading.Event()
        closing = threading.Event()

        def drive() -> None:  # a teleop: a Twist every 0.1 s while driving
            while not closing.is_set():
                if driving.is_set():
                    teleop.publish(linear=messages.make("geometry_msgs/msg/Vector3", x=0.25),
                                   angular=messages.make("geometry_msgs/msg/Vector3", z=0.0))
                closing.wait(0.1)

        thread = threading.Thread(target=drive, name="test-teleop")
        thread.start()
        try:
            driving.set()

            def moved(name: str, start: Any) -> float:
                now = odom[name][-1].pose.pose.position
                return math.hypot(now.x - start.x, now.y - start.y)

            wait_until(lambda: moved("robot1", start1) > 0.3, timeout=20, message="cmd_vel did not drive robot1")
            assert moved("robot2", start2) < 0.01  # cmd_vel of robot1 moves robot1 only
            assert odom["robot1"][-1].twist.twist.linear.x > 0.15
            driving.clear()  # the teleop goes quiet: the robot stops (cmd_vel_timeout)
            wait_until(lambda: abs(odom["robot1"][-1].twist.twist.linear.x) < 0.01, timeout=10,
                       message="robot1 kept going after the teleop stopped")
            # where it stopped is where erni watch sees it, once its odometry shows it at rest
            wait_until(lambda: at_rest(odom["robot1"]), timeout=10, message="robot1's odometry does not settle")
            pose = watched_poses({"robot1"})["robot1"]
            position = odom["robot1"][-1].pose.pose.position
            assert abs(position.x - pose["x"]) < 0.02 and abs(position.y - pose["y"]) < 0.02, (position, pose)
        finally:
            closing.set()
            thread.join()
    finally:
        teleop.close()
        for sub in subs:
            sub.close()
    print(f"team up in {startup:.1f} s; both robots' odometry {first:.2f} s after the team was up")
    p.proc.send_signal(signal.SIGINT)
    assert p.proc.wait(30) == 0
    assert processes_mentioning(str(p.run_dir)) == []


def test_a_router_started_after_the_team_carries_its_topics(sim: Any, sdk: Any, tmp_path: Path) -> None:
    """As rmw_zenohd started after `erni sim`: the control node's session joins the router once it runs, and
    a ROS 2 client of that router (as rviz2 is of rmw_zenohd) gets the odometry. The scenario's [ros2]
    table names the router (here on a free port, rmw_zenohd's 7447 being this machine's to use)."""
    from erni.sim.team import free_port
    from erni.transport.zenoh_wire import open_router

    domain = int(os.environ["ROS_DOMAIN_ID"])
    port = free_port()
    scenario = tmp_path / "ros2.toml"
    scenario.write_text(f'name = "ros2"\n[robots]\ncount = 1\n[ros2]\nconnect = ["tcp/127.0.0.1:{port}"]\n')
    p = sim(str(scenario), "--control-port", "0")  # no --ros2: the scenario's table turns it on
    p.wait_for("Ctrl-C stops the team", timeout=120)
    assert f"joins the router at tcp/127.0.0.1:{port} whenever one runs there" in p.wait_for("joins the", timeout=1)
    # the team runs without a router: its session tries the router's address and finds no Zenoh there
    # (a plain socket that takes the connection and resets it), then the router starts
    with socket.socket() as probe:
        probe.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        probe.bind(("127.0.0.1", port))
        probe.listen()
        probe.settimeout(30)
        try:
            conn, _ = probe.accept()
        except TimeoutError:
            raise AssertionError(f"the control node's session never tried tcp/127.0.0.1:{port}") from None
        conn.setsockopt(socket.SOL_SOCKET, socket.SO_LINGER, struct.pack("ii", 1, 0))
        conn.close()
    router = open_router([f"tcp/127.0.0.1:{port}"])
    try:
        sdk(port)
        got: list[Any] = []
        sub = ROS2Subscriber("/robot1/odom", messages.ODOMETRY, got.append, domain_id=domain)
        try:
            joined = time.monotonic()
            wait_until(lambda: got, timeout=20, message="no odometry through the router started after the team")
            print(f"odometry through the router {time.monotonic() - joined:.2f} s after it started")
            assert abs(got[-1].pose.pose.position.x) < 0.05 and abs(got[-1].pose.pose.position.y) < 0.05
        finally:
            sub.close()
    finally:
        router.close()


def test_a_scenario_key_turns_it_on_and_its_table_sets_the_plugin(tmp_path: Path) -> None:
    """`ros2 = true` or a `[ros2]` table: the control node's config runs the ros2 plugin with the sim's
    session settings under the scenario's, and `erni agent --check` takes it."""
    from erni.sim.scenario import load_scenario
    from erni.sim.team import Team, TeamError
    from erni.transport.identity import Authority

    on = tmp_path / "on.toml"
    on.write_text('name = "on"\nros2 = true\n[robots]\ncount = 1\n')
    table = tmp_path / "table.toml"
    table.write_text('name = "table"\n[robots]\ncount = 1\n[ros2]\ndomain_id = 7\nlisten = ["tcp/127.0.0.1:17555"]\n'
                     'connect = []\nodom_rate_hz = 5\n')
    off = tmp_path / "off.toml"
    off.write_text('name = "off"\n[robots]\ncount = 1\n')
    assert Team(load_scenario(off), run_dir=tmp_path / "off", headless=True).ros2 is None
    assert Team(load_scenario(off), run_dir=tmp_path / "off", headless=True, ros2=True).ros2 is not None
    assert Team(load_scenario(on), run_dir=tmp_path / "on-off", headless=True, ros2=False).ros2 is None
    with pytest.raises(TeamError, match=r"^--ros2 runs on the loopback team only, not with --netns"):
        Team(load_scenario(on), run_dir=tmp_path / "netns", headless=True, netns=True)

    team = Team(load_scenario(on), run_dir=tmp_path / "on", headless=True)
    assert team.ros2 is not None
    assert team.ros2["session"] == "own" and team.ros2["mode"] == "peer"
    assert team.ros2["connect"] == ["tcp/127.0.0.1:7447"]
    assert re.fullmatch(r"tcp/127\.0\.0\.1:\d+", team.ros2["listen"][0]) and team.ros2_listen == team.ros2["listen"]
    team = Team(load_scenario(table), run_dir=tmp_path / "table", headless=True)
    assert team.ros2 == {"session": "own", "mode": "peer", "connect": [], "domain_id": 7,
                         "listen": ["tcp/127.0.0.1:17555"], "odom_rate_hz": 5}
    # the configs the agents run with, as the team writes them (its robots not started: any robot URL)
    for sub in ("agents", "logs", "journal"):
        (team.run_dir / sub).mkdir(parents=True, exist_ok=True)
    team.configs.robot_url = lambda i: "socket://127.0.0.1:1"
    Authority.create(team.keys_dir, team="test").issue("control", "control")
    team.configs.write({"robot1": 1}, {"robot1": "c"}, 47100, 0)
    import tomllib

    config = team.agents["control"].config
    plugins = {p["class"]: p.get("settings", {}) for p in tomllib.loads(config.read_text())["plugin"]}
    assert plugins["ros2"] == team.ros2
    assert "ros2" not in {p["class"] for p in tomllib.loads(team.agents["robot1"].config.read_text())["plugin"]}
    check = subprocess.run([sys.executable, "-m", "erni", "agent", str(config), "--check"], cwd=ROOT,
                           capture_output=True, text=True, timeout=60)
    assert check.returncode == 0, check.stdout + check.stderr


def test_bad_ros2_settings_are_one_line_naming_the_file_and_key(tmp_path: Path) -> None:
    from erni.sim.scenario import ScenarioError, load_scenario

    cases = {
        '[ros2]\ndomain_id = 300\n': "ros2.domain_id: Input should be less than or equal to 232 (got 300)",
        '[ros2]\nspeed = 1\n': "ros2: unknown key 'speed'",
        'ros2 = "yes"\n': "ros2: expected true, false or a table of the ros2 plugin's settings, got 'yes'",
    }
    for text, message in cases.items():
        path = tmp_path / "bad.toml"
        path.write_text(text)
        with pytest.raises(ScenarioError) as err:
            load_scenario(path)
        assert str(err.value) == f"{path}: {message}"
    out = subprocess.run([sys.executable, "-m", "erni", "sim", "--ros2", "--headless", "--robots", "1"], cwd=ROOT,
                         capture_output=True, text=True, timeout=60, env={**os.environ, "ROS_DOMAIN_ID": "abc"})
    assert out.returncode == 2
    assert out.stderr.strip() == "erni sim: ROS_DOMAIN_ID: expected a ROS 2 domain 0-232, got 'abc'"


def test_without_zenoh_it_names_the_extra_to_install(tmp_path: Path) -> None:
    """A Python without eclipse-zenoh (a `zenoh` that cannot be imported first on the path): one line, exit 2,
    before anything starts."""
    fake = tmp_path / "nozenoh" / "zenoh"
    fake.mkdir(parents=True)
    (fake / "__init__.py").write_text('raise ModuleNotFoundError("No module named \'zenoh\'", name="zenoh")\n')
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(fake.parent), os.environ.get("PYTHONPATH", "")])}
    out = subprocess.run([sys.executable, "-m", "erni", "sim", "--ros2", "--headless", "--robots", "1",
                          "--run-dir", str(tmp_path / "run")], cwd=ROOT, capture_output=True, text=True, timeout=60,
                         env=env)
    assert out.returncode == 2, out.stdout + out.stderr
    assert out.stderr.strip() == "erni sim: --ros2 needs eclipse-zenoh, which is not installed: pip install 'erni[ros2]'"
    assert not (tmp_path / "run").exists()
