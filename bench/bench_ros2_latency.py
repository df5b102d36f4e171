"""ROS 2 odometry latency: a Pose's stamp -> its nav_msgs/Odometry at a zenoh-ros2-sdk subscriber.

One agent runs the motion plugin on ERNI's simulated robot (two rows: as a Pioneer reports, a SIP
every 100 ms and a Pose 10 times a second, the default `odom_rate_hz`; and a robot twice as fast,
which the plugin thins to `odom_rate_hz`) and the ros2 plugin on a Zenoh session of its own, in client mode, connected to a
Zenoh router in this process (as rmw_zenoh's `rmw_zenohd`). A ROS 2 subscriber, ROBOTIS'
zenoh-ros2-sdk (an independent rmw_zenoh client, its message definitions written from rosbags' Jazzy
store), listens to `/robot1/odom` through the router while the robot drives a slow circle, so every
Pose differs from the one before. Latency: the subscriber's callback time minus the Odometry's header
stamp (the Pose's own stamp), both on this machine's wall clock.

Where the time goes (medians over the same messages): the Pose's stamp -> the ros2 plugin's run that
takes it (the blackboard's delivery and the scheduler) -> the message handed to the plugin's sender
thread (the `odom_rate_hz` limit holds a pose back here) -> its Zenoh put -> the subscriber.

The floor, measured in the same run: a bare Zenoh session of its own (client, the same router) puts
the same Odometry bytes with an rmw_zenoh attachment on a topic the same SDK subscribes to, stamped
just before the put: Zenoh's delivery through the router plus the SDK's decoding, nothing of ERNI.
ratio = median latency / floor median.

    python bench/bench_ros2_latency.py [--poses 200] [--odom-rate-hz 10]
"""

from __future__ import annotations

import argparse
import statistics
import sys
import tempfile
import threading
import time
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

import zenoh  # noqa: E402

from erni import ros2_messages as messages  # noqa: E402
from erni import ros2_rmw as rmw  # noqa: E402
from erni.blackboard import Agent, Pose, Task  # noqa: E402
from erni.plugins.motion import RobotMotionControl  # noqa: E402
from erni.plugins.ros2 import ROS2Plugin  # noqa: E402
from erni.sim.team import free_port  # noqa: E402
from erni.transport.zenoh_wire import open_router  # noqa: E402


def stats(xs: list[float]) -> tuple[float, float, float]:
    """(median, p95, max) of `xs` (ms)."""
    ys = sorted(xs)
    return statistics.median(ys), ys[min(len(ys) - 1, int(0.95 * len(ys)))], ys[-1]


def sdk_session(port: int, definitions: Path) -> Any:
    """The SDK's shared session on the router, its registry reading `definitions` (nothing fetched)."""
    import os

    from zenoh_ros2_sdk import message_registry
    from zenoh_ros2_sdk.session import ZenohSession

    os.environ["ZENOH_ROS2_SDK_CACHE"] = str(definitions / "no-cache")
    os.environ.pop("ROS_DOMAIN_ID", None)
    message_registry._registry = None
    message_registry.get_registry(str(definitions))
    ZenohSession._instance = None
    return ZenohSession.get_instance("127.0.0.1", port)


def wait(condition: Any, timeout: float, what: str) -> None:
    end = time.monotonic() + timeout
    while not condition():
        if time.monotonic() > end:
            raise SystemExit(f"bench_ros2_latency: {what} within {timeout:g} s")
        time.sleep(0.01)


def floor(port: int, n: int, period: float) -> list[float]:
    """Bare Zenoh put (a session of its own, client) -> the SDK's subscriber, the Odometry's bytes, ms."""
    from zenoh_ros2_sdk import ROS2Subscriber

    topic = "/floor/odom"
    pose = Pose(robot="robot1", x=1.0, y=2.0, theta=0.5, v=0.2, w=0.1)
    lat: list[float] = []
    sub = ROS2Subscriber(topic, messages.ODOMETRY, lambda m: lat.append(
        (time.time_ns() - (m.header.stamp.sec * 10**9 + m.header.stamp.nanosec)) / 1e6), router_port=port)
    conf = zenoh.Config()
    conf.insert_json5("mode", '"client"')
    conf.insert_json5("connect/endpoints", f'["tcp/127.0.0.1:{port}"]')
    conf.insert_json5("scouting/multicast/enabled", "false")
    session = zenoh.open(conf)
    key = rmw.topic_key(0, topic, messages.ODOMETRY)
    pub = session.declare_publisher(key, encoding=zenoh.Encoding("application/cdr"))
    gid = bytes(16)
    try:
        wait(lambda: pub.matching_status.matching, 20, "the floor's publisher found no subscriber")
        for i in range(n + 5):
            stamp = time.time_ns()
            payload = messages.serialize(messages.odometry(pose, stamp, "robot1/odom"))
            pub.put(payload, attachment=rmw.attachment(i + 1, stamp, gid))
            time.sleep(period)
        wait(lambda: len(lat) >= n, 10, f"the floor's subscriber got {len(lat)} of {n}")
    finally:
        sub.close()
        pub.undeclare()
        session.close()
    return lat[5:n + 5]


class Stages:
    """When the ros2 plugin took each Pose (its run), handed its Odometry over and put it, by stamp (ns)."""

    def __init__(self, plugin: ROS2Plugin) -> None:
        self.taken: dict[int, int] = {}
        self.handed: dict[int, int] = {}
        self.put: dict[int, int] = {}
        publish, send = plugin._publish_poses, plugin._send

        def publish_poses(robots: set[str]) -> None:
            now = time.time_ns()
            for pose in [*plugin.poses.added, *plugin.poses.changed]:
                self.taken.setdefault(messages.stamp_ns_of(pose.stamp), now)
            publish(robots)

        def handed(typename: str, topic: str, msg: Any, stamp_ns: int) -> None:
            if typename == messages.ODOMETRY:
                self.handed[stamp_ns] = time.time_ns()
            send(typename, topic, msg, stamp_ns)

        plugin._publish_poses = publish_poses  # type: ignore[method-assign]
        plugin._send = handed  # type: ignore[method-assign]
        put = rmw.Publisher.put
        stages = self

        def timed_put(pub: rmw.Publisher, payload: bytes, stamp_ns: int | None = None) -> None:
            if pub.typename == messages.ODOMETRY and stamp_ns is not None:
                stages.put[stamp_ns] = time.time_ns()
            put(pub, payload, stamp_ns)

        rmw.Publisher.put = timed_put  # type: ignore[method-assign]
        self._put = put

    def close(self) -> None:
        rmw.Publisher.put = self._put  # type: ignore[method-assign]


def measure(port: int, n: int, pose_rate: float, odom_rate: float,
            sip_period: float = 0.1) -> tuple[list[float], dict[str, list[float]], float, float]:
    """(latency ms per Odometry received, the stages' ms, Poses a second the plugin took while they were
    received, Odometry messages a second received)."""
    from zenoh_ros2_sdk import ROS2Subscriber

    agent = Agent("robot1", workers=2)
    agent.add_plugin(RobotMotionControl, settings={"url": f"simrobot://?name=robot1&sip_period={sip_period:g}",
                                                     "pose_rate_hz": pose_rate},
                     name="motion")
    agent.add_plugin(ROS2Plugin, settings={"session": "own", "mode": "client", "connect": [f"tcp/127.0.0.1:{port}"],
                                           "odom_rate_hz": odom_rate, "sonar": False}, name="ros2")
    plugin = agent.plugin("ros2")
    assert isinstance(plugin, ROS2Plugin)
    stages = Stages(plugin)
    arrivals: list[tuple[int, int]] = []  # (stamp, arrival) ns
    lock = threading.Lock()

    def heard(msg: Any) -> None:
        now = time.time_ns()
        with lock:
            arrivals.append((msg.header.stamp.sec * 10**9 + msg.header.stamp.nanosec, now))

    sub = ROS2Subscriber("/robot1/odom", messages.ODOMETRY, heard, router_port=port)
    poses: list[int] = []
    agent.start()
    try:
        wait(lambda: plugin.node is not None and "/robot1/odom" in plugin.node.publishers
             and plugin.node.publishers["/robot1/odom"]._pub.matching_status.matching, 20,
             "ERNI's odometry publisher found no subscriber")
        with agent.transaction() as tx:  # a slow circle: every Pose differs from the last
            tx.add(Task(verb="BotMotion", preposition="velocity", params={"v": 0.2, "w": 20.0}, source="robot1"))
        wait(lambda: arrivals, 10, "no Odometry arrived")
        with lock:
            arrivals.clear()
        seen: set[int] = set()

        def count() -> bool:
            for pose in agent.query(Pose):
                stamp = messages.stamp_ns_of(pose.stamp)
                if stamp not in seen:
                    seen.add(stamp)
                    poses.append(stamp)
            return len(arrivals) >= n

        wait(count, n / min(pose_rate, odom_rate) * 3 + 10, f"{n} Odometry messages did not arrive")
    finally:
        sub.close()
        agent.stop()
        stages.close()
    with lock:
        got = arrivals[:n]
    lat = [(arrival - stamp) / 1e6 for stamp, arrival in got]
    parts: dict[str, list[float]] = {"Pose stamp -> the plugin's run": [], "run -> handed to the sender": [],
                                     "handed -> Zenoh put": [], "put -> the SDK's callback": []}
    for stamp, arrival in got:
        taken, handed, put = stages.taken.get(stamp), stages.handed.get(stamp), stages.put.get(stamp)
        if taken is None or handed is None or put is None:
            continue
        for name, (a, b) in zip(parts, ((stamp, taken), (taken, handed), (handed, put), (put, arrival)), strict=True):
            parts[name].append((b - a) / 1e6)
    first, last = got[0][0], got[-1][0]
    taken = sum(1 for stamp in stages.taken if first <= stamp <= last)
    return lat, parts, (taken - 1) / ((last - first) / 1e9), (len(got) - 1) / ((last - first) / 1e9)


ROWS = (("a Pioneer's rate: Pose 10 Hz (SIP 100 ms)", 0.1, 10.0),
        ("a faster robot: Pose 20 Hz (SIP 20 ms), thinned", 0.02, 25.0))


def main() -> int:
    import results  # bench/results.py, beside this script: the latest results, for the site's benchmarks page

    from tests.ros2.conftest import write_definitions

    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--poses", type=int, default=200, help="Odometry messages measured per row (and floor samples)")
    ap.add_argument("--odom-rate-hz", type=float, default=10.0, help="the ros2 plugin's odom_rate_hz")
    results.add_argument(ap)
    args = ap.parse_args()
    port = free_port()
    router = open_router([f"tcp/127.0.0.1:{port}"])
    measured = []
    try:
        with tempfile.TemporaryDirectory(prefix="erni-bench-ros2-") as tmp:
            session = sdk_session(port, write_definitions(Path(tmp)))
            try:
                base = floor(port, args.poses, 1.0 / args.odom_rate_hz)
                for name, sip_period, pose_rate in ROWS:
                    measured.append((name, *measure(port, args.poses, pose_rate, args.odom_rate_hz, sip_period)))
            finally:
                session.close()
    finally:
        router.close()
    fm, fp, fx = stats(base)
    print(f"floor: bare Zenoh put -> the SDK's subscriber, median {fm:.2f} ms, p95 {fp:.2f}, max {fx:.2f} "
          f"({len(base)} messages)")
    targets, tables = [], []
    for name, lat, parts, pose_hz, odom_hz in measured:
        med, p95, mx = stats(lat)
        print(f"{name}: Pose stamp -> Odometry at the SDK, median {med:.2f} ms, p95 {p95:.2f}, max {mx:.2f}, "
              f"n {len(lat)}, ratio {med / fm:.1f}; Poses {pose_hz:.2f}/s, Odometry {odom_hz:.2f}/s")
        for stage, xs in parts.items():
            if xs:
                m, p, x = stats(xs)
                print(f"  {stage:<34} median {m:6.2f} ms  p95 {p:6.2f}  max {x:6.2f}")
        targets.append(results.target(
            f"Pose stamp → Odometry at a zenoh-ros2-sdk subscriber, {name} (Odometry {odom_hz:.1f}/s)",
            "within 5 ms of the floor (median)", f"bare Zenoh put → the same subscriber, {fm:.2f} ms",
            f"{med / fm:.1f}x ({med:.1f} ms median, p95 {p95:.1f}, max {mx:.1f})", med <= fm + 5.0))
        rows = "\n".join(f"| {stage} | {stats(xs)[0]:.2f} | {stats(xs)[1]:.2f} | {stats(xs)[2]:.2f} |"
                         for stage, xs in parts.items() if xs)
        tables.append({"title": f"where the time goes, {name} (ms)",
                       "markdown": "| stage | median | p95 | max |\n|---|---|---|---|\n" + rows})
    results.write("bench_ros2_latency", targets, path=args.results, tables=tables,
                  about="a Pose's stamp → its Odometry at a ROS 2 subscriber through a Zenoh router, "
                        "beside a bare Zenoh put to the same subscriber")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
