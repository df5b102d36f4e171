"""A ROS 2 base as the motion plugin's robot: `url = "ros2://<namespace>"`.

Any base that takes geometry_msgs/Twist on `<namespace>/cmd_vel` and publishes nav_msgs/Odometry on
`<namespace>/odom` (TurtleBot 3/4, Clearpath, a Nav2 simulation) over rmw_zenoh (ROS 2 Jazzy) is
driven by the same behaviour stack as an ARCOS robot: `Ros2BaseDriver` has `ArcosDriver`'s interface,
each Odometry taking the place of a SIP and each VEL/RVEL pair becoming one Twist. A
sensor_msgs/LaserScan on `<namespace>/scan` becomes a ring of virtual sonars (the nearest echo in
each of 16 sectors around the base), so obstacle avoidance works as with a Pioneer's sonar; a
sensor_msgs/BatteryState on `<namespace>/battery_state` gives the battery voltage.

The URL's query sets the link: `ros2://tb3?connect=tcp/192.0.2.20:7447&mode=client&domain=0&scan=scan`
(`connect` may repeat; default `tcp/127.0.0.1:7447`, peer mode, domain 0 or `ROS_DOMAIN_ID`,
`scan=` (empty) for no laser, `battery=` for no battery topic).
"""

from __future__ import annotations

import json
import logging
import math
import os
import threading
from collections.abc import Mapping
from dataclasses import replace
from typing import Any
from urllib.parse import parse_qs, urlsplit

from erni.blackboard.errors import ConfigError
from erni.plugins.motion.driver import ArcosDriver, LinkError, RobotState, _wrap
from erni.plugins.motion.robots import ModelSpec, RobotModel

log = logging.getLogger(__name__)

SCHEME = "ros2"
SECTORS = 16  # virtual sonars made of a LaserScan, one per 22.5 degrees
MAX_RANGE = 5.0  # m: a sector with nothing nearer reads this (as a Pioneer's sonar reads its maximum)
BATTERY_STATE = "sensor_msgs/msg/BatteryState"
BATTERY_WAIT = 1.0  # s: how long the first Odometry waits for a BatteryState before the state goes without
RECONNECT = 2.0  # s between attempts to open a session whose router is not reachable
KEEPALIVE = 0.2  # s: a moving command is sent again this often (a ROS 2 base stops when cmd_vel goes quiet)


def is_ros2_url(url: str) -> bool:
    """True for a `ros2://` URL."""
    return url.strip().lower().startswith(f"{SCHEME}://")


def parse_url(url: str) -> dict[str, Any]:
    """The parts of a `ros2://` URL: namespace ('' or '/tb3'), connect, mode, domain, scan and battery topics.
    ConfigError naming the URL when a part is wrong."""
    from erni.transport.zenoh_keys import check_endpoint

    parts = urlsplit(url.strip())
    if parts.scheme.lower() != SCHEME:
        raise ConfigError(f"{url!r}: expected ros2://NAMESPACE")
    names = [n for n in (parts.netloc + parts.path).split("/") if n]
    for n in names:
        if not n.replace("_", "a").isalnum() or n[0].isdigit():
            raise ConfigError(f"{url!r}: namespace part {n!r} is not a ROS 2 name (letters, digits, '_')")
    query = parse_qs(parts.query, keep_blank_values=True)
    unknown = sorted(set(query) - {"connect", "mode", "domain", "scan", "battery"})
    if unknown:
        raise ConfigError(f"{url!r}: unknown parameter {unknown[0]!r}; expected connect, mode, domain, scan, "
                          "battery")
    connect = [e for v in query.get("connect", []) for e in v.split(",") if e] or ["tcp/127.0.0.1:7447"]
    for endpoint in connect:
        check_endpoint(endpoint)
    mode = query.get("mode", ["peer"])[-1]
    if mode not in ("peer", "client"):
        raise ConfigError(f"{url!r}: mode {mode!r}; expected peer or client")
    domain_text = query.get("domain", [os.environ.get("ROS_DOMAIN_ID", "0") or "0"])[-1]
    if not domain_text.isdigit() or int(domain_text) > 232:
        raise ConfigError(f"{url!r}: domain {domain_text!r}; expected 0-232")
    scan = query.get("scan", ["scan"])[-1].strip("/")
    battery = query.get("battery", ["battery_state"])[-1].strip("/")
    return {"namespace": "/" + "/".join(names) if names else "", "connect": connect, "mode": mode,
            "domain": int(domain_text), "scan": scan, "battery": battery}


def sonar_ring() -> tuple[tuple[float, float, float], ...]:
    """The virtual sonars' poses: at the base's centre, one every 360/SECTORS degrees from ahead."""
    return tuple((0.0, 0.0, (i * 360.0 / SECTORS + 180.0) % 360.0 - 180.0) for i in range(SECTORS))


def scan_sectors(angle_min: float, angle_increment: float, ranges: Any, range_min: float,
                 range_max: float) -> dict[int, float]:
    """The nearest valid echo of a LaserScan in each sector (m, at most MAX_RANGE); sectors the scan does
    not cover are left out."""
    out: dict[int, float] = {}
    width = 2 * math.pi / SECTORS
    for i, r in enumerate(ranges):
        a = angle_min + i * angle_increment
        sector = round(_wrap(a) / width) % SECTORS
        value = float(r)
        if not math.isfinite(value) or value > range_max or value < range_min:
            value = MAX_RANGE
        out[sector] = min(out.get(sector, MAX_RANGE), value, MAX_RANGE)
    return out


class Ros2BaseDriver(ArcosDriver):
    """A ROS 2 base (cmd_vel in, odom and scan out) behind ArcosDriver's interface."""

    def __init__(self, url: str, model: str | Mapping[str, Any] | RobotModel | ModelSpec | None = None, *,
                 name: str = "robot", link_timeout: float = 1.0, **_: Any) -> None:
        self.link = parse_url(url)
        super().__init__(url, model, name=name, link_timeout=link_timeout, send_limits=False)
        if self.link["scan"]:
            self.model = self.model.model_copy(update={"sonar": sonar_ring()})
        self.sip_interval = 0.05
        self._session: Any = None
        self._opened = False  # open() was called (and close() not since)
        self._next_open = -math.inf
        self._node: Any = None
        self._cmd: Any = None
        self._v = 0.0
        self._w = 0.0  # deg/s, as RVEL takes it
        self._odom_at = -math.inf
        self._first_odom = -math.inf
        self._battery: float | None = None
        self._sent_at = -math.inf
        self._seq = 0
        self._lock = threading.Lock()

    def _topic(self, name: str) -> str:
        return f"{self.link['namespace']}/{name}"

    # --- life cycle ---------------------------------------------------------------------

    def open(self, wait: bool = True, timeout: float | None = None) -> ArcosDriver:
        """Join the ROS 2 graph (a Zenoh session, a node, the cmd_vel publisher, the odom and scan
        subscriptions); with wait=True, block until the first Odometry or raise LinkError."""
        import zenoh

        from erni import ros2_messages as messages
        from erni.ros2_rmw import SENSOR_QOS, RmwNode

        self._opened = True
        if self._session is None:
            conf = zenoh.Config()
            for key, value in (("mode", self.link["mode"]), ("connect/endpoints", self.link["connect"]),
                               ("scouting/multicast/enabled", False)):
                conf.insert_json5(key, json.dumps(value))
            self._next_open = self.clock() + RECONNECT
            try:
                self._session = zenoh.open(conf)
            except zenoh.ZError as err:  # a client whose router is not up yet: `connected` tries again
                self.last_error = "cannot open a Zenoh session: " + (str(err).splitlines()[0].split(" at /")[0]
                                                                     if str(err) else repr(err))
                if wait:
                    raise LinkError(f"{self.url}: {self.last_error}") from None
                return self
            node_name = "erni_" + "".join(c if c.isalnum() or c == "_" else "_" for c in self.name) + "_base"
            self._node = RmwNode(self._session, node_name, domain_id=self.link["domain"])
            self._cmd = self._node.publisher(self._topic("cmd_vel"), messages.TWIST)
            self._node.subscribe(self._topic("odom"), messages.ODOMETRY, self._on_odom)
            if self.link["scan"]:
                self._node.subscribe(self._topic(self.link["scan"]), messages.LASER_SCAN, self._on_scan,
                                     qos=SENSOR_QOS)
            if self.link["battery"]:
                self._node.subscribe(self._topic(self.link["battery"]), BATTERY_STATE, self._on_battery,
                                     qos=SENSOR_QOS)
        if wait:
            limit = timeout if timeout is not None else 3.0 + self.link_timeout
            with self._cond:
                if not self._cond.wait_for(lambda: self.connected, limit):
                    self.last_error = self.last_error or f"no Odometry on {self._topic('odom')}"
                    raise LinkError(f"{self.url}: cannot connect to the robot: {self.last_error}")
        return self

    def close(self) -> None:
        """Stop the base (a zero Twist), leave the graph, close the session."""
        self._opened = False
        if self._session is None:
            return
        self.stop()
        self._node.close()
        self._session.close()
        self._session = self._node = self._cmd = None

    @property
    def connected(self) -> bool:
        """True while Odometry keeps coming (one within link_timeout); else `last_error` says why. Without a
        session (the router was not reachable) it tries to open one every RECONNECT seconds."""
        if self._session is None:
            if self._opened and self.clock() >= self._next_open:
                self.open(wait=False)
            return False
        if self.clock() - self._odom_at <= self.link_timeout:
            return True
        self.last_error = f"no Odometry on {self._topic('odom')} within {self.link_timeout:g} s"
        return False

    @property
    def is_simulator(self) -> bool:
        return False

    # --- the base's topics (Zenoh's threads) -----------------------------------------------

    def _on_odom(self, data: bytes) -> None:
        from erni import ros2_messages as messages

        try:
            odom = messages.deserialize(data, messages.ODOMETRY)
        except Exception as err:  # a damaged or foreign sample: counted and skipped, the link goes on
            self.stats.bad_sips += 1
            self.last_error = f"bad Odometry: {err}"
            return
        now = self.clock()
        p, t = odom.pose.pose, odom.twist.twist
        ox, oy, oth = float(p.position.x), float(p.position.y), messages.yaw(p.orientation)
        v, w = float(t.linear.x), float(t.angular.z)
        if not all(math.isfinite(value) for value in (ox, oy, oth, v, w)):  # no pose is made of NaN
            self.stats.bad_sips += 1
            self.last_error = (f"bad Odometry: expected finite numbers, got x {ox}, y {oy}, heading {oth}, "
                               f"v {v}, w {w}")
            return
        half = self.model.track / 2
        if self._first_odom == -math.inf:
            self._first_odom = now
        if self.link["battery"] and self._battery is None and now - self._first_odom < BATTERY_WAIT:
            return  # the first state waits a moment for the battery, so that no Pose says 0 V
        with self._cond:
            if self._odom_at > -math.inf:
                self.sip_interval = 0.9 * self.sip_interval + 0.1 * min(1.0, max(1e-3, now - self._odom_at))
            self._odom_at = self._last_sip = now
            self._raw_odo = (ox, oy, oth)
            fx, fy, fth = self._frame
            c, s = math.cos(fth), math.sin(fth)
            self._seq += 1
            self._state = RobotState(
                x=fx + c * ox - s * oy, y=fy + s * ox + c * oy, theta=_wrap(oth + fth), v=v, w=w,
                left=v - w * half, right=v + w * half, battery=self._battery or 0.0, stall_left=False, stall_right=False,
                bumpers=0, motors_enabled=True, moving=abs(v) > 1e-3 or abs(w) > 1e-3, sonar=dict(self._sonar),
                stamp=now, seq=self._seq)
            self.stats.sips += 1
            state = self._state
            self._cond.notify_all()
        if self.on_sip is not None:
            self.on_sip(state)
        with self._lock:  # between the stack's commands, the one standing is repeated for the base's watchdog
            if (self._v or self._w) and now - self._sent_at >= KEEPALIVE:
                self._send()

    def _on_battery(self, data: bytes) -> None:
        from erni import ros2_messages as messages

        try:
            voltage = float(messages.deserialize(data, BATTERY_STATE).voltage)
        except Exception as err:  # as for odometry
            self.last_error = f"bad BatteryState: {err}"
            return
        if math.isfinite(voltage):
            self._battery = round(voltage, 2)

    def _on_scan(self, data: bytes) -> None:
        from erni import ros2_messages as messages

        try:
            scan = messages.deserialize(data, messages.LASER_SCAN)
        except Exception as err:  # as for odometry
            self.last_error = f"bad LaserScan: {err}"
            return
        sectors = scan_sectors(float(scan.angle_min), float(scan.angle_increment), scan.ranges,
                               float(scan.range_min), float(scan.range_max))
        with self._cond:
            self._sonar = sectors
            if self._state is not None:
                self._state = replace(self._state, sonar=dict(sectors))

    # --- commands -----------------------------------------------------------------------

    def command(self, cmd: int, arg: int | bytes | str | None = None) -> bool:
        """ARCOS commands other than those below have no ROS 2 counterpart: not sent."""
        self.stats.dropped_commands += 1
        return False

    def _send(self) -> bool:
        from erni import ros2_messages as messages

        if self._cmd is None or not self.connected:
            self.stats.dropped_commands += 1
            return False
        vec = "geometry_msgs/msg/Vector3"
        twist = messages.make(messages.TWIST, linear=messages.make(vec, x=self._v),
                              angular=messages.make(vec, z=math.radians(self._w)))
        self._cmd.put(messages.serialize(twist))
        self._sent_at = self.clock()
        self.stats.commands += 1
        return True

    def vel(self, v: float) -> bool:
        """Translate at v (m/s): taken now, sent with the next rvel (a Twist has both)."""
        with self._lock:
            self._v = v
        return self._cmd is not None and self.connected

    def rvel(self, deg_s: float) -> bool:
        """Rotate at deg_s (deg/s): sends the Twist (linear.x from vel, angular.z in rad/s)."""
        with self._lock:
            self._w = deg_s
            return self._send()

    def stop(self) -> bool:
        """A zero Twist."""
        with self._lock:
            self._v = self._w = 0.0
            return self._send()

    def say(self, tones: bytes | str) -> bool:
        self.last_error = "a ROS 2 base plays no tones"
        return False

    def sim_set_pose(self, x: float, y: float, heading_deg: float) -> bool:
        """Not a simulator ERNI can move: odometry is re-based instead."""
        self.relocalise(x, y, math.radians(heading_deg))
        return True
