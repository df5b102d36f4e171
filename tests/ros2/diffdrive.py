"""A simulated differential-drive ROS 2 base, written with zenoh-ros2-sdk (its own node, not ERNI's code):
the base tests/ros2/test_ros2_base.py drives, and, run as a program, the robot of the motion suite's
real-robot mode:

    python -m tests.ros2.diffdrive --listen tcp/127.0.0.1:7447 --namespace /robot1 &
    ERNI_ROBOT_URL="ros2://robot1?connect=tcp/127.0.0.1:7447&mode=client" python -m pytest -n 0 tests/motion

(the program runs a Zenoh router on --listen and the base on it until interrupted).
"""

from __future__ import annotations

import argparse
import math
import signal
import tempfile
import threading
import time
from pathlib import Path
from typing import Any

import numpy as np
from zenoh_ros2_sdk import ROS2Publisher, ROS2Subscriber

from erni import ros2_messages as messages

VEC = "geometry_msgs/msg/Vector3"


class DiffDriveBase:
    """A differential-drive base as a ROS 2 driver node shows it: it follows the newest cmd_vel within
    its acceleration limits, stops when cmd_vel goes quiet for 0.5 s (as TurtleBot's firmware does),
    integrates its pose at 50 Hz, publishes Odometry at 20 Hz, a 360-beam LaserScan (of a wall at
    x = `wall`, if any) at 10 Hz and a BatteryState (12.3 V) at 5 Hz."""

    def __init__(self, port: int, ns: str = "/tb3", wall: float | None = None) -> None:
        self.x = self.y = self.th = 0.0
        self.v = self.w = 0.0
        self.cmd = (0.0, 0.0)
        self.cmd_at = -math.inf
        self.wall = wall
        self.commands = 0
        self.silent = threading.Event()
        self.lock = threading.Lock()
        self.odom = ROS2Publisher(f"{ns}/odom", messages.ODOMETRY, router_port=port, node_name="tb3_base")
        self.scan = ROS2Publisher(f"{ns}/scan", messages.LASER_SCAN, router_port=port, node_name="tb3_laser")
        self.battery = ROS2Publisher(f"{ns}/battery_state", "sensor_msgs/msg/BatteryState", router_port=port,
                                     node_name="tb3_power")
        self.sub = ROS2Subscriber(f"{ns}/cmd_vel", messages.TWIST, self._on_cmd, router_port=port,
                                  node_name="tb3_base_cmd")
        self.closing = threading.Event()
        self.thread = threading.Thread(target=self._loop, name="test-diffdrive")
        self.thread.start()

    def _on_cmd(self, msg: Any) -> None:
        with self.lock:
            self.cmd = (float(msg.linear.x), float(msg.angular.z))
            self.cmd_at = time.monotonic()
            self.commands += 1

    def _loop(self) -> None:
        dt, tick = 0.02, 0
        while not self.closing.wait(dt):
            with self.lock:
                v, w = self.cmd if time.monotonic() - self.cmd_at < 0.5 else (0.0, 0.0)
                self.v += max(-1.5 * dt, min(1.5 * dt, v - self.v))
                self.w += max(-6.0 * dt, min(6.0 * dt, w - self.w))
                self.th = math.atan2(math.sin(self.th + self.w * dt), math.cos(self.th + self.w * dt))
                self.x += self.v * math.cos(self.th) * dt
                self.y += self.v * math.sin(self.th) * dt
                x, y, th, lv, aw = self.x, self.y, self.th, self.v, self.w
            tick += 1
            if self.silent.is_set():
                continue
            stamp = messages.header(time.time_ns(), "odom")
            if tick % 2 == 0:
                self.odom.publish(
                    header=stamp, child_frame_id="base_footprint",
                    pose=messages.make("geometry_msgs/msg/PoseWithCovariance", pose=messages.make(
                        "geometry_msgs/msg/Pose", position=messages.make("geometry_msgs/msg/Point", x=x, y=y),
                        orientation=messages.quaternion(th))),
                    twist=messages.make("geometry_msgs/msg/TwistWithCovariance", twist=messages.make(
                        messages.TWIST, linear=messages.make(VEC, x=lv), angular=messages.make(VEC, z=aw))))
            if tick % 10 == 0:
                power = messages.make("sensor_msgs/msg/BatteryState", header=messages.header(time.time_ns(), ""),
                                      voltage=12.3, present=True)
                self.battery.publish(**{f: getattr(power, f) for f in power.__dataclass_fields__
                                        if f != "__msgtype__"})
            if tick % 5 == 0:
                angles = -math.pi + np.arange(360) * (2 * math.pi / 360)
                with np.errstate(divide="ignore"):
                    cos = np.cos(th + angles)
                    ranges = np.full(360, np.inf) if self.wall is None else \
                        np.where(cos > 1e-6, (self.wall - x) / np.where(cos > 1e-6, cos, 1.0), np.inf)
                self.scan.publish(header=messages.header(time.time_ns(), "base_scan"), angle_min=-math.pi,
                                  angle_max=math.pi - 2 * math.pi / 360, angle_increment=2 * math.pi / 360,
                                  time_increment=0.0, scan_time=0.1, range_min=0.12, range_max=3.5,
                                  ranges=ranges.astype(np.float32), intensities=np.zeros(0, dtype=np.float32))

    def close(self) -> None:
        self.closing.set()
        self.thread.join()
        for entity in (self.sub, self.odom, self.scan, self.battery):
            entity.close()


def main(argv: list[str] | None = None) -> int:
    from zenoh_ros2_sdk import message_registry
    from zenoh_ros2_sdk.session import ZenohSession

    from erni.transport.zenoh_wire import open_router
    from tests.ros2.conftest import write_definitions

    parser = argparse.ArgumentParser(prog="python -m tests.ros2.diffdrive", description=__doc__.splitlines()[0])
    parser.add_argument("--listen", default="tcp/127.0.0.1:7447", help="the Zenoh router's endpoint")
    parser.add_argument("--namespace", default="/robot1", help="the base's topics: NAMESPACE/cmd_vel, /odom, /scan")
    parser.add_argument("--wall", type=float, default=None, help="a wall at this x (m) in the LaserScan")
    args = parser.parse_args(argv)
    port = int(args.listen.rsplit(":", 1)[1])
    router = open_router([args.listen])
    with tempfile.TemporaryDirectory() as folder:
        message_registry.get_registry(str(write_definitions(Path(folder))))
        ZenohSession.get_instance("127.0.0.1", port)
        base = DiffDriveBase(port, ns=args.namespace, wall=args.wall)
        done = threading.Event()
        signal.signal(signal.SIGINT, lambda *_: done.set())
        signal.signal(signal.SIGTERM, lambda *_: done.set())
        print(f"base {args.namespace} on {args.listen}", flush=True)
        done.wait()
        base.close()
        ZenohSession.get_instance().close()
    router.close()
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
