"""`erni experiment NAME [--plot OUT.png] [--csv OUT.csv]`: reproduce one of the papers' experiments."""

from __future__ import annotations

import argparse
import sys
import time
from typing import TYPE_CHECKING, Any

from erni.commands._text import say, say_lines

if TYPE_CHECKING:
    from erni.sim.experiments import Experiment
    from erni.sim.scenario import Scenario


def register(sub: Any) -> None:
    """Add the `experiment` sub-command."""
    from erni.sim.experiments import EXPERIMENTS

    names = "; ".join(f"{e.name} (paper {e.paper})" for e in EXPERIMENTS.values())
    p = sub.add_parser(
        "experiment", help="run one of the papers' experiments headless and write its figure and metrics",
        description=f"Run an experiment on its scenario (examples/scenario-NAME.toml) and print its "
                    f"metrics, with the paper's numbers beside ours. Experiments: {names}.")
    p.add_argument("name", nargs="?", help="experiment name (omit, or --list, to list them)")
    p.add_argument("--plot", metavar="OUT.png", help="write the figure here (PNG, SVG or PDF; default "
                   "NAME.png in the current directory)")
    p.add_argument("--no-plot", action="store_true", help="draw no figure")
    p.add_argument("--csv", metavar="OUT.csv", help="write every number (section, t, robot, quantity, value, unit)")
    p.add_argument("--scenario", metavar="FILE.toml", help="run on this scenario instead of the named one")
    p.add_argument("--duration", type=float, help="override the scenario's duration (s)")
    p.add_argument("--robots", type=int, help="override the number of robots")
    p.add_argument("--seed", type=int, help="override the random seed")
    p.add_argument("--mode", choices=["kinematic", "agents"], help="agents: real agent processes tasked through "
                   "the control node (the default wherever the team is small enough); kinematic: the strategies "
                   "stepped in one process (large teams)")
    p.add_argument("--seeds", type=int, help="repeat over this many seeds (from --seed) and summarise "
                   "(poi, spread-open, spread-corridor, spread-paths, netaware)")
    p.add_argument("--netns", action="store_true", help="run the teams on the real-mesh tier, as `erni sim --netns` "
                   "(namespaces, babeld; needs root) (netaware, relay-video, roundtrip)")
    p.add_argument("--channel", choices=["nftables", "ns3"], help="with --netns: the channel between the "
                   "namespaces, the radio model as nftables rules or ns-3's 802.11a network (needs Debian's "
                   "libns3-dev, g++ and pkg-config); default: the scenario's radio.channel")
    p.add_argument("--paper-durations", action="store_true", help="hold every phase as long as the paper does "
                   "(energy: standby 600 s, each sweep speed 120 s; about 30 minutes)")
    p.add_argument("--list", action="store_true", help="list the experiments and exit")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    """Run the experiment; exit 0, 1 when it failed, 2 on bad input."""
    from erni.sim.experiments import EXPERIMENTS
    from erni.sim.experiments import run as run_experiment
    from erni.sim.netns import NetnsError
    from erni.sim.progress import Progress
    from erni.sim.scenario import ScenarioError

    if args.list or not args.name:
        return _list(args)
    if args.name not in EXPERIMENTS:
        say(f"erni experiment: unknown experiment {args.name!r}; expected one of "
              f"{', '.join(EXPERIMENTS)}", file=sys.stderr)
        return 2
    exp = EXPERIMENTS[args.name]
    if args.plot is None and not args.no_plot:
        args.plot = f"{exp.name}.png"
    for flag, path in (("--plot", args.plot), ("--csv", args.csv)):
        if path is not None and not _writable(path):
            say(f"erni experiment: {flag} {path}: cannot write there (no such directory?)", file=sys.stderr)
            return 2
    try:
        scenario = _scenario(args, exp)
        _check_flags(args, exp, scenario)
        mode = args.mode or exp.default_mode(scenario)
        if mode not in exp.modes:
            raise ScenarioError(f"{exp.name} runs in {' or '.join(exp.modes)} mode, not {mode!r}")
    except (ScenarioError, NetnsError) as err:
        say(f"erni experiment: {err}", file=sys.stderr)
        return 2
    say(f"erni experiment {exp.name}: paper {exp.paper}, {exp.title} ({mode} mode, "
          f"{scenario.count} robot(s){f', {args.seeds} seeds' if args.seeds else ''}"
          f"{f', real-mesh tier, {scenario.radio.channel} channel' if args.netns else ''})", flush=True)
    progress = Progress()
    t0 = time.monotonic()
    try:
        result = run_experiment(exp.name, scenario, progress, **_options(args, mode))
    except (ValueError, RuntimeError, OSError) as err:
        progress.done()
        say(f"erni experiment {exp.name}: {err}", file=sys.stderr)
        return 1
    progress.done(f"done in {time.monotonic() - t0:.1f} s")
    if args.csv:
        result.write_csv(args.csv)
        say(f"numbers: {args.csv}")
    if args.plot and not args.no_plot:
        result.plot(args.plot)
        say(f"figure: {args.plot}")
    say_lines(result.report(), flush=True)
    return 0


def _list(args: argparse.Namespace) -> int:
    """List the experiments with their modes; exit 0 when asked to (--list), 2 when no name was given."""
    from erni.sim.experiments import EXPERIMENTS
    from erni.sim.scenario import ScenarioError, find_scenario, load_scenario

    say(f"{'name':<16} {'paper':<6} {'mode (default first)':<22} what")
    for e in EXPERIMENTS.values():
        try:
            default = e.default_mode(load_scenario(find_scenario(e.scenario)))
        except ScenarioError:
            default = e.default_mode()
        modes = [default] + [m for m in e.modes if m != default]
        say(f"{e.name:<16} {e.paper:<6} {' / '.join(modes):<22} {e.title}")
    if not args.list:
        say("erni experiment: name an experiment, e.g. `erni experiment poi --plot poi.png`", file=sys.stderr)
    return 0 if args.list else 2


def _scenario(args: argparse.Namespace, exp: Experiment) -> Scenario:
    """The experiment's scenario (or --scenario's) with --robots, --duration and --seed applied."""
    from erni.sim.scenario import ScenarioError, find_scenario, load_scenario

    scenario = load_scenario(args.scenario or find_scenario(exp.scenario))
    if args.robots is not None:
        scenario = scenario.with_robots(args.robots)
    updates: dict[str, Any] = {}
    if args.duration is not None:
        if args.duration <= 0:
            raise ScenarioError(f"--duration: expected a positive number of seconds, got {args.duration}")
        updates["duration"] = args.duration
    if args.seed is not None:
        updates["seed"] = args.seed
    if args.channel is not None:
        updates["radio"] = scenario.radio.model_copy(update={"channel": args.channel})
    return scenario.model_copy(update=updates) if updates else scenario


def _check_flags(args: argparse.Namespace, exp: Experiment, scenario: Scenario) -> None:
    """Refuse (ScenarioError) a flag the experiment does not take; with --netns, check the tier (and the
    ns-3 channel, when it carries the mesh) is there."""
    from erni.sim.experiments import EXPERIMENTS
    from erni.sim.scenario import ScenarioError

    def takers(feature: str) -> str:
        return ", ".join(e.name for e in EXPERIMENTS.values() if getattr(e, feature))

    if args.seeds is not None and args.seeds < 1:
        raise ScenarioError(f"--seeds: expected at least 1, got {args.seeds}")
    if args.seeds is not None and not exp.seeds:
        raise ScenarioError(f"--seeds: {exp.name} runs one seed at a time (use --seed K); "
                            f"--seeds works with {takers('seeds')}")
    if args.netns and not exp.netns:
        raise ScenarioError(f"--netns: {exp.name} runs on the loopback tier only; --netns works with "
                            f"{takers('netns')}")
    if args.paper_durations and not exp.paper_durations:
        raise ScenarioError(f"--paper-durations: {exp.name} has no long form; --paper-durations works with "
                            f"{takers('paper_durations')}")
    if args.channel is not None and not args.netns:
        raise ScenarioError("--channel chooses the real-mesh tier's channel: add --netns")
    if args.netns:
        from erni.sim.netns import check_available
        from erni.sim.ns3_channel import Ns3Error, check_channel

        check_available()  # not root, no namespaces, no babeld: say why, before any team starts
        if scenario.radio.channel == "ns3":
            try:
                check_channel(scenario.count + 1)
            except Ns3Error as err:
                raise ScenarioError(str(err)) from None


def _options(args: argparse.Namespace, mode: str) -> dict[str, Any]:
    """The keyword options the experiment's runner takes from the command line."""
    options: dict[str, Any] = {"mode": mode}
    if args.seeds is not None:
        options["seeds"] = args.seeds
    if args.netns:
        options["netns"] = True
    if args.paper_durations:
        options["paper_durations"] = True
    return options


def _writable(path: str) -> bool:
    from pathlib import Path

    parent = Path(path).resolve().parent
    return parent.is_dir()
