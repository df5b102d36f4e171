"""`erni sim [SCENARIO.toml]`: run a whole simulated team (robots, radio, agents, control node)."""

from __future__ import annotations

import argparse
import faulthandler
import os
import shutil
import signal
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

from erni.commands._team_file import announce, withdraw
from erni.commands._text import say
from erni.logs import mask_secrets

KEEP_RUNS = 3  # run directories of finished `erni sim` runs kept in the temporary directory (newest first)
RUN_PREFIX = "erni-sim-"  # what `erni sim` names its run directory in the temporary directory
OWNER_FILE = "erni-sim.pid"  # in a run directory: the PID of the `erni sim` that made it
UNMARKED_AGE = 86400.0  # a run directory without an owner file (an older ERNI's) is finished after a day
# Robots a core holds in real time, as measured: bench/bench_team.py on a quiet 2-core machine, 50 robots
# keep the control node's Pose interval p99 within 2x the period and 100 do not (bench/results/bench_team.json)
ROBOTS_PER_CORE = 25


def register(sub: Any) -> None:
    """Add the `sim` sub-command."""
    p = sub.add_parser(
        "sim", help="run a whole simulated team on this machine until Ctrl-C",
        description="Start a simulated team: the world, one simulated ARCOS robot and one simulated "
                    "SNMP network node per robot, one agent process per robot on 127.0.1.N, and the "
                    "control node. Traffic between robots the radio cannot connect is dropped. While it runs, "
                    "erni task, peers, watch, record and console of the same user reach its control node "
                    "without --via. A team larger than this machine is measured to hold in real time "
                    f"(about {ROBOTS_PER_CORE} robots per core, bench/bench_team.py) starts with a warning.")
    p.add_argument("scenario", nargs="?", help="scenario TOML or the name of one in examples/ "
                   "(default: four robots in an open room)")
    p.add_argument("--robots", type=int, help="number of robots (overrides the scenario)")
    p.add_argument("--headless", action="store_true", help="no GUI on the control node")
    p.add_argument("--gui-listen", metavar="HOST:PORT", help="where the GUI listens (default 127.0.0.1:8080; "
                   "0.0.0.0:8080 for operators on other machines: the printed URL names this host and "
                   "carries the token the page needs)")
    p.add_argument("--duration", type=float, help="stop after S seconds (default: the scenario's, "
                   "else run until Ctrl-C)")
    p.add_argument("--seed", type=int, help="random seed (start layout, robots)")
    p.add_argument("--control-port", type=int, default=47100,
                   help="control node's port on 127.0.1.250 (default 47100; any free one if taken)")
    p.add_argument("--run-dir", help="directory for agent configs, logs and journals, this user's only "
                   f"(0700, its files 0600; default: a new temporary directory {RUN_PREFIX}*, of which the "
                   f"newest {KEEP_RUNS} of finished runs are kept: older ones are removed when a run starts)")
    p.add_argument("--log-level", choices=["DEBUG", "INFO", "WARNING", "ERROR"], default="WARNING",
                   help="log level of the agents (their logs are in RUN_DIR/logs)")
    p.add_argument("--timeout", type=float, default=180.0, help="give up starting after S seconds")
    p.add_argument("--netns", action="store_true",
                   help="the real-mesh tier (root): every agent in a network namespace of its own on one "
                   "mesh segment, the radio as nftables rules between them, babeld routing in each, "
                   "broadcast discovery; Ctrl-C removes it all (see docs/tutorials/real-mesh.md)")
    p.add_argument("--mobinet", choices=["babel", "snmp"],
                   help="what MobiNet reads: babeld's local interface (babel, the default with --netns) "
                   "or the simulated SNMP nodes (snmp, the default without)")
    p.add_argument("--hello-interval", type=float, default=None, metavar="S",
                   help="babeld's Hello interval with --netns (default 0.5 s)")
    p.add_argument("--channel", choices=["nftables", "ns3"],
                   help="what carries the frames with --netns: the radio model as nftables drop rules "
                   "(nftables, the default) or ns-3's 802.11a ad-hoc network in real time (ns3: needs "
                   "Debian's libns3-dev, g++ and pkg-config); default: the scenario's radio.channel")
    p.add_argument("--ros2", action="store_true",
                   help="show the team to ROS 2 (as the scenario's ros2 = true does): the control node runs the "
                   "ros2 plugin, every robot's /ROBOT/odom, /tf and cmd_vel on a Zenoh session listening on "
                   "tcp/127.0.0.1:7448 (or a free port; printed) and joining rmw_zenohd on 127.0.0.1:7447 when "
                   "one runs; domain $ROS_DOMAIN_ID, else 0 (needs pip install 'erni[ros2]')")
    p.add_argument("--listen", metavar="ADDR",
                   help="with --agent-host: this host's IPv4 address on the segment it shares with the agent hosts "
                   "(the simulated robots, their SNMP nodes, the radio feed and the control node listen there)")
    p.add_argument("--agent-host", action="append", metavar="ADDR", dest="agent_hosts",
                   help="run a share of the robots' agents on the host at ADDR (repeat for more hosts): this "
                   "run writes RUN_DIR/hosts/host-K for each, to copy there and start with --join "
                   "(see docs/how-to/agent-hosts.md)")
    p.add_argument("--agents-here", type=int, metavar="N",
                   help="with --agent-host: how many robots' agents run on this host, which also runs the simulator "
                   "and the control node (default: an even share); the rest are dealt evenly over the agent hosts")
    p.add_argument("--join", metavar="BUNDLE",
                   help="be an agent host: run the agents of BUNDLE (a RUN_DIR/hosts/host-K another host's "
                   "erni sim --agent-host wrote) until that run ends or Ctrl-C")
    p.add_argument("--netns-clean", action="store_true",
                   help="remove what killed --netns runs left behind (namespaces, links) and exit")
    p.set_defaults(func=run)


def load(args: argparse.Namespace) -> Any:
    """Return the scenario the arguments ask for (raises ScenarioError)."""
    from erni.sim.scenario import Scenario, ScenarioError, find_scenario, load_scenario

    scenario = load_scenario(find_scenario(args.scenario)) if args.scenario else Scenario()
    if args.robots is not None:
        scenario = scenario.with_robots(args.robots)
    if args.seed is not None:
        scenario = scenario.model_copy(update={"seed": args.seed})
    if args.duration is not None:
        if args.duration <= 0:
            raise ScenarioError(f"--duration: expected a positive number of seconds, got {args.duration}")
        scenario = scenario.model_copy(update={"duration": args.duration})
    if args.ros2 and scenario.ros2 is False:
        scenario = scenario.model_copy(update={"ros2": True})
    settings = scenario.ros2_settings()
    if settings is not None and "domain_id" not in settings and os.environ.get("ROS_DOMAIN_ID", "").strip():
        # the ROS 2 side's domain, as ROS 2 tools take it
        scenario = scenario.model_copy(update={"ros2": {**settings, "domain_id": domain_id(os.environ["ROS_DOMAIN_ID"])}})
    return scenario


def domain_id(text: str) -> int:
    """ROS_DOMAIN_ID as a number (raises ScenarioError naming it)."""
    from erni.sim.scenario import ScenarioError

    try:
        value = int(text.strip())
    except ValueError:
        value = -1
    if not 0 <= value <= 232:
        raise ScenarioError(f"ROS_DOMAIN_ID: expected a ROS 2 domain 0-232, got {text[:40]!r}")
    return value


def ros2_missing() -> str:
    """'' when the ros2 plugin's libraries are installed, else the one line naming the extra that adds them."""
    try:
        import erni.plugins.ros2  # noqa: F401  # the plugin and every library it imports
    except ImportError as err:
        package = {"zenoh": "eclipse-zenoh"}.get(err.name or "", err.name or "a library of the ros2 plugin")
        return f"--ros2 needs {package}, which is not installed: pip install 'erni[ros2]'"
    return ""


def ros2_lines(team: Any) -> list[str]:
    """How ROS 2 tools reach the team, when its control node runs the ros2 plugin ([] when not)."""
    from erni.plugins.ros2.plugin import ros_name
    from erni.sim.team_configs import RMW_ZENOHD

    settings = team.ros2
    if settings is None:
        return []
    names = [ros_name(name) for name in team.names]
    topics = f"/{names[0]}/odom" + (f" ... /{names[-1]}/odom" if len(names) > 1 else "")
    listen = team.ros2_listen
    where = f"listening on {', '.join(listen)}" if listen else f"a client of {', '.join(settings['connect'])}"
    lines = [f"ROS 2 (domain {settings.get('domain_id', 0)}): {topics}, /tf, /ROBOT/cmd_vel, /ROBOT/goal_pose, "
             f"/erni/stop from the control node's Zenoh session, {where}"]
    connect = settings.get("connect", [])
    if listen and connect:
        lines.append(f"  it joins the router at {', '.join(connect)} whenever one runs there" + (
            " (ros2 run rmw_zenoh_cpp rmw_zenohd): rviz2, Foxglove's bridge and ros2 topic list see the team with "
            "RMW_IMPLEMENTATION=rmw_zenoh_cpp" if RMW_ZENOHD in connect else ""))
    if listen:
        endpoints = ",".join(f'"{e}"' for e in listen)
        lines.append(f"  a Zenoh client or router of another port connects with "
                     f"ZENOH_CONFIG_OVERRIDE='connect/endpoints=[{endpoints}]'")
    return lines


def run(args: argparse.Namespace) -> int:
    """Start the team, print how to reach it, run the scenario's tasks, stop cleanly on Ctrl-C."""
    from erni.sim.netns import HELLO_INTERVAL, NetnsError, check_available, clean_stale
    from erni.sim.progress import Progress
    from erni.sim.scenario import ScenarioError
    from erni.sim.team import Team, TeamError

    os.umask(0o077)  # everything the run makes (configs, logs, journals, keys) is this user's only
    if args.join:
        return run_join(args)
    try:
        if args.netns_clean or args.netns:
            check_available()  # not root, no namespaces, no babeld: say why and how to run without
        if args.netns_clean:
            removed = clean_stale()
            say(f"erni sim: removed {len(removed)} dead run(s) of --netns" +
                  (f" ({', '.join(removed)})" if removed else ""))
            return 0
        scenario = _checked(args)
        hosts = args.agent_hosts or []
        too_many = capacity_warning(local_share(scenario.count, hosts, args.agents_here), cores())
        if not args.run_dir:
            prune_run_dirs(Path(tempfile.gettempdir()))
        team = Team(scenario, run_dir=args.run_dir, headless=args.headless,
                    control_port=args.control_port, log_level=args.log_level, gui_listen=args.gui_listen,
                    netns=args.netns, mobinet=args.mobinet, channel=args.channel,
                    hello_interval=args.hello_interval if args.hello_interval is not None else HELLO_INTERVAL,
                    listen=args.listen, agent_hosts=hosts, agents_here=args.agents_here,
                    keep_run_dir=True)  # it prints where the configs and logs are
        if not args.run_dir:
            (team.run_dir / OWNER_FILE).write_text(f"{os.getpid()}\n", encoding="utf-8")
    except (ScenarioError, TeamError, NetnsError, ValueError) as err:
        say(f"erni sim: {err}", file=sys.stderr)
        return 2

    # Ctrl-C or a TERM: while the team starts, abandon the start (KeyboardInterrupt); once it runs,
    # only note it, and the scenario loop returns within 0.2 s. An interrupt raised wherever the main
    # thread happens to be (inside the control node client's request, holding its lock) could leave
    # the team's stop waiting on that lock for good.
    stopping: list[int] = []
    running: list[bool] = []

    def on_signal(signum: int, frame: Any) -> None:
        stopping.append(signum)
        if not running:
            raise KeyboardInterrupt

    previous = {s: signal.signal(s, on_signal) for s in (signal.SIGINT, signal.SIGTERM)}
    if too_many:
        say(f"erni sim: {too_many}", file=sys.stderr, flush=True)
    progress = Progress()
    code = 0
    announced = None
    try:
        say(f"erni sim: {scenario.title} ({scenario.name}): {scenario.count} robot(s), "
              f"R = {scenario.radio.comm_range:g} m; starting...", flush=True)
        say(f"erni sim: run directory {team.run_dir} (agent configs, logs, journals, the team's keys)", flush=True)
        for line in join_lines(team):
            say(f"erni sim: {line}", flush=True)
        t0 = time.monotonic()
        team.start(progress, timeout=args.timeout)
        progress.done()
        announced = announce(team.control_address, team.discovery_port, team.cli_identity, team.run_dir)
        _print_team(team, time.monotonic() - t0, announced)
        for line in ros2_lines(team):
            say(line)
        say("Ctrl-C stops the team", flush=True)
        for note in speech_notes(team.url is None):
            say(f"erni sim: {note}", flush=True)
        running.append(True)
        _run_scenario(team, scenario, stopping)
    except (TeamError, NetnsError) as err:
        progress.done()
        say(f"erni sim: {err}", file=sys.stderr)
        code = 1
    except KeyboardInterrupt:
        progress.done()
    finally:
        signal.signal(signal.SIGINT, signal.SIG_IGN)  # a second Ctrl-C must not cut the clean stop short
        withdraw(announced)  # the commands no longer find a team that is stopping
        say("erni sim: stopping the team...", flush=True)
        # a stop that hangs says where: every thread's stack on stderr after 30 s (the stop waits at
        # most 8 s for the agents, then kills them)
        faulthandler.dump_traceback_later(30, exit=False)
        team.stop()
        faulthandler.cancel_dump_traceback_later()
        for sig, handler in previous.items():
            signal.signal(sig, handler)
        say(f"erni sim: stopped; configs and logs in {team.run_dir}", flush=True)
    return code


def local_share(robots: int, hosts: list[str], here: int | None) -> int:
    """How many of `robots` agents run on this host: all without agent `hosts`, else the world host's share."""
    from erni.sim.agent_hosts import world_share

    return world_share(robots, len(hosts), here) if hosts else robots


def join_lines(team: Any) -> list[str]:
    """What to run on each agent host of `team` ([] when every agent runs here)."""
    from erni.sim.agent_hosts import bundle_dir

    placement = team.placement
    if placement is None:
        return []
    lines = []
    for k, host in enumerate(placement.hosts, start=2):
        bundle = bundle_dir(team.run_dir, k)
        lines.append(f"agent host {k} ({host}, {len(placement.names_of(k))} robot agents): once the start shows "
                     f"'agent hosts joined', copy {bundle} there (scp -r) and run: erni sim --join {bundle.name}")
    return lines


def run_join(args: argparse.Namespace) -> int:
    """`erni sim --join BUNDLE`: run an agent host's agents until the world host's run ends or Ctrl-C."""
    from erni.blackboard.errors import UsageError
    from erni.sim.agent_hosts import AgentHost

    def on_term(signum: int, frame: Any) -> None:
        raise KeyboardInterrupt

    previous = signal.signal(signal.SIGTERM, on_term)
    host: AgentHost | None = None
    why = "interrupted"
    try:
        host = AgentHost(args.join)
        say(f"erni sim: agent host {host.host} of the team at {host.world[0]}:{host.world[1]}, "
            f"{len(host.names)} robot agent(s) ({host.names[0]} ... {host.names[-1]}); joining...", flush=True)
        host.connect(timeout=args.timeout)
        host.start()
        say(f"erni sim: joined; {len(host.names)} agent(s) started, logs in {host.dir / 'logs'}; "
            "Ctrl-C stops them", flush=True)
        why = host.relay()
    except UsageError as err:
        say(f"erni sim: {err}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        pass
    finally:
        signal.signal(signal.SIGINT, signal.SIG_IGN)  # a second Ctrl-C must not cut the clean stop short
        if host is not None:
            host.stop()
        signal.signal(signal.SIGTERM, previous)
    if host is not None:
        say(f"erni sim: {why}; the agents of host {host.host} stopped", flush=True)
    return 0


def _checked(args: argparse.Namespace) -> Any:
    """The scenario of `args`, once the options and what they need are checked: a wrong combination, a
    missing ns-3 or Zenoh, a bad GUI address is one line (a `TeamError`, `ScenarioError` or `ValueError`)
    before anything starts."""
    from erni.sim.team import TeamError

    if args.hello_interval is not None and not args.netns:
        raise TeamError("--hello-interval is babeld's, which runs only with --netns")
    if args.channel is not None and not args.netns:
        raise TeamError("--channel chooses the real-mesh tier's channel: add --netns")
    scenario = load(args)
    if args.netns and (args.channel or scenario.radio.channel) == "ns3":
        from erni.sim.ns3_channel import Ns3Error, check_channel

        try:  # ns-3 missing, or more nodes than it carries in real time
            check_channel(scenario.count + 1)
        except Ns3Error as err:
            raise TeamError(str(err)) from None
    if scenario.ros2 is not False and (missing := ros2_missing()):
        raise TeamError(missing)
    if args.gui_listen:
        from erni.transport import parse_address

        parse_address(args.gui_listen)
    return scenario


def cores() -> int:
    """The cores this process may run on (its CPU affinity, else the machine's count)."""
    try:
        return len(os.sched_getaffinity(0)) or 1
    except (AttributeError, OSError):
        return os.cpu_count() or 1


def capacity_warning(robots: int, cores: int) -> str:
    """'' when `robots` is within what `cores` are measured to hold in real time, else the one-line warning."""
    holds = ROBOTS_PER_CORE * cores
    if robots <= holds:
        return ""
    return (f"{robots} robots is more than this machine is measured to hold in real time (about "
            f"{ROBOTS_PER_CORE} robots per core: {holds} on its {cores} core{'' if cores == 1 else 's'}, "
            "bench/bench_team.py); starting anyway, expect a slow start and skipped SIPs")


def prune_run_dirs(tmp: Path, keep: int = KEEP_RUNS, now: float | None = None) -> list[Path]:
    """Remove the run directories of finished `erni sim` runs in `tmp` but the newest `keep`; return those removed.

    A run directory is `tmp/erni-sim-*`, owned by this user, holding the run's folders (agents/, logs/).
    It is finished when the `erni sim` named in its owner file no longer runs, or, without an owner
    file (an ERNI before the rule), when nothing in it changed for a day. A run still going is never
    touched, nor anything else in `tmp`.
    """
    from erni.sim.team import RUN_SUBDIRS

    now = time.time() if now is None else now
    finished: list[tuple[float, Path]] = []
    for path in tmp.glob(f"{RUN_PREFIX}*"):
        try:
            st = path.lstat()
            if path.is_symlink() or not path.is_dir() or st.st_uid != os.getuid() \
                    or not any((path / sub).is_dir() for sub in RUN_SUBDIRS):
                continue
            owner = path / OWNER_FILE
            if owner.is_file():
                if _running(owner.read_text(encoding="utf-8").strip()):
                    continue
            elif now - st.st_mtime < UNMARKED_AGE:
                continue
            finished.append((st.st_mtime, path))
        except OSError:
            continue
    finished.sort(reverse=True)
    removed = [path for _, path in finished[keep:]]
    for path in removed:
        shutil.rmtree(path, ignore_errors=True)
    return removed


def _running(pid: str) -> bool:
    """Whether the process with this PID runs (an unreadable PID counts as running: nothing is removed)."""
    try:
        os.kill(int(pid), 0)
    except ValueError:
        return True
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


def speech_notes(headless: bool) -> list[str]:
    """What the GUI's speech front end lacks on this machine, each with the command that adds it."""
    import importlib.util

    if headless:
        return []
    notes = []
    if importlib.util.find_spec("pocketsphinx") is None:
        notes.append("voice commands off: no speech recogniser (pip install pocketsphinx)")
    if shutil.which("espeak-ng") is None:
        notes.append("spoken feedback off: espeak-ng is not installed (sudo apt install espeak-ng)")
    return notes


def _print_team(team: Any, seconds: float, announced: Path | None = None) -> None:
    host, port = team.control_address
    say(f"team up in {seconds:.1f} s: {len(team.names)} robot agent(s) and the control node; "
          f"run directory {team.run_dir}")
    for i, name in enumerate(team.names):
        r = team.robots[i]
        where = f" netns {team.mesh.node(name).netns}" if team.mesh is not None else ""
        say(f"  {name:<10} agent {team.agents[name].address[0]:<12} pid {team.agents[name].pid or '-':<8} "
              f"robot {team.host.url(i):<26} at ({r.x:6.2f}, {r.y:6.2f}){where}")
    say(f"  control    agent {host}:{port}  pid {team.agents['control'].pid or '-'}" +
          (f" netns {team.mesh.node('control').netns}" if team.mesh is not None else ""))
    if team.mesh is not None:
        say(f"  mesh       segment {team.mesh.subnet} (namespace {team.mesh.hub}), {team.mesh.channel} channel, "
              "babeld in every node, "
              f"MobiNet reads {team.mobinet}; routes: ip -n {team.mesh.node(team.names[-1]).netns} route")
    if not team.url:
        say("  GUI        none (headless, or the UI plugin is not installed)")
    elif sys.stdout.isatty():
        say(f"  GUI        {team.url}")
    else:  # output to a file or a pipe is a log: the token stays in the control node's config (0600)
        say(f"  GUI        {mask_secrets(team.url)} (the token is shown on a terminal only; it is the ui "
            f"plugin's token in {team.run_dir / 'agents' / 'control.toml'})")
    say("to task the team from another terminal:")
    say(f"  export ERNI_IDENTITY={team.cli_identity}")
    say(f"  erni peers --via {host}:{port}")
    say(f"  erni task --via {host}:{port} {team.names[0]} BotMotion goto x=1 y=2 --wait")
    say(f"  erni watch --via {host}:{port}")
    say(f"  erni stop --via {host}:{port}")
    if announced is not None:
        from erni.transport.client import IDENTITY_ENV

        say(f"  (while it runs, erni peers, task, stop, watch, record and console find this team without --via and "
            f"{IDENTITY_ENV}: it is named in {announced})", flush=True)


def _run_scenario(team: Any, scenario: Any, stopping: list[int]) -> None:
    """Send the scenario's tasks and failures on time and print what comes back, until its duration
    or until `stopping` holds a signal."""
    from erni.blackboard import Task
    from erni.blackboard.schemas import ResultUpdate

    client = team.client()
    start = time.monotonic()
    pending = sorted(scenario.task, key=lambda t: t.at)
    failures = sorted(scenario.failure, key=lambda f: f.at)
    sent: dict[str, str] = {}
    next_status = start + 10.0
    while not stopping:
        now = time.monotonic() - start
        if scenario.duration is not None and now >= scenario.duration:
            say(f"t={now:6.1f} s  duration reached", flush=True)
            return
        while pending and pending[0].at <= now:
            spec = pending.pop(0)
            for name in (team.names if spec.to == "all" else [spec.to]):
                task = Task(verb=spec.verb, preposition=spec.preposition, params=spec.params,
                            destination=name, source=client.endpoint.name)
                client.send(team.control_address, "task.add", task)
                sent[task.uid] = name
                say(f"t={now:6.1f} s  {name}: {task.describe()}", flush=True)
        while failures and failures[0].at <= now:
            f = failures.pop(0)
            team.fail(f.robot)
            say(f"t={now:6.1f} s  {f.robot} fails (agent killed)", flush=True)
        msg = client.receive(0.2)
        if msg is not None and msg.kind == "task.result" and isinstance(msg.body, ResultUpdate):
            res = msg.body.result
            if msg.body.uid in sent and res.state.done:
                say(f"t={now:6.1f} s  {sent.pop(msg.body.uid)}: {res.state.value} {res.message}".rstrip(),
                      flush=True)
        if time.monotonic() >= next_status:
            next_status += 10.0
            say(f"t={now:6.1f} s  {status_line(team)}", flush=True)


def status_line(team: Any) -> str:
    """Robot agents running, and the robots the control node hears (its own directory, not the radio model)."""
    names = team.names
    placement = team.placement
    here = [n for n in names if placement is None or not placement.remote(n)]
    dead = [n for n in here if not team.agents[n].alive]
    line = f"{len(here) - len(dead)}/{len(here)} robot agents running" + (
        f" ({', '.join(dead)} exited)" if dead else "")
    if team.feed is not None:  # the agent hosts' agents: heard or not below
        line += (f" here, {len(names) - len(here)} on agent hosts ({len(team.feed.joined())}/"
                 f"{len(placement.hosts)} joined)")
    if not team.agents["control"].alive:
        return line + "; the control node is not running"
    peers = team.peers(1.0)
    heard = [n for n in names if n in peers and peers[n].up]
    if not peers:
        return line + "; the control node does not answer"
    return line + f"; control hears {len(heard)}/{len(names)}" + (
        f" (not {', '.join(n for n in names if n not in heard)})" if len(heard) < len(names) else "") + (
        f"; {team.status.components} radio component(s)") + sips_note(*team.sips_since()) + channel_note(team)


def channel_note(team: Any) -> str:
    """The ns-3 channel's lag behind real time (its probe's latest and largest), when it carries the mesh."""
    channel = team.mesh.ns3 if team.mesh is not None else None
    if channel is None:
        return ""
    if not channel.alive:
        return f"; the ns-3 channel is not running (see {channel.log_path})"
    if not channel.lag.probes:
        return ""
    lag = channel.lag
    return f"; ns-3 lag {lag.now_ms:.0f} ms (at most {lag.max_ms:.0f} ms, {lag.late} of {lag.probes} probes late)"


def sips_note(sent: int, skipped: int) -> str:
    """The simulated robots' SIPs since the last status line: on time, or how many were skipped."""
    slots = sent + skipped
    if not slots:
        return ""
    if skipped <= 0.01 * slots:
        return f"; SIPs on time {sent / slots:.1%}"
    return (f"; SIPs on time {sent / slots:.1%} ({skipped} of {slots} skipped: this machine is too busy "
            f"for the team to run in real time; try fewer robots)")
