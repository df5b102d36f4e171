"""`simrobot://` — a simulated ARCOS robot served in the calling process, opened like a serial port.

    simrobot://                                      a Pioneer 3 in an empty world
    simrobot://?world=examples/world-corridor.toml   in that world (its first start pose)
    simrobot://?model=amigo&sip_period=0.05&name=robot1&sonar_cycle=0

Opening the URL starts a `RobotHost` with one robot on a free loopback TCP port and connects
to it as `socket://` does; closing the port stops the host. Everything on the wire is ARCOS
bytes, exactly as with a real robot or MobileSim.
"""

from __future__ import annotations

import math
import urllib.parse

from serial import SerialException
from serial.urlhandler.protocol_socket import Serial as SocketSerial

from erni.blackboard.errors import ConfigError
from erni.plugins.motion.robots import MODELS, lookup
from erni.sim.robot import SimRobotConfig
from erni.sim.robot_host import RobotHost
from erni.sim.world import World

OPTIONS = ("world", "model", "sip_period", "name", "sonar_cycle")


def robot_config(query: dict[str, str]) -> tuple[World, SimRobotConfig]:
    """Return the world and robot a `simrobot://` query asks for (raise ConfigError naming the option)."""
    unknown = sorted(set(query) - set(OPTIONS))
    if unknown:
        raise ConfigError(f"simrobot://: unknown option {unknown[0]!r}; expected some of {', '.join(OPTIONS)}")
    world = World.load(query["world"]) if query.get("world") else World()
    model = query.get("model", "p3dx-sh").strip()
    name = query.get("name", "sim")
    period, cycle = _seconds(query, "sip_period", 0.1), _seconds(query, "sonar_cycle", 0.04)
    if not 0 < period <= 10:
        raise ConfigError(f"simrobot://: sip_period: expected seconds in (0, 10], got {query['sip_period']!r}")
    if not 0 <= cycle <= 1:
        raise ConfigError(f"simrobot://: sonar_cycle: expected seconds in [0, 1], got {query['sonar_cycle']!r}")
    if lookup(model) is None:
        raise ConfigError(f"simrobot://: model: unknown robot model {model!r}; expected one of "
                          f"{', '.join(MODELS)} (or pioneer3, amigobot)")
    return world, SimRobotConfig.for_model(model, name=name, sip_period=period, sonar_cycle=cycle)


def _seconds(query: dict[str, str], key: str, default: float) -> float:
    try:
        return float(query.get(key, default))
    except ValueError:
        return math.nan


class Serial(SocketSerial):  # type: ignore[misc]  # pyserial ships no type information
    """A pyserial port whose far end is a simulated robot this port starts and stops."""

    _host: RobotHost | None = None

    def from_url(self, url: str) -> tuple[str, int]:
        parts = urllib.parse.urlsplit(url)
        if parts.scheme != "simrobot":
            raise SerialException(f"expected a simrobot:// URL, got {url!r}")
        query = {k: v[-1] for k, v in urllib.parse.parse_qs(parts.query, keep_blank_values=True).items()}
        try:
            world, config = robot_config(query)
        except ConfigError as err:
            raise SerialException(str(err)) from None
        self._stop_host()
        host = RobotHost(world)
        host.add_robot(config)
        self._host = host.start()
        _, address = host.url(0).split("://", 1)
        name, port = address.rsplit(":", 1)
        return name, int(port)

    def close(self) -> None:
        super().close()
        self._stop_host()

    def _stop_host(self) -> None:
        if self._host is not None:
            self._host.stop()
            self._host = None


