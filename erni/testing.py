"""What a plugin author needs to unit-test a plugin in a few lines.

An agent holding the plugin under test, tasked from the test and waited on without blind sleeps::

    from erni.testing import agent_with, run_task

    def test_greeter_answers_goto():
        with agent_with(Greeter, settings={"greeting": "hi"}) as agent:
            done = run_task(agent, "BotMotion", "goto", x=1, y=2)
        assert done.result is not None and done.result.message == "hi: going to (1.0, 2.0)"

Several agents that task each other over an in-memory network (seedable loss, delay, partitions),
with the real transport plugin on it::

    with MockTeam(seed=1, loss=0.2) as team:
        team.add("control", role="control")
        team.add("robot1").add_plugin(Greeter)
        team.start()
        done = run_task(team["control"], "BotMotion", "stop", destination="robot1")

Time the test owns: `ManualClock`, given as `agent_with(..., clock=clock)`, times the agent's
wake-ups, slow-run watch and task retention; `clock.advance(5.0)` runs what falls due at once.

A robot for motion plugins and missions: `fake_robot()` gives the settings of the motion plugin
on ERNI's simulated ARCOS robot, in the agent's own process (`agent.add_plugin("motion",
settings=fake_robot())`).

Nothing here is used by an agent at run time.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable
from typing import Any

from erni.blackboard import clock
from erni.blackboard.agent import Agent
from erni.blackboard.errors import UsageError
from erni.blackboard.plugin import Plugin
from erni.blackboard.schemas import Peer
from erni.blackboard.tasks import Task, TaskState
from erni.blackboard.testing import wait_until
from erni.transport.mock import MockNetwork
from erni.transport.plugin import TransportPlugin

__all__ = ["MockNetwork", "MockTeam", "agent_with", "fake_robot", "find_task", "post_task", "run_task",
           "wait_for_task", "wait_until"]

# the simulated robot of `fake_robot()`: a SIP every 20 ms, a planner that brakes hard, so tests run fast
FAST_ROBOT = {"base": "pioneer3", "decel": 2.5, "rot_decel": 500.0, "max_rv": 300.0, "max_v": 2.0}


def agent_with(plugin: type[Plugin[Any]] | str | None = None, settings: dict[str, Any] | None = None, *,
               name: str = "robot1", plugin_name: str | None = None, workers: int = 2,
               clock: Callable[[], float] | None = None) -> Agent:
    """An agent named `name` holding `plugin` (a class, `module:Class` or an entry point name) with
    `settings`, not started: add more plugins if needed, then `with agent:` starts and stops it.
    `clock`: the agent's clock (a `ManualClock` to time its wake-ups from the test)."""
    agent = Agent(name, workers=workers) if clock is None else Agent(name, workers=workers, clock=clock)
    if plugin is not None:
        agent.add_plugin(plugin, settings=settings, name=plugin_name)
    return agent


def post_task(agent: Agent, verb: str, preposition: str, *, destination: str | None = None,
              source: str | None = None, **params: Any) -> Task:
    """Publish a task on `agent`'s blackboard (from `source`, default the agent itself) and return it.
    With a `destination` another agent performs it (through the agent's transport)."""
    task = Task(verb=verb, preposition=preposition, params=params, source=source or agent.name,
                destination=destination)
    with agent.transaction() as tx:
        tx.add(task)
    return task


def find_task(agent: Agent, uid: str) -> Task | None:
    """The task with this uid as `agent`'s blackboard holds it now (None if it is not there)."""
    found = agent.blackboard.get(uid)
    return found if isinstance(found, Task) else None


def wait_for_task(agent: Agent, task: Task | str, state: TaskState | None = None, timeout: float = 5.0) -> Task:
    """Wait until the task is done (or, with `state`, in that state) on `agent`'s blackboard; return
    that version. AssertionError naming the task and its last state on timeout."""
    uid = task if isinstance(task, str) else task.uid

    def reached() -> Task | None:
        now = find_task(agent, uid)
        if now is None:
            return None
        return now if (now.state is state if state is not None else now.done) else None

    try:
        found: Task = wait_until(reached, timeout=timeout)  # type: ignore[assignment]  # truthy: a Task
        return found
    except AssertionError:
        now = find_task(agent, uid)
        seen = "not on the blackboard" if now is None else f"{now.state.value}: {now.result.message if now.result else ''}"
        wanted = state.value if state is not None else "done"
        raise AssertionError(f"task {uid} not {wanted} within {timeout:g} s at {agent.name} ({seen})") from None


def run_task(agent: Agent, verb: str, preposition: str, *, destination: str | None = None,
             timeout: float = 5.0, **params: Any) -> Task:
    """Post a task on `agent` (`post_task`) and return it once it is done (`wait_for_task`)."""
    return wait_for_task(agent, post_task(agent, verb, preposition, destination=destination, **params),
                         timeout=timeout)


def fake_robot(name: str = "robot1", **settings: Any) -> dict[str, Any]:
    """Settings of the motion plugin (`"motion"`) driving a simulated ARCOS robot in the agent's
    own process: a fast Pioneer at the origin of an empty world. `settings` override any key
    (`url="simrobot://?world=FILE"` puts it in a world)."""
    return {"url": f"simrobot://?sip_period=0.02&name={name}", "model": dict(FAST_ROBOT), "rate_hz": 50,
            "pose_rate_hz": 25, "sync_timeout": 0.3, **settings}


def _transport(agent: Agent) -> TransportPlugin:
    plugin = agent.plugin("transport")
    assert isinstance(plugin, TransportPlugin)
    return plugin


class MockTeam:
    """Agents whose transports talk over one `MockNetwork` (no sockets, no keys).

    `add(name, role=...)` returns the agent, not started, with its transport on the network; add
    the plugins under test to it, then `start()` starts every agent and waits until each one
    sees every other up. Used as a context manager, it stops them all at the end.
    """

    def __init__(self, seed: int = 0, *, network: MockNetwork | None = None, **loss: Any):
        self.network = network if network is not None else MockNetwork(seed, **loss)
        self.agents: dict[str, Agent] = {}
        self._started: list[Agent] = []

    def add(self, name: str, *, role: str = "robot", workers: int = 2, **transport: Any) -> Agent:
        """A new agent of the team with its transport plugin (named `transport`; `transport` overrides
        its settings); role `control` tasks anyone, `robot` performs."""
        if name in self.agents:
            raise UsageError(f"MockTeam: there is already an agent {name}")
        net = self.network

        class OnMockNetwork(TransportPlugin):
            endpoint_factory = staticmethod(net.endpoint)

        agent = Agent(name, workers=workers)
        settings = {"insecure": True, "discovery_port": 0, "beacon_period": 0.1, "peer_timeout": 1.0,
                    "ack_timeout": 0.2, "role": role, **transport}
        agent.add_plugin(OnMockNetwork, settings=settings, name="transport")
        self.agents[name] = agent
        return agent

    def __getitem__(self, name: str) -> Agent:
        return self.agents[name]

    def start(self, timeout: float = 5.0) -> MockTeam:
        """Start the agents in the order they were added (each one knows the ones before as static
        peers; they learn it from its beacons), then wait until all see each other up."""
        for agent in self.agents.values():
            if agent in self._started:
                continue
            peers = ["{}@{}:{}".format(a.name, *_transport(a).address) for a in self._started]
            transport = _transport(agent)
            transport.settings = transport.settings.model_copy(update={"peers": peers})
            agent.start()
            self._started.append(agent)
        self.wait_connected(timeout)
        return self

    def wait_connected(self, timeout: float = 5.0, names: Iterable[str] | None = None) -> None:
        """Wait until every agent (of `names`) sees every other up."""
        group = [self.agents[n] for n in (names if names is not None else self.agents)]
        wanted = {a.name for a in group}

        def connected() -> bool:
            return all(wanted - {a.name} <= {p.name for p in a.query(Peer) if p.up} for a in group)

        wait_until(connected, timeout=timeout, message=f"agents {sorted(wanted)} did not all see each other up")

    def stop(self) -> None:
        """Stop every agent started, the last started first."""
        while self._started:
            self._started.pop().stop()

    def __enter__(self) -> MockTeam:
        return self

    def __exit__(self, *exc: Any) -> None:
        self.stop()


class ManualClock:
    """A clock that moves only when the test says: give it to `Agent(clock=...)`, then `advance()`.

    Plugin wake-ups (`wake_in`, `wake_every`), the slow-run watch, task retention and the
    transport's waits (a peer's silence, a task's deadline, a handshake, an idle session) are timed
    by the agent's clock; an agent made with this one runs them when the test advances it, without
    waiting for them. (Thread joins at stop, socket waits, retries' pace and robots keep real time.)

        clock = ManualClock()
        with agent_with(Ticker, clock=clock) as agent:
            clock.advance(5.0)      # Ticker's wake_every(5.0) is due: it runs now
    """

    def __init__(self, start: float = 1000.0, *, wall_start: float | None = None) -> None:
        self.now = start
        self._wall_offset = (clock.wall() if wall_start is None else wall_start) - start
        self._watchers: list[Any] = []

    def __call__(self) -> float:
        return self.now

    def wall(self) -> float:
        """Seconds since the epoch: `wall_start` (the process's wall time when made, by default), moved
        as the clock is advanced."""
        return self.now + self._wall_offset

    def on_advance(self, fn: Any) -> None:
        """Call `fn()` after every `advance` (the agent's timers look at the clock again)."""
        self._watchers.append(fn)

    def advance(self, seconds: float) -> float:
        """Move the clock forward by `seconds` (not back) and return the new time."""
        if not seconds >= 0:
            raise UsageError(f"ManualClock.advance: expected seconds >= 0, got {seconds}")
        self.now += seconds
        for fn in list(self._watchers):
            fn()
        return self.now
