"""Network-aware behaviour: a robot that becomes a cut vertex (or loses its links) holds, stops or retreats."""

from __future__ import annotations

from collections.abc import Iterator

import pytest

from erni.blackboard import Task, TaskState
from erni.blackboard.tasks import Link
from erni.blackboard.testing import wait_until
from erni.plugins.mission.netaware import NetGuard
from erni.sim.manet import ManetNetwork, RadioModel
from erni.sim.snmp_agent import ManetSnmpAgent
from tests.core.helpers import scheduler_idle
from tests.mission.conftest import current, plugin, pose_of, send, subs_of


@pytest.fixture
def manet() -> Iterator[tuple[ManetNetwork, dict[str, tuple[str, int]]]]:
    """robot0 - robot1 - robot2 in a line, 30 m apart, R = 40 m: robot1 is a cut vertex."""
    net = ManetNetwork(RadioModel(40.0, 20.0, 0.1))
    for name, x in (("robot0", -30.0), ("robot1", 0.0), ("robot2", 30.0)):
        net.add_node(name, x, 0.0)
    agent = ManetSnmpAgent(net).start()
    try:
        yield net, agent.serve_all()
    finally:
        agent.close()


def mobinet(addresses, name="robot1"):
    host, port = addresses[name]
    return ("mobinet", {"host": host, "port": port, "timeout": 0.3, "cache_seconds": 0.0}, "mobinet")


def message(agent, task) -> str:
    t = current(agent, task.uid)
    return t.result.message if t is not None and t.result else ""


def guard_stops(agent) -> list[Task]:
    return agent.query(Task, where=lambda t: t.preposition == "stop" and t.source == agent.name and not t.parent)


def test_hold_when_a_cut_vertex_and_resume_when_no_longer(robots, manet):
    net, addresses = manet
    agent = robots("robot1", extra=[mobinet(addresses)],
                   mission={"network_aware": True, "policy": "hold", "min_link_quality": 0.05,
                            "resume_after": 0.3, "net_rate_hz": 10.0})
    watches = agent.query(Task, where=lambda t: t.verb == "NetWatch" and t.source == "robot1")
    assert sorted(t.preposition for t in watches) == ["link_quality", "network_topology", "node_position"]
    task = send(agent, "goto", x=3.0, y=0.0, speed=1.2)
    wait_until(lambda: "articulation point" in message(agent, task), timeout=10,
               message="the guard never held the robot")
    assert message(agent, task).startswith("holding: robot1 is an articulation point")
    assert len(guard_stops(agent)) == 1
    assert current(agent, task.uid).state == TaskState.RUNNING
    held_at = pose_of(agent).x
    assert held_at < 0.5
    net.move("robot2", -30.0, 10.0)  # robot2 next to robot0: robot1 is now a leaf
    wait_until(lambda: message(agent, task) == "resumed: connectivity restored", timeout=10,
               message="never resumed")
    assert not guard_stops(agent)
    done = wait_until(lambda: (t := current(agent, task.uid)).done and t, timeout=10)
    assert done.state == TaskState.SUCCEEDED
    assert pose_of(agent).x > 2.8
    # a cut vertex again: nothing runs, so nothing is held
    net.move("robot2", 30.0, 0.0)
    wait_until(lambda: plugin(agent).guard.state.at_risk, timeout=10)
    assert not guard_stops(agent)


def test_stop_policy_fails_the_task_with_the_reason_when_the_best_link_is_poor(robots, manet):
    net, addresses = manet
    net.move("robot0", -36.0, 0.0)
    net.move("robot2", 60.0, 0.0)  # robot1 s only link: 36 m, quality (40 - 36) / (40 - 20) = 0.2
    agent = robots("robot1", extra=[mobinet(addresses)],
                   mission={"network_aware": True, "policy": "stop", "min_link_quality": 0.5,
                            "articulation": False, "net_rate_hz": 10.0})
    wait_until(lambda: plugin(agent).guard.state.at_risk, timeout=10,
               message="poor link not noticed")
    task = send(agent, "forward", distance=5.0, speed=0.5)
    done = wait_until(lambda: (t := current(agent, task.uid)).done and t, timeout=5)
    assert done.state == TaskState.FAILED
    assert done.result.message == "stopped: best link quality 0.20 is below 0.50"
    assert not subs_of(agent, task.uid)
    assert abs(pose_of(agent).v) < 0.05


def test_retreat_policy_goes_back_along_the_good_trail_then_resumes(robots, manet):
    net, addresses = manet
    net.move("robot2", -30.0, 10.0)  # robot1 is a leaf: connectivity good where it stands
    agent = robots("robot1", extra=[mobinet(addresses)],
                   mission={"network_aware": True, "policy": "retreat", "min_link_quality": 0.05,
                            "resume_after": 0.2, "net_rate_hz": 10.0, "speed": 1.0, "retreat_distance": 1.0})
    task = send(agent, "goto", x=8.0, y=0.0, speed=1.0)
    wait_until(lambda: pose_of(agent).x > 2.0, timeout=5, message="never moved")
    net.move("robot2", 30.0, 0.0)  # cut vertex again, mid-way
    wait_until(lambda: message(agent, task).startswith("retreating to ("), timeout=10)
    risk_at = pose_of(agent).x
    wait_until(lambda: guard_stops(agent), timeout=10, message="no hold after the retreat")
    back = pose_of(agent).x
    assert risk_at - back > 0.7, (risk_at, back)
    net.move("robot2", -30.0, 10.0)
    wait_until(lambda: message(agent, task) == "resumed: connectivity restored", timeout=10)
    wait_until(lambda: pose_of(agent).x > back + 0.5, timeout=5, message="did not carry on after resuming")
    assert not guard_stops(agent) and current(agent, task.uid).state == TaskState.RUNNING


def test_guard_hysteresis_and_degraded_readings():
    g = NetGuard("a", min_quality=0.3, resume_after=1.0)
    assert g.update(0.0, (0, 0)) is None  # nothing read yet
    g.topology([Link(a="a", b="b"), Link(a="a", b="c")])  # no qualities: a is a cut vertex
    assert g.update(0.1, (0, 0)) == "risk"
    g.topology([Link(a="a", b="b"), Link(a="a", b="c"), Link(a="b", b="c")])
    g.quality([0.9, 0.2])
    assert g.update(0.5, (1, 1)) is None and g.pending_clear_in(0.5) == pytest.approx(1.0)
    g.quality([0.1])
    assert g.update(0.8, (1, 1)) is None and g.state.reason.startswith("best link quality 0.10")
    g.quality([0.4])
    assert g.update(1.0, (2, 2)) is None
    assert g.update(2.1, (2, 2)) == "clear"
    assert g.last_good is None  # no good reading was ever taken outside a risk
    for x in (3.0, 3.1, 3.3, 4.0, 5.0):
        assert g.update(3.0 + x, (x, 0.0)) is None
    assert g.last_good == (5.0, 0.0)
    assert list(g.trail) == [(3.0, 0.0), (3.3, 0.0), (4.0, 0.0), (5.0, 0.0)]
    assert g.retreat_point((5.0, 0.0), 1.0) == (4.0, 0.0)
    assert g.retreat_point((5.0, 0.0), 9.0) == (3.0, 0.0)


def test_the_same_reading_again_is_not_judged_again_and_a_changed_quality_is(monkeypatch):
    import erni.plugins.mission.netaware as netaware

    graphs = []
    real = netaware.netgraph.from_edges
    monkeypatch.setattr(netaware.netgraph, "from_edges", lambda *a, **k: graphs.append(1) or real(*a, **k))
    rows = [Link(a="a", b="b", quality=0.9), Link(a="a", b="c", quality=0.9), Link(a="b", b="c", quality=0.9)]
    g = NetGuard("a", min_quality=0.3)
    g.topology(rows)
    assert (g.risk(), len(graphs)) == ("", 1)
    for _ in range(5):  # a reading whose walk was not redone: a new list of the very same rows
        g.topology(list(rows))
    assert len(graphs) == 1
    g.topology([rows[0].model_copy(update={"quality": 0.5}), rows[1], rows[2]])  # a quality moved
    assert len(graphs) == 1 and g.risk() == ""  # which links are good did not change: no graph work
    lone = [rows[0], rows[1].model_copy(update={"quality": 0.1}), Link(a="b", b="c", quality=0.1)]
    g.topology(lone)
    assert len(graphs) == 2 and g.risk() == "a's weak link to c (0.10) alone joins it to the rest of the network"


def _guards(links: list[Link], *names: str) -> dict[str, str]:
    """Each named robot's risk for one topology reading ("" when none)."""
    out = {}
    for name in names:
        g = NetGuard(name, min_quality=0.3)
        g.topology(links)
        out[name] = g.risk()
    return out


def test_robots_walking_off_together_are_each_at_risk_on_their_weak_link_before_it_goes():
    """The aware random walk once kept connectivity 36 % of a run: all four robots walked away from
    the control node, two of them each with a link to it. Neither was a cut vertex while both
    links stood, and when one went the other was already out of reach. Judged without the links
    below `min_quality`, each holds on its own weak link while it still carries packets."""
    ctl = "control"
    drift = [Link(a=ctl, b="r1", quality=0.25), Link(a=ctl, b="r2", quality=0.28),
             Link(a="r1", b="r2", quality=1.0), Link(a="r2", b="r3", quality=1.0), Link(a="r1", b="r3", quality=0.9)]
    risk = _guards(drift, "r1", "r2", "r3")
    assert risk["r1"] == "r1's weak link to control (0.25) alone joins it to the rest of the network"
    assert risk["r2"].startswith("r2's weak link to control (0.28)")
    assert risk["r3"] == ""  # it has only good links, and it is no cut vertex of them
    # one link still good: its robot is the cut vertex; the other's weak link is no longer alone
    held = [Link(a=ctl, b="r1", quality=0.9), *drift[1:]]
    risk = _guards(held, "r1", "r2", "r3")
    assert risk == {"r1": "r1 is an articulation point of the network", "r2": "", "r3": ""}
    # without qualities (a routing protocol whose metric does not tell them) every link counts
    plain = [Link(a=link.a, b=link.b) for link in drift]
    assert _guards(plain, "r1", "r2", "r3") == {"r1": "", "r2": "", "r3": ""}
    assert _guards([], "r1") == {"r1": ""}


def test_a_stop_while_held_by_the_guard_ends_the_task_and_it_does_not_resume_when_connectivity_returns(robots, manet):
    """A robot standing by under the guard's hold: an operator's stop ends its held task (cancelled,
    naming who), the hold goes, and connectivity coming back does not set it moving again."""
    net, addresses = manet
    agent = robots("robot1", extra=[mobinet(addresses)],
                   mission={"network_aware": True, "policy": "hold", "min_link_quality": 0.05,
                            "resume_after": 0.3, "net_rate_hz": 10.0})
    task = send(agent, "goto", x=3.0, y=0.0, speed=1.2)
    wait_until(lambda: "articulation point" in message(agent, task), timeout=10,
               message="the guard never held the robot")
    stop = Task(verb="BotMotion", preposition="stop", source="control", destination="robot1")
    with agent.transaction() as tx:
        tx.add(stop)
    ended = wait_until(lambda: (t := current(agent, task.uid)).done and t, timeout=5,
                       message="the held task did not end on the stop")
    assert ended.state == TaskState.CANCELLED and ended.result.message == f"stopped by control (task {stop.uid})"
    wait_until(lambda: not guard_stops(agent), timeout=5, message="the guard's hold stayed after the stop")
    assert wait_until(lambda: (t := current(agent, stop.uid)).done and t, timeout=5).state == TaskState.SUCCEEDED
    held_at = pose_of(agent).x
    net.move("robot2", -30.0, 10.0)  # connectivity returns
    mission = plugin(agent)
    wait_until(lambda: not mission.guard.state.at_risk, timeout=10)
    # the run that cleared (it would resume a held job at once) is over; then a second of SIPs
    wait_until(lambda: scheduler_idle(mission), timeout=10)
    assert not [t for t in agent.query(Task) if t.verb == "BotMotion" and not t.done], "a motion resumed"
    driver = agent.plugin("motion").resource.driver
    sips = driver.stats.sips
    wait_until(lambda: driver.stats.sips >= sips + max(1, round(1.0 / driver.sip_interval)), timeout=30)
    assert abs(pose_of(agent).x - held_at) < 0.02 and abs(pose_of(agent).v) < 0.01  # nothing resumed
    assert not [t for t in agent.query(Task) if t.verb == "BotMotion" and not t.done], "a motion resumed"
