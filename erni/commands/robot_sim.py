"""`erni robot-sim`: simulated ARCOS robots on TCP ports 8101, 8102, ... or on ptys."""

from __future__ import annotations

import argparse
import signal
import sys
import threading
from typing import Any

from erni.commands._text import say
from erni.logs import setup_logging


def register(sub: Any) -> None:
    """Add the `robot-sim` sub-command."""
    p = sub.add_parser(
        "robot-sim", help="run simulated ARCOS robots (MobileSim-compatible port 8101)",
        description="Run simulated ARCOS robots that any ARCOS client (ERNI, ARIA, Player) can drive: "
                    "robot i listens on TCP port PORT+i, or on a pty with --pty.")
    p.add_argument("--port", type=int, default=8101, help="TCP port of the first robot (default 8101)")
    p.add_argument("--host", default="127.0.0.1", help="address to listen on (default 127.0.0.1)")
    p.add_argument("--robots", type=int, default=1, help="how many robots (default 1)")
    p.add_argument("--pty", action="store_true", help="serve each robot on a pty and print its path")
    p.add_argument("--world", help="world file (TOML: walls, circles, polygons, robot start poses)")
    p.add_argument("--model", default="p3dx-sh", metavar="MODEL",
                   help="robot model, as the subtype ARIA knows: p3dx-sh (default), p3at-sh, amigo, amigo-sh, "
                        "peoplebot-sh, powerbot-sh, p3dx, ...; pioneer3 and amigobot are aliases")
    p.add_argument("--sip-period", type=float, default=0.1, help="seconds between SIPs (default 0.1)")
    p.add_argument("--sonar-cycle", type=float, default=0.04,
                   help="seconds between firings in each bank of 8 sonar, as real firmware (default 0.04); "
                        "0 puts every reading in every SIP")
    p.add_argument("--watchdog", type=float, default=2.0, help="stop after this long without commands (s)")
    p.add_argument("--physics-hz", type=float, default=100.0, help="physics steps per second")
    p.add_argument("--log-level", choices=["DEBUG", "INFO", "WARNING", "ERROR"], default="INFO")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    """Start the robots, print where they listen, serve until SIGINT or SIGTERM."""
    from erni.plugins.motion.robots import MODELS, lookup
    from erni.sim.robot import SimRobotConfig
    from erni.sim.robot_host import RobotHost
    from erni.sim.world import World, WorldError

    setup_logging(args.log_level)
    problems = _problems(args)
    model = lookup(args.model)
    if model is None:
        problems.append(f"--model: unknown robot model {args.model!r}; expected one of {', '.join(MODELS)} "
                        "(or pioneer3, amigobot)")
    if problems:
        say("erni robot-sim: " + "; ".join(problems), file=sys.stderr)
        return 2
    try:
        world = World.load(args.world) if args.world else World()
    except WorldError as err:
        say(f"erni robot-sim: {err}", file=sys.stderr)
        return 2
    host = RobotHost(world, physics_hz=args.physics_hz, host=args.host)
    try:
        for i in range(args.robots):
            start = world.start_pose(i)
            name = start.name or f"robot{i + 1}"
            assert model is not None
            cfg = SimRobotConfig.for_model(model.name, name=name, sip_period=args.sip_period,
                                           watchdog=args.watchdog, sonar_cycle=args.sonar_cycle)
            port = None if args.pty else (args.port + i if args.port else 0)
            host.add_robot(cfg, port=port, pty=args.pty)
    except OSError as err:
        host.stop()
        say(f"erni robot-sim: {err}", file=sys.stderr)
        return 1
    stop = threading.Event()

    def on_signal(signum: int, frame: Any) -> None:
        stop.set()

    previous = {s: signal.signal(s, on_signal) for s in (signal.SIGINT, signal.SIGTERM)}
    try:
        host.start()
        for i, robot in enumerate(host.robots):
            say(f"{robot.config.name}: {host.url(i)}  ({robot.config.subclass}, world {world.name!r}, "
                  f"start {robot.x:.2f} {robot.y:.2f})", flush=True)
        stop.wait()   # the signal handler sets it
    finally:
        host.stop()
        for s, handler in previous.items():
            signal.signal(s, handler)
    return 0


def _problems(args: argparse.Namespace) -> list[str]:
    """What is wrong with the numbers on the command line (each a message)."""
    problems = []
    if args.robots < 1:
        problems.append(f"--robots: expected at least 1, got {args.robots}")
    if not args.pty and not 0 <= args.port <= 65535 - args.robots + 1:
        problems.append(f"--port: expected 0..{65536 - args.robots}, got {args.port}")
    if args.sip_period <= 0 or args.watchdog <= 0 or args.physics_hz <= 0:
        problems.append("--sip-period, --watchdog and --physics-hz: expected positive numbers")
    if args.sonar_cycle < 0:
        problems.append(f"--sonar-cycle: expected seconds >= 0, got {args.sonar_cycle}")
    return problems
