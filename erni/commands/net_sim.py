"""`erni net-sim SCENARIO.toml`: serve a simulated MANET over SNMP, one UDP port per node."""

from __future__ import annotations

import argparse
import signal
import sys
import time
from typing import TYPE_CHECKING, Any

from erni.blackboard.errors import ConfigError
from erni.commands._text import say

if TYPE_CHECKING:
    from erni.plugins.mobinet.usm import UsmUser
    from erni.sim.manet import ManetNetwork
    from erni.sim.manet_scenario import MoveSpec, Scenario
    from erni.sim.snmp_agent import ManetSnmpAgent

AUTH_ENV, PRIV_ENV = "ERNI_SNMP_AUTH_KEY", "ERNI_SNMP_PRIV_KEY"


def register(sub: Any) -> None:
    """Add the `net-sim` sub-command."""
    p = sub.add_parser(
        "net-sim", help="simulate a MANET and serve each node's NHDP/OLSRv2/ERNI MIBs over SNMP",
        description="Serve a simulated MANET: each node answers SNMP v1/v2c (or, with --v3-user, SNMPv3 "
                    "only) on its own UDP port (SNMPv2-MIB, NHDP-MIB, OLSRv2-MIB, IP-FORWARD-MIB, "
                    "ERNI-MOBINET-MIB) until Ctrl-C; scenario moves are applied at their times.")
    p.add_argument("scenario", help="scenario TOML (nodes, comm_range, lossless_range, moves)")
    p.add_argument("--host", help="address to serve on (default: the scenario's host)")
    p.add_argument("--base-port", type=int, help="port of the first node, 0 = any free port "
                   "(default: the scenario's base_port)")
    p.add_argument("--duration", type=float, default=None,
                   help="stop after this many seconds (default: serve until Ctrl-C)")
    v3 = p.add_argument_group("SNMPv3", "with --v3-user every node speaks only SNMPv3, USM authPriv: the user "
                              "reads and writes, v1/v2c requests and communities are refused")
    v3.add_argument("--v3-user", metavar="NAME", help="the USM user every node requires")
    v3.add_argument("--v3-auth", metavar="PROTOCOL", default="SHA-256",
                    help="authentication protocol: SHA-224, SHA-256 (default), SHA-384 or SHA-512")
    v3.add_argument("--v3-priv", metavar="PROTOCOL", default="AES", help="privacy protocol: AES (AES-128)")
    v3.add_argument("--v3-auth-key-file", metavar="FILE", help="file (mode 600) whose first line is the "
                    f"authentication passphrase (default: environment variable {AUTH_ENV})")
    v3.add_argument("--v3-priv-key-file", metavar="FILE", help="file (mode 600) whose first line is the "
                    f"privacy passphrase (default: environment variable {PRIV_ENV})")
    p.set_defaults(func=run)


def _topology_line(net: Any) -> str:
    truth = net.truth()
    cuts = ", ".join(sorted(truth.articulation_points)) or "none"
    return (f"{len(truth.links)} link(s), {len(truth.components)} component(s), "
            f"articulation points: {cuts}")


def v3_users(args: argparse.Namespace) -> list[UsmUser]:
    """The --v3-user with its keys (from the key files, else the environment); ConfigError naming the source."""
    from erni.plugins.mobinet.usm import UsmUser, read_key

    if args.v3_user is None:
        if args.v3_auth_key_file or args.v3_priv_key_file:
            raise ConfigError("--v3-auth-key-file and --v3-priv-key-file need --v3-user")
        return []
    auth = read_key("SNMPv3 auth key", file=args.v3_auth_key_file,
                    env=None if args.v3_auth_key_file else AUTH_ENV)
    priv = read_key("SNMPv3 priv key", file=args.v3_priv_key_file,
                    env=None if args.v3_priv_key_file else PRIV_ENV)
    return [UsmUser(args.v3_user, auth, priv, args.v3_auth, args.v3_priv)]


def run(args: argparse.Namespace) -> int:
    """Load the scenario, serve every node, apply moves; exit code 0, or 2 on bad input."""
    from erni.sim.manet_scenario import load_scenario
    from erni.sim.scenario import ScenarioError
    from erni.sim.snmp_agent import ManetSnmpAgent

    try:
        users = v3_users(args)
        scenario = load_scenario(args.scenario)
        if args.base_port is not None:
            scenario = scenario.model_copy(update={"base_port": args.base_port})
            scenario = type(scenario).model_validate(scenario.model_dump())
    except (ScenarioError, ValueError) as err:   # ConfigError is a ValueError
        say(f"erni net-sim: {err}", file=sys.stderr)
        return 2
    host = args.host or scenario.host
    net = scenario.build()
    # Ctrl-C or a TERM sets a flag the serving loop reads between its short sleeps, rather than
    # raising KeyboardInterrupt wherever the main thread happens to be (inside a move, holding the
    # simulated network's lock that the SNMP threads and the close then wait for)
    stopping: list[int] = []
    previous = {sig: signal.signal(sig, lambda signum, frame: stopping.append(signum))
                for sig in (signal.SIGINT, signal.SIGTERM)}
    agent = ManetSnmpAgent(net, read_community=scenario.read_community, v3_users=users).start()
    try:
        writes = scenario.write_communities()
        try:
            for name, port in scenario.ports().items():
                agent.serve(name, host, port, write_community=writes[name])
        except OSError as err:
            say(f"erni net-sim: {err}", file=sys.stderr)
            return 2
        _announce(agent, net, scenario, users, writes)
        _play_moves(net, sorted(scenario.moves, key=lambda m: m.at), args.duration, stopping)
    finally:
        agent.close()
        for sig, handler in previous.items():
            signal.signal(sig, handler)
        say(_stopped_line(agent.stats, bool(users)), flush=True)
    return 0


def _announce(agent: ManetSnmpAgent, net: ManetNetwork, scenario: Scenario, users: list[UsmUser],
              writes: dict[str, str | None]) -> None:
    """Say what is served: the nodes, their SNMP addresses, the access, the topology."""
    addresses = agent.addresses()
    writable = sum(1 for w in writes.values() if w is not None)
    access = (f"SNMPv3 only: user {users[0].name!r}, authPriv {users[0].auth_protocol}/{users[0].priv_protocol}"
              if users else f"read community {scenario.read_community!r}, "
              f"{writable} node(s) writable with their write community")
    say(f"net-sim: {len(addresses)} node(s), R = {scenario.comm_range} m, "
          f"loss-free to {scenario.lossless_range} m, {access}")
    for name, (h, port) in addresses.items():
        say(f"  {name:<12} {net.info(name).address:<12} snmp udp:{h}:{port}")
    say(f"  {_topology_line(net)}")
    say("serving; Ctrl-C to stop", flush=True)


def _play_moves(net: ManetNetwork, moves: list[MoveSpec], duration: float | None, stopping: list[int]) -> None:
    """Apply each move at its time (s from now) until `duration` ends or a signal is in `stopping`."""
    start = time.monotonic()
    while not stopping:
        now = time.monotonic() - start
        if duration is not None and now >= duration:
            break
        while moves and moves[0].at <= now:
            m = moves.pop(0)
            net.move(m.node, m.x, m.y)
            say(f"t={m.at:6.1f} s  {m.node} -> ({m.x:g}, {m.y:g}); {_topology_line(net)}",
                  flush=True)
        waits = [0.2]
        if moves:
            waits.append(moves[0].at - now)
        if duration is not None:
            waits.append(duration - now)
        time.sleep(max(0.01, min(waits)))


def _stopped_line(st: dict[str, int], v3: bool) -> str:
    """The last line: requests answered, and those dropped by kind."""
    return (f"net-sim: stopped ({st['answered']} request(s) answered; dropped: "
            f"{st['snmpInASNParseErrs']} undecodable, {st['snmpInBadCommunityNames']} unknown community, "
            f"{st['snmpUnknownPDUHandlers']} response/notification PDU(s)"
            + (f", {sum(v for k, v in st.items() if k.startswith('usmStats') and k != 'usmStatsUnknownEngineIDs')} "
               "refused by USM" if v3 else "") + ")")
