"""The harnesses of `fuzz_run` that follow an input past its parser, as far as it goes in process.

- **frames after authentication**: payloads sealed in a real session from an authenticated robot's
  key (and a command-line client's), handed to the control node's `Endpoint.receive_datagram` (what
  its UDP reader calls), through `TransportPlugin` (the role policy, status ownership, results,
  tasks) onto a real agent's blackboard and out to its UI plugin's state as `/api/state` serialises it;
- **ARCOS bytes**: the robot's byte stream through the driver's own reader (`ArcosDriver._service`
  on an in-process port; now and then a whole handshake with damaged SYNC and CONFIG answers), its
  `RobotState`, the motion resource's publication and the motion plugin's `Pose` on a blackboard;
- **WebSocket messages (GUI)**: page text through the server's handler (`WebServer._text`, as the
  WebSocket loop hands it over), the UI plugin's handlers and the tasks they publish;
- **replay logs** and **MCAP bags**: a file through `read_log` and the replay plugin's publishing
  onto a control node's blackboard and out to its page state.

The agents are stepped on the caller's thread (`Stepped`: each plugin's run, as a worker runs it,
until none has work), and reused across inputs. After each input the oracles look at what it left
(`Oracle`, a plugin that sees every object committed): every number finite, on the blackboard and in
the page's serialised state; every name field of the name character set; every line `erni watch`
and `erni task --wait` would print for an object exactly one line without control characters; and,
every `MEMORY_EVERY` inputs, the objects held for each sender within its bound. A broken invariant
raises `Violation`, counted apart from crashes.
"""

from __future__ import annotations

import argparse
import asyncio
import io
import json
import math
import random
import tempfile
import unicodedata
from collections import Counter
from collections.abc import Mapping
from pathlib import Path
from typing import Any

from erni.blackboard.testing import wait_until
from tests.reliability.fuzz_run import (
    Violation,
    as_text,
    confirmed,
    dumps,
    mutate,
    mutated_json,
    number,
    surface,
    text,
    value,
)

MEMORY_EVERY = 50
"""Inputs between two looks at what is held per sender (a walk over the blackboard)."""
NAME_FIELDS = ("robot", "name", "node", "source", "destination", "sender", "agent")
"""Top-level fields of blackboard objects that hold an agent's name ('' or None where not known yet)."""
HIDDEN = frozenset({"Cc", "Cf", "Cs", "Zl", "Zp"})

_open: list[Any] = []   # what the harnesses started, stopped by `close_all`


def close_all() -> None:
    """Stop every agent and endpoint the harnesses started."""
    while _open:
        part = _open.pop()
        try:
            part.close()
        except Exception:   # noqa: BLE001 - closing what is left must not hide the results
            pass


# --- the oracles --------------------------------------------------------------------------------


def non_finite(data: Any, where: str = "") -> str | None:
    """Where in plain data (dicts, lists, tuples) a float is not finite, or None."""
    stack: list[tuple[str, Any]] = [(where, data)]
    while stack:
        at, item = stack.pop()
        if isinstance(item, float):
            if not math.isfinite(item):
                return f"{at or '(top)'} = {item}"
        elif isinstance(item, Mapping):
            stack.extend((f"{at}.{k}", v) for k, v in item.items())
        elif isinstance(item, (list, tuple)):
            stack.extend((f"{at}[{i}]", v) for i, v in enumerate(item))
    return None


def printed(line: str) -> str | None:
    """What is wrong with `line` as a command prints it (`erni.commands._text.say`), or None."""
    from erni.commands._text import say

    out = io.StringIO()
    say(line, file=out)
    shown = out.getvalue()
    if not shown.endswith("\n") or "\n" in shown[:-1]:
        return f"printed as {shown.count(chr(10))} lines: {shown[:120]!r}"
    bad = [ch for ch in shown[:-1] if unicodedata.category(ch) in HIDDEN]
    if bad:
        return f"printed with control character {bad[0]!r}: {shown[:120]!r}"
    return None


def object_problems(agent: str, obj: Any) -> list[str]:
    """The invariants one blackboard object breaks: a number not finite, a name field out of the name
    character set, a line `erni watch` or `erni task --wait` would print for it that is not one line of
    visible characters (or cannot be printed at all)."""
    from erni.blackboard import Task
    from erni.blackboard.schemas import WatchEvent
    from erni.blackboard.text import is_name
    from erni.commands.task import _line
    from erni.commands.watch import describe

    kind = type(obj).__name__
    problems = []
    data = obj.model_dump()
    bad = non_finite(data, kind)
    if bad:
        problems.append(f"non-finite number on the blackboard: {bad}")
    for f in NAME_FIELDS:
        v = data.get(f)
        if v not in (None, "") and not is_name(v):
            problems.append(f"{kind}.{f} on the blackboard is no name: {v!r:.80}")
    if kind in ("Task", "Pose", "NetInfo", "Peer"):
        try:
            lines = [describe(WatchEvent(agent=agent, op="change", type=kind, data=obj.model_dump(mode="json")))]
            if isinstance(obj, Task) and obj.result is not None:
                lines.append(_line(argparse.Namespace(json=False, agent=obj.destination or agent), obj, obj.result))
        except Exception as err:   # noqa: BLE001 - a command that cannot print an object is a finding
            problems.append(f"erni watch / erni task cannot print {kind} {obj.uid[:40]}: {type(err).__name__}: {err}")
            lines = []
        for line in lines:
            why = printed(line)
            if why:
                problems.append(f"{kind} {obj.uid[:40]}: {why}")
    return problems


def page_problems(state: dict[str, Any]) -> list[str]:
    """The invariants the page's state breaks, serialised as `/api/state` serialises it (`page_json`):
    a number that is not finite (which it would have to send as null), text that is not JSON, a robot
    or link end that is no name."""
    from erni.blackboard.text import is_name
    from erni.plugins.ui.server import page_json

    replaced: list[bool] = []
    body = page_json(state, lambda: replaced.append(True))
    problems = []
    if replaced:
        problems.append(f"non-finite number in the page's state: {non_finite(state, 'state')}")

    def refuse(constant: str) -> None:
        raise ValueError(constant)

    try:
        json.loads(body, parse_constant=refuse)
    except ValueError as err:
        problems.append(f"/api/state is not JSON: {err}")
    for robot in state.get("robots", []):
        if not is_name(robot.get("name")):
            problems.append(f"a robot on the page is no name: {robot.get('name')!r:.80}")
    for link in state.get("links", []):
        if not (is_name(link.get("a")) and is_name(link.get("b"))):
            problems.append(f"a link on the page ends at no name: {link.get('a')!r:.40} {link.get('b')!r:.40}")
    return problems


def oracle_class() -> type:
    from erni.blackboard import Plugin, Task, TaskState

    class Oracle(Plugin):   # type: ignore[type-arg]
        """Sees every object committed on its agent's blackboard and notes the invariants it breaks;
        with `perform`, ends every task sent to those robots as a performer would (succeeded)."""

        def setup(self) -> None:
            self.everything = self.subscribe(lambda o: True)
            self.found: list[str] = []
            self.perform: set[str] = set()

        def execute(self) -> None:
            for obj in self.everything.added + self.everything.changed:
                self.found += object_problems(self.agent_name, obj)
                if isinstance(obj, Task) and obj.destination in self.perform and not obj.done:
                    self.change(obj.with_result(TaskState.SUCCEEDED, message="done"))

    return Oracle


class Stepped:
    """An agent whose plugins run on the caller's thread: `settle()` gives each plugin the run a worker
    would (its deltas, wake-ups and hand-offs, then `execute()` in a transaction) until none has work.
    Nothing runs between two inputs, so what one input leaves is what the oracles see."""

    def __init__(self, name: str) -> None:
        from erni.blackboard import Agent

        self.agent = Agent(name, workers=1, retention=None)
        self.oracle: Any = None

    def add(self, plugin: Any, settings: dict[str, Any] | None = None, name: str | None = None) -> Any:
        return self.agent.add_plugin(plugin, settings=settings, name=name)

    def start(self) -> Stepped:
        a = self.agent
        self.oracle = a.add_plugin(oracle_class(), name="oracle")
        a.started = True   # setups as `Agent.start` runs them, without the worker and timer threads
        for p in list(a.plugins):
            if p._disabled:   # a plugin whose parts the harness drives itself: no setup, no runs
                p._setup_ran = False
                continue
            a._setup(p)
            if p._setup_error is not None:
                raise RuntimeError(f"{p.name}: setup failed: {p._setup_error}")
        _open.append(self)
        self.settle()
        return self

    def settle(self, rounds: int = 30) -> None:
        for _ in range(rounds):
            ran = False
            for p in self.agent.plugins:
                if p._disabled:
                    continue
                runs = p.runs
                self.agent.scheduler._run(p)
                ran = ran or p.runs != runs
            if not ran:
                return
        raise Violation(f"agent {self.agent.name} still has work after {rounds} rounds of runs")

    def problems(self) -> list[str]:
        found, self.oracle.found = self.oracle.found, []
        return found

    def close(self) -> None:
        self.agent.stop(timeout=2.0, announce=False)


def raise_found(problems: list[str]) -> None:
    if problems:
        raise Violation("; ".join(dict.fromkeys(problems))[:900])


def ui_settings() -> dict[str, Any]:
    return {"listen": "127.0.0.1:0", "speak": False, "token": "fuzz-token-0123", "rate_hz": 50.0}


def page_state(ui: Any) -> list[str]:
    return page_problems(ui.server.state())


# --- frames after authentication ------------------------------------------------------------------


class Control:
    """A control node (transport and UI plugins, the oracle) stepped in process, and two authenticated
    peers with a live session to it: `fuzz-robot` (role robot) and `fuzz-cli` (role cli)."""

    def __init__(self, status_objects: int = 64, tasks_per_requester: int = 64) -> None:
        from erni.blackboard import Task
        from erni.transport.endpoint import Endpoint
        from erni.transport.identity import load_identity
        from erni.transport.limits import Limits
        from erni.transport.policy import STATUS
        from erni.transport.settings import TransportSettings
        from tests.transport.helpers import identity

        self.node = Stepped("control-fuzz")
        settings: dict[str, Any] = {"identity": identity("control-fuzz"), "listen": "127.0.0.1:0",
                                    "discovery_port": 0, "beacon_period": 1.0, "peer_timeout": 3600.0,
                                    "link_deadline": 86400.0, "task_ttl": 86400.0}
        fields = TransportSettings.model_fields
        self.bounds = {"status_objects": status_objects, "tasks_per_requester": tasks_per_requester}
        for k, v in self.bounds.items():   # the bounds per sender, where the transport has them: small, to reach them
            if k in fields:
                settings[k] = v
        self.transport = self.node.add("transport", settings, "transport")
        self.ui = self.node.add("ui", ui_settings(), "ui")
        self.node.start()
        self.rx = self.transport.endpoint
        limits = Limits(handshakes_per_host=1e9, handshakes_total=1e9, beacons_total=1e9)
        self.peers = {}
        for name, role in (("fuzz-robot", "robot"), ("fuzz-cli", "cli")):
            ep = Endpoint(name, identity=load_identity(identity(name, role)), limits=limits, role=role)
            ep.start()
            _open.append(_Stop(ep))
            ep.send(self.rx.address, "beacon", None, reliable=False)
            self.peers[name] = ep
        def ready() -> bool:  # both ends of every peer's session confirmed
            self.node.settle()
            return all(confirmed(ep, self.rx) and confirmed(self.rx, ep) for ep in self.peers.values())

        wait_until(ready, timeout=20, interval=0.01, message="the fuzz peers did not get a session with the control node")
        self.node.settle()
        self.sessions = {name: ep.session_with(self.rx.address) for name, ep in self.peers.items()}
        # tasks the control node gave the robot: its results (task.result) then reach the performer's rule
        self.given = []
        with self.node.agent.transaction() as tx:
            for prep, params in (("goto", {"x": 1, "y": 2}), ("forward", {"distance": 1.0}), ("stop", {})):
                task = Task(verb="BotMotion", preposition=prep, params=params, source="control-fuzz",
                            destination="fuzz-robot")
                tx.add(task)
                self.given.append(task.uid)
        self.node.settle()
        self.status_types = sorted(STATUS)
        self.node.problems()

    def deliver(self, sender: str, payload: bytes) -> None:
        """`payload` sealed in `sender`'s session, through the control node's UDP reader, then its runs."""
        frame = self.sessions[sender].seal(payload, 65536)
        self.rx.receive_datagram(frame, ("127.0.0.1", 9))
        self.node.settle()

    def held(self) -> list[str]:
        """What is held for one sender beyond its bound: status objects per sender and type on the
        blackboard, tasks per requester, and the transport's records of them."""
        from erni.blackboard import Task

        t = self.transport
        board = self.node.agent.blackboard
        per: Counter[tuple[str, str]] = Counter()
        for uid, sender in list(t.status_owner.items()):
            obj = board.get(uid)
            if obj is not None:
                per[(sender, type(obj).__name__)] += 1
        limit = getattr(t.settings, "status_objects", 256)
        problems = [f"{n} {kind} objects of {sender} held (bound {limit})" for (sender, kind), n in per.items()
                    if n > limit]
        tasks: Counter[str] = Counter()
        for uid, given in list(t.tasks_in.items()):
            if given.sender and isinstance(board.get(uid), Task):
                tasks[given.sender] += 1
        task_limit = getattr(t.settings, "tasks_per_requester", 1000)
        problems += [f"{n} tasks of {sender} held (bound {task_limit})" for sender, n in tasks.items()
                     if n > task_limit]
        cap = 4 * limit * (len(self.status_types) + 1) + task_limit + 4096
        # every table the transport keeps per sender, in the collaborator that holds it (a name not found is
        # the harness out of date, an error, never an empty table)
        held = {"status_in": t.replication.status_in, "status_owner": t.replication.status_owner,
                "status_base": t.replication.status_base, "_resend_asked": t.replication._resend_asked,
                "tasks_in": t.tasking.tasks_in, "addresses": t.presence.addresses, "peers": t.presence.peers,
                "directory": t.presence.directory, "watchers": t.watchers.watchers}
        for name, table in held.items():
            n = len(table)
            if n > cap:
                problems.append(f"the transport holds {n} entries in {name} (more than {cap})")
        return problems

    def close(self) -> None:
        self.node.close()


class _Stop:
    def __init__(self, part: Any) -> None:
        self.part = part

    def close(self) -> None:
        self.part.stop()


_control: Control | None = None


def control() -> Control:
    global _control
    if _control is None:
        _control = Control()
        _open.append(_Forget())
    return _control


class _Forget:
    def close(self) -> None:
        global _control, _robot, _page, _replay
        _control = _robot = _page = _replay = None


def _body_seeds(c: Control) -> list[tuple[str, str, str, dict[str, Any]]]:
    """(sender, kind, type, body) of what each peer may send: its statuses, results of the tasks it was
    given, freshness notes and removals, beacons; the client's tasks, cancels, queries, watches."""
    from erni.blackboard import AllocationResult, NetInfo, Pose, Task, TaskState
    from erni.blackboard.schemas import Beacon, Cancel, Fresh, Peer, ResultUpdate, StatusRemoved, TaskQuery
    from erni.blackboard.tasks import Link, Neighbor, Position, Route

    me = "fuzz-robot"
    pose = Pose(robot=me, x=1.0, y=-2.0, theta=0.5, v=0.2, w=0.1, battery=12.1, sonar=[0.5, 1.5])
    info = NetInfo(uid="net:fuzz-robot:topology", node=me, kind="topology",
                   neighbors=[Neighbor(name="robot2", address="127.0.0.1:47001", quality=0.8)],
                   links=[Link(a=me, b="robot2", quality=0.7)], routes=[Route(destination="10.0.0.2", hops=2,
                                                                               cost=1.5)],
                   positions={me: Position(x=1.0, y=2.0)})
    peer = Peer(uid=f"peer:{me}", name=me, address="127.0.0.1:47001", role="robot", up=True)
    result = AllocationResult(state=TaskState.RUNNING, progress=0.5, message="on my way", values={"d": 1.5})
    out: list[tuple[str, str, str, dict[str, Any]]] = [
        (me, "status", "Pose", pose.model_dump(mode="json")),
        (me, "status", "NetInfo", info.model_dump(mode="json")),
        (me, "status", "Peer", peer.model_dump(mode="json")),
        (me, "status.fresh", "Fresh", Fresh(uid=pose.uid, base=pose.stamp, stamp=pose.stamp + 1).model_dump(mode="json")),
        (me, "status.remove", "StatusRemoved", StatusRemoved(uid=info.uid).model_dump(mode="json")),
        (me, "beacon", "Beacon", Beacon(role="robot", capabilities=["motion"], seq=1).model_dump(mode="json")),
    ]
    for uid in c.given:
        out.append((me, "task.result", "ResultUpdate", ResultUpdate(uid=uid, result=result).model_dump(mode="json")))
    for dest in ("control-fuzz", "fuzz-robot", "robot9"):
        task = Task(verb="BotMotion", preposition="goto", params={"x": 1, "y": 2}, source="fuzz-cli",
                    destination=dest)
        out.append(("fuzz-cli", "task.add", "Task", task.model_dump(mode="json")))
    out += [("fuzz-cli", "task.cancel", "Cancel", Cancel(uid=c.given[0]).model_dump(mode="json")),
            ("fuzz-cli", "task.query", "TaskQuery", TaskQuery(uid=c.given[1]).model_dump(mode="json")),
            ("fuzz-cli", "peers.request", "", {}),
            ("fuzz-robot", "task.add", "Task", Task(verb="Deploy", preposition="relay", params={"source": "robot2", "destination": "robot3"},
                                                     source=me, destination="control-fuzz").model_dump(mode="json"))]
    return out


BODY_FIELDS = ["robot", "x", "y", "theta", "v", "w", "battery", "sonar", "stamp", "uid", "node", "kind", "neighbors",
               "links", "routes", "positions", "name", "address", "role", "up", "epoch", "base", "result", "state",
               "progress", "message", "values", "verb", "preposition", "params", "source", "destination",
               "capabilities", "interval", "seq", "degraded", "quality", "a", "b", "lease"]
HOSTILE_TEXT = ["\x1b]0;owned\x07\x1b[2J", "robot1\nrobot2 succeeded 100% arrived", "\u202eevil", "", "x" * 70,
                "control-fuzz", "fuzz-robot", "robot2", "pose:fuzz-robot", "peer:fuzz-robot"]


def hostile(rng: random.Random, depth: int = 1) -> Any:
    """A value an adversary would put in a field: a non-finite number, an escape, a forged line, a name of
    another agent, or any JSON value."""
    r = rng.random()
    if r < 0.2:
        return rng.choice([float("nan"), float("inf"), float("-inf"), 1e308 * 10, -0.0, 2**64, 1e300])
    if r < 0.3:
        return rng.uniform(-1e3, 1e3)
    if r < 0.45:
        return rng.choice(HOSTILE_TEXT) + (text(rng, 4) if rng.random() < 0.3 else "")
    return value(rng, depth, BODY_FIELDS)


def damaged_body(rng: random.Random, body: dict[str, Any]) -> Any:
    """`body` with 1-4 fields (at the top or one level down) replaced by hostile values, dropped or added."""
    obj = json.loads(json.dumps(body))
    for _ in range(rng.choice([1, 1, 1, 2, 3, 4])):
        target = obj
        if rng.random() < 0.35:
            inner = [k for k, v in obj.items() if isinstance(v, (dict, list)) and v]
            if inner:
                target = obj[rng.choice(inner)]
                if isinstance(target, list):
                    i = rng.randrange(len(target))
                    if isinstance(target[i], dict):
                        target = target[i]
                    else:
                        target[i] = hostile(rng)
                        continue
        op = rng.random()
        if op < 0.15 and target:
            target.pop(rng.choice(list(target)))
        elif op < 0.85 and target:
            target[rng.choice(list(target))] = hostile(rng)
        else:
            target[rng.choice(BODY_FIELDS)] = hostile(rng)
    return obj


@surface("frames after authentication",
         "what a key holder can send in its own session, sealed correctly: a robot's statuses (Pose, NetInfo, "
         "Peer), freshness notes, removals, beacons and task results, a client's tasks, cancels, queries and "
         "watches, each with fields replaced by non-finite numbers, escapes, forged lines, other agents' names "
         "or any JSON value, as one envelope or a batch, damaged envelopes and bytes; through the control node's "
         "`Endpoint.receive_datagram`, `TransportPlugin` (role policy, status ownership, results, tasks) onto its "
         "blackboard and into its UI plugin's page state")
def frames_after(_: argparse.Namespace) -> tuple[Any, Any]:
    from erni.transport.wire import EnvelopeHead

    c = control()
    seeds = _body_seeds(c)
    head_fields = set(EnvelopeHead.model_fields)
    seq = iter(range(10, 10**12))
    count = [0]

    def envelope(sender: str, kind: str, type_name: str, body: Any) -> dict[str, Any]:
        ep = c.peers[sender]
        return {"sender": sender, "role": ep.role, "to": "control-fuzz", "inst": ep.inst,
                "reply": list(ep.address), "seq": next(seq), "id": f"f{next(seq):x}", "kind": kind,
                "type": type_name or None, "body": body}

    def gen(rng: random.Random) -> tuple[str, bytes]:
        sender, kind, type_name, body = rng.choice(seeds)
        r = rng.random()
        if r < 0.05:
            return sender, rng.randbytes(rng.randint(0, 300))
        if r < 0.1 or rng.random() < 0.1:   # a valid message: it goes all the way (a Pose moves, a result lands)
            if type_name in ("NetInfo", "Task") and rng.random() < 0.7:   # under a fresh uid: one more held
                body = dict(body, uid=f"fuzz{rng.getrandbits(40):x}")
        else:
            body = damaged_body(rng, body) if isinstance(body, dict) and rng.random() < 0.9 else hostile(rng, 1)
        env = envelope(sender, kind, type_name, body)
        if r < 0.2:   # the envelope itself damaged: any field any value
            env = mutated_json(rng, [env], list(env))
            if isinstance(env, dict):
                env["seq"] = next(seq)
        if r > 0.8 and kind in ("status", "status.fresh", "status.remove"):   # a batch of statuses
            head = {k: v for k, v in env.items() if k in head_fields}
            items = []
            for _ in range(rng.randint(1, 4)):
                s2, k2, t2, b2 = rng.choice([s for s in seeds if s[0] == sender and s[1].startswith("status")])
                item = {k: v for k, v in envelope(s2, k2, t2, b2).items() if k not in head_fields or k == "v"}
                if rng.random() < 0.7:
                    item["body"] = damaged_body(rng, b2)
                items.append(item)
            return sender, as_text(rng, [head, items], []) if rng.random() < 0.1 else dumps([head, items]).encode()
        return sender, as_text(rng, env, []) if rng.random() < 0.1 else dumps(env).encode()

    def check(item: tuple[str, bytes]) -> None:
        sender, payload = item
        c.deliver(sender, payload)
        problems = c.node.problems() + page_state(c.ui)
        count[0] += 1
        if count[0] % MEMORY_EVERY == 0:
            problems += c.held()
        raise_found(problems)

    return gen, check


# --- ARCOS bytes --------------------------------------------------------------------------------


class FakePort:
    """What the driver reads from and writes to, in process: `feed` queues the robot's bytes, and an
    `answer` callback may queue the robot's reply to each command the driver writes (a handshake)."""

    baudrate = 9600

    def __init__(self) -> None:
        self.buffer = bytearray()
        self.answer: Any = None
        self.written = 0

    @property
    def in_waiting(self) -> int:
        return len(self.buffer)

    def read(self, n: int = 1) -> bytes:
        out = bytes(self.buffer[:n])
        del self.buffer[:n]
        return out

    def write(self, data: bytes) -> int:
        self.written += 1
        if self.answer is not None:
            self.buffer += self.answer(bytes(data))
        return len(data)

    def reset_input_buffer(self) -> None:
        self.buffer.clear()

    def flush(self) -> None:
        pass

    def close(self) -> None:
        pass


class Ticks:
    """A clock that moves `step` seconds each time it is read: a handshake's waits end after a few reads."""

    def __init__(self, step: float = 0.02) -> None:
        self.now, self.step = 1000.0, step

    def __call__(self) -> float:
        self.now += self.step
        return self.now


class Robot:
    """A robot agent (the motion plugin, not started: its driver and resource are driven here) stepped in
    process, with an ARCOS driver whose port is in process."""

    def __init__(self) -> None:
        from erni.plugins.motion import RobotMotionControl
        from erni.plugins.motion.driver import ArcosDriver
        from erni.plugins.motion.resource import RobotMotionResource

        self.node = Stepped("robot-fuzz")
        self.motion = self.node.add(RobotMotionControl, {"url": "loop://", "model": "auto"}, "motion")
        self.motion._disabled = True   # its setup would open the port and start threads: its parts are driven here
        self.node.start()
        self.motion.pose = None
        self.clock = Ticks()
        self.driver = ArcosDriver("loop://", "auto", name="robot-fuzz", link_timeout=1e9, pulse_interval=1e9,
                                  sync_timeout=0.1, sync_attempts=2, config_timeout=0.1, clock=self.clock)
        self.port = FakePort()
        self.driver._port = self.port
        self.resource = RobotMotionResource(self.driver, self.motion._publish, name="robot-fuzz",
                                            clock=self.clock)
        self.driver.on_sip = self.resource._sip

    def close(self) -> None:
        self.node.close()


_robot: Robot | None = None


def robot() -> Robot:
    global _robot
    if _robot is None:
        _robot = Robot()
        _open.append(_Forget())
    return _robot


def state_problems(state: Any) -> list[str]:
    from dataclasses import fields

    seen = {f.name: getattr(state, f.name) for f in fields(state)}
    if seen["sim_stamp"] == -math.inf:
        del seen["sim_stamp"]   # the driver's own "no simulator pose yet", not a reading
    bad = non_finite(seen, "RobotState")
    return [f"non-finite number in the driver's state: {bad}"] if bad else []


@surface("ARCOS bytes",
         "the robot's byte stream in random chunks: mutated SIP, CONFIG, SIMSTAT, battery and SYNC2 bodies "
         "re-framed with a valid checksum (so the parsers see them), damaged frames, noise; now and then a whole "
         "handshake whose SYNC and CONFIG answers are damaged; through the driver's reader (`ArcosDriver._service` "
         "on an in-process port), its `RobotState`, the motion resource's publication and the motion plugin's "
         "`Pose` on a blackboard")
def arcos_bytes(_: argparse.Namespace) -> tuple[Any, Any]:
    from erni.plugins.motion import arcos
    from erni.sim.robot import ArcosFirmware, SimRobot, SimRobotConfig

    fw = ArcosFirmware(SimRobot(SimRobotConfig(name="fuzz")))
    sip = fw.sip()
    bodies = [sip, sip, fw.config_packet(), fw.simstat_packet(), fw.battery_packet(), b"Pioneer\x00p3dx\x00fuzz\x00"]
    r = robot()

    def body_of(rng: random.Random) -> bytes:
        body = rng.choice(bodies)
        if rng.random() < 0.9:
            body = mutate(rng, body, bodies) or b"\x32"
        return body[:240]

    def gen(rng: random.Random) -> tuple[list[bytes] | None, list[bytes]]:
        handshake = None
        if rng.random() < 0.05:   # the answers to SYNC0, SYNC1, SYNC2 and CONFIG, each maybe damaged
            handshake = [arcos.frame(b"\x00"), arcos.frame(b"\x01"), arcos.frame(b"\x02" + body_of(rng)[1:] if
                                                                                 rng.random() < 0.5 else bodies[5]),
                         arcos.frame(body_of(rng) if rng.random() < 0.5 else bodies[2])]
            handshake = [mutate(rng, h) if rng.random() < 0.1 else h for h in handshake]
        stream = b""
        for _ in range(rng.randint(1, 4)):
            x = rng.random()
            if x < 0.6:
                stream += arcos.frame(body_of(rng))
            elif x < 0.85:
                stream += mutate(rng, arcos.frame(rng.choice(bodies)[:240]))
            else:
                stream += rng.randbytes(rng.randint(0, 80))
        cuts = sorted(rng.randint(0, len(stream)) for _ in range(rng.randint(0, 4)))
        return handshake, [stream[a:b] for a, b in zip([0, *cuts], [*cuts, len(stream)])]

    def check(item: tuple[list[bytes] | None, list[bytes]]) -> None:
        handshake, chunks = item
        d = r.driver
        if handshake is not None:
            answers = iter(handshake)
            syncs = {arcos.encode_command(n) for n in (0, 1, 2)} | {arcos.encode_command(arcos.Cmd.CONFIG, 1)}
            r.port.answer = lambda data: next(answers, b"") if data in syncs else b""
            try:
                d._start_session(r.port)
            finally:
                r.port.answer = None
                d._port = r.port
        for chunk in chunks:
            r.port.buffer += chunk
            d._service()   # what the reader thread does with what the port gives
            d._port = r.port   # a link loss (none is due: link_timeout is far) would have closed it
        problems = []
        if d.state is not None:
            problems += state_problems(d.state)
        with r.resource._pub_lock:
            r.resource._publish_round()   # the poll thread's publication: the Pose on the blackboard
        r.node.settle()
        raise_found(problems + r.node.problems())

    return gen, check


# --- WebSocket messages -------------------------------------------------------------------------------


class FakeSocket:
    """The page's end of the WebSocket as `WebServer._text` uses it: what is sent to the page is kept."""

    def __init__(self) -> None:
        self.sent: list[str] = []
        self.closed = False

    async def send_str(self, data: str) -> None:
        self.sent.append(data)

    async def close(self, code: int = 1000, message: bytes = b"") -> None:
        self.closed = True


class Page:
    """A control node with the UI plugin (its web server started once, then handed page text directly) and
    a team of four robots on its blackboard, whose tasks the oracle ends as their performers would."""

    def __init__(self) -> None:
        from erni.blackboard import Pose
        from erni.blackboard.schemas import Peer

        self.node = Stepped("control")
        self.ui = self.node.add("ui", ui_settings(), "ui")
        self.node.start()
        self.node.oracle.perform = {f"robot{i}" for i in range(1, 5)}
        with self.node.agent.transaction() as tx:
            for i in range(1, 5):
                tx.add(Pose(robot=f"robot{i}", x=float(i), y=1.0))
                tx.add(Peer(uid=f"peer:robot{i}", name=f"robot{i}", role="robot", up=True, address="127.0.0.1:1"))
        self.node.settle()
        self.server = self.ui.server
        self.emitted: list[dict[str, Any]] = []   # what the handlers emit, before the server's pump takes it
        emit = self.server.emit
        self.server.emit = lambda event, client=None: (self.emitted.append(event.model_dump(warnings=False)), emit(event, client))  # type: ignore[method-assign]
        self.loop = asyncio.new_event_loop()
        self.node.problems()

    def close(self) -> None:
        self.node.close()
        self.loop.close()


_page: Page | None = None


def page() -> Page:
    global _page
    if _page is None:
        _page = Page()
        _open.append(_Forget())
    return _page


WS_SEEDS: list[dict[str, Any]] = [
    {"type": "command", "robots": ["robot1"], "action": "goto", "params": {"x": 1, "y": -2.5}},
    {"type": "command", "robots": ["robot1", "robot2"], "action": "forward", "params": {"distance": 1.5}},
    {"type": "command", "robots": ["robot3"], "action": "turn", "params": {"degrees": 90}},
    {"type": "command", "robots": [], "action": "stop", "params": {}},
    {"type": "command", "robots": ["robot2"], "action": "velocity", "params": {"v": 0.2, "w": 0.1}},
    {"type": "command", "robots": ["robot1", "robot4"], "action": "spread", "params": {}},
    {"type": "say", "text": "robot 1 go forward 2 meters", "selection": ["robot2"]},
    {"type": "say", "text": "robots 1 and 2 turn right 90 degrees", "selection": []},
    {"type": "say", "text": "yes", "selection": []},
    {"type": "say", "text": "cancel that", "selection": []},
    {"type": "select", "robots": ["robot1", "robot2"]},
    {"type": "cancel_task", "uid": "abc"},
    {"type": "mic", "on": True},
    {"type": "ping"},
]
WS_KEYS = ["type", "robots", "action", "params", "text", "selection", "uid", "on", "rate", "x", "y", "distance",
           "degrees", "v", "w", "speed", "theta"]
SAY_WORDS = ["robot", "robots", "1", "2", "3", "and", "go", "forward", "back", "turn", "left", "right", "to", "stop",
             "90", "degrees", "meters", "2.5", "-1", "nan", "1e308", "yes", "no", "cancel", "that", "everyone",
             "teleport", "clear", "spread", "faster", "slower", "\x1b[2J", "\n"]


@surface("WebSocket messages (GUI)",
         "page text: valid messages of every type (commands of every action with their parameters, typed "
         "utterances, selections, cancels, the microphone) with fields replaced, dropped or added (any JSON "
         "value, non-finite numbers, escapes), utterances of grammar words, any JSON, broken JSON, nesting up to "
         "5,000 deep; through `WebServer._text` (as the WebSocket loop hands it over), the UI plugin's handlers "
         "and the tasks they publish on the control node's blackboard; answers and page state checked")
def websocket(_: argparse.Namespace) -> tuple[Any, Any]:
    p = page()
    seeds = [dumps(v).encode() for v in WS_SEEDS]
    count = [0]

    def gen(rng: random.Random) -> str:
        r = rng.random()
        if r < 0.05:
            obj: Any = value(rng, 0, WS_KEYS)
        elif r < 0.3:
            obj = dict(rng.choice([s for s in WS_SEEDS if s["type"] == "say"]))
            obj["text"] = " ".join(rng.choice(SAY_WORDS) for _ in range(rng.randint(1, 10)))
        elif r < 0.45:
            obj = json.loads(dumps(rng.choice(WS_SEEDS)))   # valid: it goes all the way
        else:
            obj = mutated_json(rng, WS_SEEDS, WS_KEYS)
            if isinstance(obj, dict) and isinstance(obj.get("params"), dict) and rng.random() < 0.5:
                obj["params"][rng.choice(WS_KEYS[9:])] = number(rng)
        raw = as_text(rng, obj, seeds)
        return raw.decode("utf-8", "replace")

    def check(message: str) -> None:
        ws = FakeSocket()
        p.loop.run_until_complete(p.server._text("page1", ws, message))
        p.node.settle()
        events, p.emitted[:] = list(p.emitted), []
        problems = p.node.problems()
        for sent in ws.sent:
            if not sent.startswith("{") or non_finite(json.loads(sent)):
                problems.append(f"an answer to the page that is not finite JSON: {sent[:120]!r}")
        for event in events:
            bad = non_finite(event, "event")
            if bad:
                problems.append(f"non-finite number in an event to the page: {bad}")
        count[0] += 1
        if count[0] % 10 == 0:
            problems += page_state(p.ui)
        if count[0] % MEMORY_EVERY == 0:
            n = len(p.node.agent.blackboard.query(lambda o: True))
            if n > 4 * 2 + p.ui.settings.history * 2 + 64:
                problems.append(f"the control node holds {n} objects after {count[0]} page messages")
        raise_found(problems)

    return gen, check


# --- replay logs and bags -----------------------------------------------------------------------


class Replay:
    """A replaying control node: the replay plugin (publishing driven here, not by its thread) and the UI."""

    def __init__(self) -> None:
        from erni.replay import ReplayPlugin

        self.dir = Path(tempfile.mkdtemp(prefix="erni-fuzz-replay-"))
        self.node = Stepped("control")
        self.replay = self.node.add(ReplayPlugin, {"log": str(self.dir / "none.jsonl")}, "replay")
        self.replay._disabled = True   # its setup reads a log and starts a thread: its publishing is driven here
        self.ui = self.node.add("ui", ui_settings(), "ui")
        self.node.start()
        self.node.problems()

    def play(self, path: Path) -> list[str]:
        """Read `path` as `erni replay` does and publish every event, then take it all away again (the
        replay's loop does that at its end); return what the oracles found."""
        from erni.replay import LogError, read_log
        from erni.transport.wire import TYPES

        try:
            _, events, problems = read_log(path)
        except LogError as err:
            return [] if "\n" not in str(err) else [f"a refusal of more than one line: {str(err)[:200]!r}"]
        found = [f"a problem line that is not one line naming the file: {p[:120]!r}" for p in problems
                 if not p.startswith(str(path)) or "\n" in p]
        for event in events:
            self.replay._publish(event)
            self.node.settle()
        found += self.node.problems() + page_state(self.ui)
        with self.node.agent.transaction() as tx:
            for obj in self.node.agent.query(lambda o: type(o).__name__ in TYPES):
                tx.remove(obj)
        self.node.settle()
        self.node.problems()
        return found

    def close(self) -> None:
        self.node.close()


_replay: Replay | None = None


def replayer() -> Replay:
    global _replay
    if _replay is None:
        _replay = Replay()
        _open.append(_Forget())
    return _replay


LOG_VALID: list[dict[str, Any]] = [
    {"t": 0.5, "agent": "robot1", "op": "add", "type": "Pose",
     "data": {"robot": "robot1", "x": 1.0, "y": 2.0, "theta": 0.0, "battery": 12.0}},
    {"t": 0.7, "agent": "robot2", "op": "change", "type": "Pose", "data": {"robot": "robot2", "x": -1.0, "y": 0.5}},
    {"t": 0.8, "agent": "control", "op": "add", "type": "Peer",
     "data": {"uid": "peer:robot1", "name": "robot1", "role": "robot", "up": True, "address": "127.0.0.1:1"}},
    {"t": 1.0, "agent": "control", "op": "change", "type": "Task",
     "data": {"uid": "t1", "verb": "BotMotion", "preposition": "goto", "params": {"x": 1, "y": 2}, "source": "control",
              "destination": "robot1", "result": {"state": "running", "progress": 0.5, "message": "on my way",
                                                  "values": {"d": 1.0}}}},
    {"t": 1.5, "agent": "robot1", "op": "change", "type": "NetInfo",
     "data": {"uid": "net:robot1", "node": "robot1", "kind": "topology",
              "neighbors": [{"name": "robot2", "quality": 0.8}], "links": [{"a": "robot1", "b": "robot2",
                                                                            "quality": 0.7}]}},
    {"t": 2.0, "agent": "robot1", "op": "remove", "type": "Pose", "data": {"robot": "robot1"}},
]
LOG_KEYS = ["t", "agent", "op", "type", "data"]


def log_event(rng: random.Random) -> Any:
    """A recorded change: valid, with its data damaged by hostile values, or with any field any value."""
    event = json.loads(json.dumps(rng.choice(LOG_VALID)))
    r = rng.random()
    if r < 0.3:
        return event
    if r < 0.8:
        event["data"] = damaged_body(rng, event["data"])
        return event
    return mutated_json(rng, LOG_VALID, LOG_KEYS)


@surface("replay logs",
         "a log file: a valid or damaged header, then lines of recorded changes of every type (Pose, Peer, Task "
         "with its result, NetInfo), valid, with data fields replaced by non-finite numbers, escapes, forged lines "
         "or any JSON value, with any field any value, times up to 1e300, broken lines; through `read_log` (every "
         "problem one line naming file and line), the replay plugin's publishing onto a control node's "
         "blackboard and out to its page state")
def replay_logs(_: argparse.Namespace) -> tuple[Any, Any]:
    rp = replayer()
    path = rp.dir / "x.jsonl"
    header = {"erni_record": 1, "via": "fuzz"}
    seeds = [dumps(v).encode() for v in LOG_VALID]

    def gen(rng: random.Random) -> bytes:
        first = dumps(header).encode()
        if rng.random() < 0.05:
            first = mutate(rng, first)
        lines = [first]
        for _ in range(rng.randint(0, 6)):
            obj = log_event(rng)
            if isinstance(obj, dict) and rng.random() < 0.1:
                obj["t"] = rng.choice([1e300, -1.0, float("inf"), float("nan"), 2**70, 2.6e6, True, "1"])
            lines.append(as_text(rng, obj, seeds) if rng.random() < 0.2 else dumps(obj).encode())
        return b"\n".join(lines)

    def check(raw: bytes) -> None:
        path.write_bytes(raw)
        raise_found(rp.play(path))

    return gen, check


def _bag_writer() -> Any:
    from rosbags.rosbag2 import StoragePlugin, Writer
    from rosbags.typesys import Stores, get_typestore

    return Writer, StoragePlugin, get_typestore(Stores.ROS2_JAZZY)


def odometry_bytes(x: float, y: float, theta: float, v: float, w: float, stamp: float) -> bytes:
    """A serialised nav_msgs/msg/Odometry with these numbers, whatever they are (a bag's numbers are
    unchecked); a heading that is not finite goes into the quaternion as it is."""
    from erni.blackboard import Pose
    from erni.plugins.ros2 import messages as ros

    msg = ros.odometry(Pose(robot="r", x=0.0, y=0.0, theta=0.0), int(stamp * 1e9))
    msg.pose.pose.position.x, msg.pose.pose.position.y = x, y
    q = msg.pose.pose.orientation
    q.z, q.w = (math.sin(theta / 2), math.cos(theta / 2)) if math.isfinite(theta) else (theta, theta)
    msg.twist.twist.linear.x, msg.twist.twist.angular.z = v, w
    return ros.serialize(msg)


@surface("MCAP bags",
         "a rosbag2 MCAP bag as rosbags writes it: Odometry on /<robot>/odom topics (names of robots, escapes, "
         "empty parts) with finite, huge and non-finite numbers, ERNI statuses on /diagnostics whose 'erni' JSON "
         "is a recorded change with hostile data or any JSON, /erni/task_status strings; some bags damaged as "
         "bytes; through `read_log` (`read_bag`, the bounds first), the replay plugin's publishing onto a control "
         "node's blackboard and out to its page state")
def mcap_bags(_: argparse.Namespace) -> tuple[Any, Any]:
    from erni.plugins.ros2 import messages as ros

    rp = replayer()
    Writer, StoragePlugin, store = _bag_writer()
    folder = rp.dir / "bags"
    folder.mkdir(exist_ok=True)
    numbers = [0.0, 1.5, -3.25, 1e308, -1e308, float("nan"), float("inf"), float("-inf"), 5e-324]
    topics = ["/robot1/odom", "/robot2/odom", "/r\x1b[2J/odom", "/robot1\n/odom", "//odom", "/robot3/odom/x"]
    made = [0]

    def gen(rng: random.Random) -> tuple[list[tuple[str, str, list[bytes]]], int]:
        conns: list[tuple[str, str, list[bytes]]] = []
        for _ in range(rng.randint(1, 3)):
            r = rng.random()
            if r < 0.5:
                msgs = [odometry_bytes(*(rng.choice(numbers) if rng.random() < 0.3 else rng.uniform(-10, 10)
                                         for _ in range(5)), 1.7e9 + i) for i in range(rng.randint(1, 3))]
                conns.append((rng.choice(topics), ros.ODOMETRY, msgs))
            elif r < 0.85:
                events = []
                for _ in range(rng.randint(1, 3)):
                    event = log_event(rng)
                    text_ = dumps(event) if rng.random() < 0.9 else text(rng, 20)
                    events.append(text_)
                conns.append(("/diagnostics", ros.DIAGNOSTIC_ARRAY, [diagnostic(e) for e in events]))
            else:
                status = {"uid": "t1", "verb": "BotMotion", "preposition": "goto", "params": {"x": 1},
                          "destination": "robot1", "state": "running", "progress": 0.5, "message": "m"}
                status = damaged_body(rng, status) if rng.random() < 0.7 else status
                conns.append(("/erni/task_status", ros.STRING, [string_msg(dumps(status))]))
        return conns, rng.getrandbits(32) if rng.random() < 0.1 else 0

    def check(item: tuple[list[tuple[str, str, list[bytes]]], int]) -> None:
        conns, damage = item
        made[0] += 1
        bag = folder / f"b{made[0]}"
        writer = Writer(bag, version=9, storage_plugin=StoragePlugin.MCAP)
        writer.open()
        for i, (topic, kind, msgs) in enumerate(conns):
            conn = writer.add_connection(topic, kind, typestore=store) if topic not in [c[0] for c in conns[:i]] \
                else next(c for c in writer.connections if c.topic == topic)
            for j, data in enumerate(msgs):
                writer.write(conn, (1_700_000_000 + j) * 10**9, data)
        writer.close()
        mcap = bag / f"{bag.name}.mcap"
        if damage:
            mrng = random.Random(damage)
            mcap.write_bytes(mutate(mrng, mcap.read_bytes()))
        try:
            raise_found(rp.play(mcap))
        finally:
            for f in bag.iterdir():
                f.unlink()
            bag.rmdir()

    return gen, check


def diagnostic(event_json: str) -> bytes:
    """A serialised DiagnosticArray holding one status whose 'erni' value is `event_json`."""
    from erni.plugins.ros2 import messages as ros

    kv = ros.make("diagnostic_msgs/msg/KeyValue", key="erni", value=event_json)
    status = ros.make("diagnostic_msgs/msg/DiagnosticStatus", name="erni", hardware_id="robot1", values=[kv])
    return ros.serialize(ros.make(ros.DIAGNOSTIC_ARRAY, header=ros.header(1_700_000_000 * 10**9, "map"),
                                  status=[status]))


def string_msg(data: str) -> bytes:
    from erni.plugins.ros2 import messages as ros

    return ros.serialize(ros.make(ros.STRING, data=data))
