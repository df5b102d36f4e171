"""`erni record [--via HOST:PORT] [--format jsonl|mcap] OUT`: record what one agent of a running team
sees, as ERNI's JSON lines or a rosbag2 MCAP bag; `erni record --convert LOG OUT.mcap` converts a log."""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path
from typing import Any

from erni.commands._client import add_client_options, check_seconds, open_client, watch_events
from erni.commands._text import say
from erni.replay import LogError, Recorder

COMPRESSIONS = ("none", "zstd", "lz4")  # erni.bags.COMPRESSIONS, named without importing the ros2 extra
LEASE = 10.0


def register(sub: Any) -> None:
    """Add the `record` sub-command."""
    p = sub.add_parser("record", help="record a team's tasks, results, poses and peer events",
                       description="Record every blackboard change one agent (usually the control "
                       "node) sees, as JSON lines or a rosbag2 MCAP bag (ROS 2 Jazzy types: Odometry on "
                       "/<robot>/odom and /tf; tasks, results, robots' health, network and peers as "
                       "diagnostic_msgs/DiagnosticArray on /diagnostics; network markers on /erni/network), "
                       "until Ctrl-C. Replay either with `erni replay`. With --convert LOG, write the ERNI "
                       "log LOG as the MCAP bag OUT instead, without reaching any agent.")
    p.add_argument("out", help="what to write: JSON lines; or an MCAP bag, one file when OUT ends in .mcap, "
                   "else (with --format mcap) a rosbag2 directory OUT/ as `ros2 bag record -o OUT` writes")
    p.add_argument("--format", choices=("jsonl", "mcap"), default=None,
                   help="jsonl (ERNI's log) or mcap (a rosbag2 bag that ros2 bag, Foxglove and PlotJuggler open; "
                   "needs the ros2 extra); default: mcap when OUT ends in .mcap, else jsonl")
    p.add_argument("--compression", choices=COMPRESSIONS, default="none",
                   help="the bag's chunk compression: none (the default of ros2 bag record's MCAP storage), "
                   "zstd (a ninth of the size, for poses) or lz4")
    p.add_argument("--convert", metavar="LOG", help="convert this JSON-lines log (from `erni record`) into "
                   "the MCAP bag OUT and exit")
    p.add_argument("--seconds", type=float, default=0, help="stop after S seconds (0 = at Ctrl-C)")
    add_client_options(p)
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    """Lease a watch and write every event to the log, with a progress line on stderr."""
    from erni.transport.client import ClientError

    fmt = args.format or ("mcap" if args.out.lower().endswith(".mcap") else "jsonl")
    if fmt == "jsonl" and args.compression != "none" and not args.convert:
        say("erni record: --compression is the MCAP bag's: OUT must end in .mcap, or give --format mcap",
            file=sys.stderr)
        return 2
    if args.convert:
        return _convert(args.convert, args.out, fmt, args.compression)
    problem = check_seconds(args.seconds, "--seconds", zero=True)
    if problem:
        say(f"erni record: {problem}", file=sys.stderr)
        return 2
    if fmt == "mcap" and _bags() is None:
        return 2
    client = open_client(args, "record")
    if client is None:
        return 2
    end = time.monotonic() + args.seconds if args.seconds else None
    with client:
        try:
            addr = client.find(None)
            via = f"{addr[0]}:{addr[1]}"
            bags = _bags() if fmt == "mcap" else None
            recorder: Recorder | Any = (bags.BagRecorder(args.out, via, compression=args.compression) if bags
                                        else Recorder(args.out, via))
        except (ClientError, LogError) as err:
            say(f"erni record: {err}", file=sys.stderr)
            return 1 if isinstance(err, ClientError) else 2
        say(f"recording {addr[0]}:{addr[1]} into {args.out} (Ctrl-C stops)", file=sys.stderr)
        shown = 0.0
        try:
            for ev in watch_events(client, addr, end, LEASE, command="record"):
                if ev is not None:
                    recorder.write(ev.agent, ev.op, ev.type, ev.data)
                if sys.stderr.isatty() and time.monotonic() >= shown:
                    print("\r", end="", file=sys.stderr)  # the count overwrites itself
                    say(f"{recorder.count} events", end="", file=sys.stderr, flush=True)
                    shown = time.monotonic() + 0.5
        except KeyboardInterrupt:
            pass
        finally:
            problem = _close(recorder)
    if problem:
        print(file=sys.stderr)
        say(f"erni record: {problem}", file=sys.stderr)
        return 2
    print(file=sys.stderr)
    say(f"recorded {recorder.count} events into {args.out}", file=sys.stderr)
    return 0


def _close(recorder: Any) -> str:
    """Close the log or bag; return what went wrong ('' when nothing did)."""
    try:
        recorder.close()
    except LogError as err:
        return str(err)
    return ""


def _bags() -> Any:
    """The bag module, or None after saying on stderr that the ros2 extra (rosbags, mcap, PyYAML) is missing."""
    try:
        from erni import bags
    except ImportError as err:
        say(f"erni record: MCAP bags need the ros2 extra (pip install 'erni[ros2]'): {err}", file=sys.stderr)
        return None
    return bags


def _convert(log: str, out: str, fmt: str, compression: str = "none") -> int:
    """Write the JSON-lines log `log` as the MCAP bag `out`."""
    if fmt != "mcap":
        say("erni record: --convert writes an MCAP bag: OUT must end in .mcap, or give --format mcap",
              file=sys.stderr)
        return 2
    if Path(log).resolve() == Path(out).resolve():
        say(f"erni record: --convert: {out} is the log itself", file=sys.stderr)
        return 2
    bags = _bags()
    if bags is None:
        return 2
    try:
        count, problems = bags.convert(log, out, compression)
    except LogError as err:
        say(f"erni record: {err}", file=sys.stderr)
        return 2
    for line in problems:
        say(f"erni record: skipping {line}", file=sys.stderr)
    say(f"converted {count} events from {log} into {out}", file=sys.stderr)
    return 0
