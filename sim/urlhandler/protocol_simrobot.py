"""`simrobot://` — a simulated ARCOS robot served in the calling process, opened like a serial port.

    simrobot://                                      a Pioneer 3 in an empty world
    simrobot://?world=examples/world-corridor.toml   in that world (its first start pose)
    simrobot://?model=amigobot&sip_period=0.05&name=robot1

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
from erni.sim.robot import SimRobotConfig
from erni.sim.robot_host import RobotHost
from erni.sim.world import World

OPTIONS = ("world", "model", "sip_period", "name")


def robot_config(query: dict[str, str]) -> tuple[World, SimRobotConfig]:
    """Return the world and robot a `simrobot://` query asks for (raise ConfigError naming the option)."""
    unknown = sorted(set(query) - set(OPTIONS))
    if unknown:
        raise ConfigError(f"simrobot://: unknown option {unknown[0]!r}; expected some of {', '.join(OPTIONS)}")
    world = World.load(query["world"]) if query.get("world") else World()
    model = query.get("model", "pioneer3").strip().lower()
    name = query.get("name", "sim")
    try:
        period = float(query.get("sip_period", "0.1"))
    except ValueError:
        period = math.nan
    if not 0 < period <= 10:
        raise ConfigError(f"simrobot://: sip_period: expected seconds in (0, 10], got {query['sip_period']!r}")
    if model in ("amigobot", "amigo"):
        return world, SimRobotConfig.amigobot(name=name, sip_period=period)
    if model in ("pioneer3", "p3", "p3dx", "p3at"):
        return world, SimRobotConfig(name=name, sip_period=period)
    raise ConfigError(f"simrobot://: model: expected pioneer3 or amigobot, got {model!r}")


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


