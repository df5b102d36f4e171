"""`erni replay LOG [--speed X]`: play a recorded log or MCAP bag into a control node, as if live."""

from __future__ import annotations

import argparse
import importlib.util
import math
import select
import sys
import threading
import time
from typing import Any

from erni.blackboard import Agent
from erni.blackboard.errors import ErniError
from erni.commands._text import say
from erni.logs import setup_logging
from erni.replay import LogError, ReplayPlugin, read_log

FOXGLOVE = "erni.plugins.ros2.foxglove:FoxglovePlugin"


def register(sub: Any) -> None:
    """Add the `replay` sub-command."""
    p = sub.add_parser("replay", help="replay a recorded log or MCAP bag into a control node",
                       description="Start a control node that publishes a recorded log on its "
                       "blackboard at the recorded pace; `erni watch --via` it or open its GUI. "
                       "Type p + Enter to pause or resume, a number + Enter to set the speed.")
    p.add_argument("log", help="log file or MCAP bag written by `erni record` (a bag from other tools "
                   "replays its nav_msgs/msg/Odometry on /<robot>/odom as poses, and on /odom with --robot)")
    p.add_argument("--robot", metavar="NAME", help="replay a single robot's own bag (nav_msgs/msg/Odometry on "
                   "/odom, as the robot's ROS 2 stack records it) as robot NAME")
    p.add_argument("--speed", type=float, default=1.0, help="1 = recorded pace, 0.25 = slow motion")
    p.add_argument("--listen", default="127.0.0.1:47100", help="transport address of the replay node")
    p.add_argument("--name", default="control", help="agent name of the replay node")
    p.add_argument("--loop", action="store_true", help="start again at the end")
    p.add_argument("--no-gui", action="store_true", help="do not start the web GUI")
    p.add_argument("--foxglove", metavar="HOST:PORT", help="also serve the replay to Foxglove over its WebSocket "
                   "protocol (robots, headings, trails, links; needs foxglove-sdk), e.g. 127.0.0.1:8765")
    p.add_argument("--identity", metavar="FILE", help="identity bundle of the replay node (role control); "
                   "without it the team key in ERNI_TEAM_KEY")
    p.add_argument("--insecure", action="store_true", help="accept unauthenticated clients")
    p.set_defaults(func=run)


def _commands(plugin: ReplayPlugin, stop: threading.Event) -> None:
    while not stop.is_set():
        ready, _, _ = select.select([sys.stdin], [], [], 0.2)
        if not ready:
            continue
        line = sys.stdin.readline()
        if not line:
            return
        word = line.strip().lower()
        if word in ("p", "pause", ""):
            plugin.pause(not plugin.paused.is_set())
            say("paused" if plugin.paused.is_set() else "playing", file=sys.stderr)
        elif word in ("q", "quit"):
            stop.set()
        else:
            try:
                speed = float(word)
            except ValueError:
                speed = math.nan
            if math.isfinite(speed) and speed > 0:
                plugin.speed = max(0.01, min(1000.0, speed))
                say(f"speed {plugin.speed:g}", file=sys.stderr)
            else:
                say(f"unknown command {word!r}: p (pause/resume), a speed such as 0.5, q", file=sys.stderr)


def run(args: argparse.Namespace) -> int:
    """Check the log, start the replay node, report progress until the end or Ctrl-C."""
    try:
        _, events, problems = read_log(args.log, args.robot)
    except LogError as err:
        say(f"erni replay: {err}", file=sys.stderr)
        return 2
    if not math.isfinite(args.speed) or args.speed <= 0:
        say(f"erni replay: --speed: expected a finite number > 0, got {args.speed}", file=sys.stderr)
        return 2
    for line in problems:
        say(f"erni replay: skipping {line}", file=sys.stderr)
    setup_logging("WARNING")
    agent = Agent(args.name, workers=2)
    try:
        auth = {"identity": args.identity} if args.identity else {"insecure": args.insecure}
        agent.add_plugin("transport", settings={"listen": args.listen, "role": "control", "discovery_port": 0,
                                                "forward_tasks": False, **auth}, name="transport")
        plugin = agent.add_plugin(ReplayPlugin, settings={"log": args.log, "speed": args.speed,
                                                          "loop": args.loop, "robot": args.robot}, name="replay")
        fox = None
        if args.foxglove:
            if importlib.util.find_spec("foxglove") is None:
                say("erni replay: --foxglove needs foxglove-sdk (pip install 'erni[ros2]')", file=sys.stderr)
                return 2
            fox = agent.add_plugin(FOXGLOVE, settings={"listen": args.foxglove}, name="foxglove")
        if not args.no_gui and importlib.util.find_spec("erni.plugins.ui") is not None:
            try:
                agent.add_plugin("ui", name="ui")
            except ErniError as err:
                say(f"erni replay: no GUI: {err}", file=sys.stderr)
    except (ErniError, ValueError) as err:
        say(f"erni replay: {str(err).splitlines()[0]}", file=sys.stderr)
        return 2
    stop = threading.Event()
    try:
        agent.start()
        duration = events[-1].t if events else 0.0
        say(f"replaying {len(events)} events ({duration:.1f} s at x{args.speed:g}) as agent "
              f"{args.name} on {args.listen}; `erni watch --via {args.listen}` to see them",
              file=sys.stderr)
        if args.foxglove:
            port = getattr(fox, "port", None)
            if port is None:  # its setup failed and disabled it: the agent logged why
                say("erni replay: the Foxglove server did not start", file=sys.stderr)
            else:
                say(f"Foxglove: ws://{args.foxglove.rsplit(':', 1)[0]}:{port}", file=sys.stderr)
        if sys.stdin.isatty():
            threading.Thread(target=_commands, args=(plugin, stop), name="replay-keys", daemon=True).start()
        while not stop.is_set() and not (plugin.finished.is_set() and not args.loop):  # --loop: until Ctrl-C
            time.sleep(0.2)
        if plugin.finished.is_set() and not args.loop:
            say(f"replay finished ({plugin.position} events)", file=sys.stderr)
            time.sleep(0.5)  # let watchers receive the last events
    except KeyboardInterrupt:
        pass
    finally:
        stop.set()
        agent.stop()
    return 0
