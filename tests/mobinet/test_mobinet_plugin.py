"""MobiNetControl in a real agent, against the simulated MANET over real UDP SNMP."""

from __future__ import annotations

import logging
import math
import time

import pytest

from erni.blackboard import Agent, NetInfo, Pose, Task, TaskState
from erni.blackboard.testing import wait_until
from erni.sim.manet import METRIC_UNIT, link_metric
from erni.sim.snmp_agent import ManetSnmpAgent
from tests.core.helpers import scheduler_idle
from tests.mobinet.conftest import WRITE

PREPOSITIONS = ["node_position", "network_topology", "path_cost", "link_quality", "neighbor_list"]


@pytest.fixture
def make_agent():
    agents: list[Agent] = []

    def make(name: str, address: tuple[str, int], **settings) -> tuple[Agent, object]:
        agent = Agent(name, workers=2)
        plugin = agent.add_plugin("erni.plugins.mobinet:MobiNetControl",
                                  settings={"host": address[0], "port": address[1],
                                            "write_community": WRITE, **settings},
                                  name="mobinet")
        agent.start()
        agents.append(agent)
        return agent, plugin

    yield make
    for agent in agents:
        agent.stop()


def watch(agent: Agent, preposition: str, rate_hz: float = 20.0, **params) -> Task:
    task = Task(verb="NetWatch", preposition=preposition, params={"rate_hz": rate_hz, **params},
                source="test")
    with agent.transaction() as tx:
        tx.add(task)
    return task


def info_of(agent: Agent, task: Task) -> NetInfo | None:
    found = agent.query(NetInfo, where=lambda i: i.task == task.uid)
    return found[0] if found else None


def fresh(agent: Agent, task: Task, check=lambda info: True, timeout: float = 5.0) -> NetInfo:
    """Wait for a non-degraded NetInfo of `task` that satisfies `check`."""
    def ok():
        info = info_of(agent, task)
        return info if info and info.stamp and not info.degraded and not info.message \
            and check(info) else None
    return wait_until(ok, timeout=timeout)


def result_of(agent: Agent, task: Task) -> Task:
    return agent.query(Task, where=lambda t: t.uid == task.uid)[0]


def test_every_netwatch_preposition_is_answered_from_live_snmp(served, net, make_agent):
    agent, _ = make_agent("robot2", served["robot2"])
    tasks = {p: watch(agent, p) for p in PREPOSITIONS}
    truth = net.truth()

    nbrs = fresh(agent, tasks["neighbor_list"], lambda i: i.neighbors)
    assert [n.name for n in nbrs.neighbors] == ["robot1", "robot3"]
    assert nbrs.node == "robot2" and nbrs.kind == "neighbor_list"
    assert nbrs.uid == f"netinfo:{tasks['neighbor_list'].uid}"

    quality = fresh(agent, tasks["link_quality"], lambda i: i.neighbors)
    assert {n.name: n.quality for n in quality.neighbors} == {"robot1": 0.8, "robot3": 0.8}
    assert all(n.metric == link_metric(0.8) for n in quality.neighbors)

    topo = fresh(agent, tasks["network_topology"], lambda i: i.links)
    assert {frozenset((l.a, l.b)) for l in topo.links} == set(truth.links)
    assert set(topo.articulation_points) == truth.articulation_points

    paths = fresh(agent, tasks["path_cost"], lambda i: i.routes)
    to5 = next(r for r in paths.routes if r.destination == "robot5")
    assert (to5.next_hop, to5.hops, to5.cost) == ("robot3", 3, 3 * link_metric(0.8) / METRIC_UNIT)

    pos = fresh(agent, tasks["node_position"], lambda i: i.positions)
    assert {n: (p.x, p.y) for n, p in pos.positions.items()} == {
        n: xy for n, xy in truth.positions.items()}

    for prep, task in tasks.items():
        res = wait_until(lambda task=task: (t := result_of(agent, task)).result and
                         t.result.values.get("netinfo") and len(t.result.values) > 1 and t)
        assert res.result.state == TaskState.RUNNING, prep
        assert res.result.values["netinfo"] == f"netinfo:{task.uid}"
    topo_task = result_of(agent, tasks["network_topology"])
    assert topo_task.result.values["articulation_point"] is True
    assert result_of(agent, tasks["neighbor_list"]).result.values["neighbors"] == ["robot1", "robot3"]


def test_poses_are_written_to_the_network_subsystem(served, net, make_agent):
    agent, plugin = make_agent("robot2", served["robot2"])
    with agent.transaction() as tx:
        tx.add(Pose(robot="robot2", x=61.25, y=3.5, theta=math.pi / 2))
        tx.add(Pose(robot="robot9", x=999.0, y=999.0))          # another robot: not ours
    wait_until(lambda: net.view("robot5").positions["robot2"].x == 61.25)
    known = net.view("robot5").positions["robot2"]
    assert (known.y, known.heading) == (3.5, 90.0)
    pose = agent.query(Pose, where=lambda p: p.robot == "robot2")[0]
    with agent.transaction() as tx:
        tx.change(pose.evolve(x=62.0, theta=-math.pi / 4))
    wait_until(lambda: net.view("robot1").positions["robot2"].x == 62.0)
    assert net.view("robot1").positions["robot2"].heading == -45.0
    assert net.view("robot2").position_updates == 2
    assert plugin.resource.stats["write_errors"] == 0


def test_cancelling_a_task_stops_its_monitoring(served, net, make_agent):
    agent, plugin = make_agent("robot2", served["robot2"])
    task = watch(agent, "neighbor_list", rate_hz=50)
    other = watch(agent, "path_cost", rate_hz=1)
    fresh(agent, task, lambda i: i.neighbors)
    with agent.transaction() as tx:
        tx.remove(task)
    wait_until(lambda: info_of(agent, task) is None)
    wait_until(lambda: plugin.resource.watching() == [other.uid])
    assert info_of(agent, other) is not None


def test_a_task_removed_while_the_plugin_starts_it_leaves_nothing_behind(served, net, make_agent, caplog):
    """The requester removes a NetWatch task while MobiNet's run is starting it (its own thread,
    between the run's view and its changes): no traceback, no NetInfo left, the plugin still works."""
    import threading

    agent, plugin = make_agent("robot2", served["robot2"])
    start = plugin._start
    removed: list[str] = []

    def start_after_removal(task):
        if not removed:
            def remove():
                with agent.transaction() as tx:
                    tx.remove(task)
            t = threading.Thread(target=remove)
            t.start()
            t.join()
            removed.append(task.uid)
        start(task)

    plugin._start = start_after_removal
    task = watch(agent, "neighbor_list", rate_hz=50)
    wait_until(lambda: removed and not plugin._running and not agent.query(Task, where=lambda t: t.uid == task.uid))
    plugin._start = start
    again = watch(agent, "neighbor_list", rate_hz=50)
    fresh(agent, again, lambda i: i.neighbors)
    wait_until(lambda: plugin.resource.watching() == [again.uid])
    assert info_of(agent, task) is None
    assert not [r for r in caplog.records if r.levelno >= logging.ERROR], caplog.text


def test_moving_nodes_changes_what_the_plugin_publishes(served, net, make_agent):
    agent, _ = make_agent("robot3", served["robot3"])
    nbrs = watch(agent, "neighbor_list")
    topo = watch(agent, "network_topology")
    paths = watch(agent, "path_cost", destination="robot5")
    fresh(agent, topo, lambda i: set(i.articulation_points) == {"robot2", "robot3", "robot4"})
    net.move("robot5", 150.0, 40.0)      # robot5 comes next to robot3 and robot4
    fresh(agent, topo, lambda i: set(i.articulation_points) == {"robot2", "robot3"})
    fresh(agent, nbrs, lambda i: {n.name for n in i.neighbors} == {"robot2", "robot4", "robot5"})
    route = fresh(agent, paths, lambda i: i.routes and i.routes[0].hops == 1).routes
    assert [r.destination for r in route] == ["robot5"]
    net.move("robot2", 60.0, 300.0)      # robot1 and robot2 leave: robot3 is no longer a cut vertex
    fresh(agent, topo, lambda i: i.articulation_points == [] and len(i.links) == 3)
    fresh(agent, nbrs, lambda i: {n.name for n in i.neighbors} == {"robot4", "robot5"})
    res = wait_until(lambda: (t := result_of(agent, topo)).result.values.get(
        "articulation_point") is False and t)
    assert res.result.values["articulation_points"] == []


def test_articulation_points_are_found_again_only_when_the_links_change(served, net, make_agent, monkeypatch):
    import erni.plugins.mobinet.control as control

    calls = []
    real = control.articulation_points
    monkeypatch.setattr(control, "articulation_points", lambda links: calls.append(len(links)) or real(links))
    agent, plugin = make_agent("robot3", served["robot3"])
    topo = watch(agent, "network_topology", rate_hz=20.0)
    fresh(agent, topo, lambda i: set(i.articulation_points) == {"robot2", "robot3", "robot4"})
    polls = plugin._polls[topo.uid]
    wait_until(lambda: plugin._polls[topo.uid] >= polls + 10)   # ten readings of the same links
    assert len(calls) == 1
    net.move("robot5", 150.0, 40.0)
    fresh(agent, topo, lambda i: set(i.articulation_points) == {"robot2", "robot3"})
    assert len(calls) == 2


def test_filters_and_missing_targets(served, net, make_agent):
    agent, _ = make_agent("robot1", served["robot1"])
    to3 = watch(agent, "path_cost", destination="10.0.0.3")
    nowhere = watch(agent, "path_cost", destination="robot42")
    one = watch(agent, "link_quality", neighbor="robot2")
    stranger = watch(agent, "link_quality", neighbor="robot5")
    info = fresh(agent, to3, lambda i: i.routes)
    assert [(r.destination, r.hops) for r in info.routes] == [("robot3", 2)]
    assert fresh(agent, one, lambda i: i.neighbors).neighbors[0].name == "robot2"
    wait_until(lambda: (t := result_of(agent, nowhere)).result
               and t.result.message == "no route to robot42")
    wait_until(lambda: (t := result_of(agent, stranger)).result
               and t.result.message == "robot5 is not a neighbour")


def test_tasks_for_other_agents_are_ignored(served, make_agent):
    agent, plugin = make_agent("robot2", served["robot2"])
    task = Task(verb="NetWatch", preposition="neighbor_list", destination="robot4", source="t")
    mine = watch(agent, "neighbor_list")
    with agent.transaction() as tx:
        tx.add(task)
    fresh(agent, mine, lambda i: i.neighbors)
    assert info_of(agent, task) is None
    assert plugin.resource.watching() == [mine.uid]


@pytest.mark.parametrize("mode, expected", [
    ("silent", "no SNMP response received before timeout"),
    ("garbage", "malformed answer(s), the last: "),
    ("wrongtype", "erniNodeName (1.3.6.1.4.1.32473.1.1.1.0): expected OCTET STRING"),
])
def test_bad_agents_give_degraded_results_without_stalling(mode, expected, bad_agent, make_agent,
                                                           caplog):
    bad = bad_agent(mode)
    caplog.set_level(logging.WARNING)
    agent, plugin = make_agent("robot2", bad.address, timeout=0.1, log_interval=60.0)
    task = watch(agent, "neighbor_list", rate_hz=20)
    first = wait_until(lambda: info_of(agent, task))
    assert first.degraded       # "waiting for the first reading", or already the failure
    info = wait_until(lambda: (i := info_of(agent, task)) and i.degraded
                      and i.message != "waiting for the first reading" and i)
    assert expected in info.message
    res = wait_until(lambda: (t := result_of(agent, task)).result
                     and t.result.message.startswith("degraded:") and t)
    assert res.result.state == TaskState.RUNNING and res.result.confidence == 0.0
    assert expected in res.result.message
    wait_until(lambda: plugin.resource.stats["read_errors"] >= 3)
    # the plugin still runs: a pose published now is handed to the resource
    with agent.transaction() as tx:
        tx.add(Pose(robot="robot2", x=1.0, y=2.0))
    wait_until(lambda: plugin.resource.stats["writes"] >= 1)
    lines = [r for r in caplog.records if "network read failed" in r.getMessage()]
    assert len(lines) == 1, [r.getMessage() for r in lines]


def test_degraded_then_recovered_when_the_agent_comes_back(net, make_agent):
    snmp = ManetSnmpAgent(net).start()
    try:
        host, port = snmp.serve("robot2")
        snmp.close()                                   # nobody answers on that port now
        agent, _ = make_agent("robot2", (host, port), timeout=0.1)
        task = watch(agent, "neighbor_list", rate_hz=20)
        wait_until(lambda: (i := info_of(agent, task)) and i.degraded and "timeout" in i.message)
        snmp = ManetSnmpAgent(net).start()
        snmp.serve("robot2", host, port)
        info = fresh(agent, task, lambda i: i.neighbors)
        assert not info.degraded and [n.name for n in info.neighbors] == ["robot1", "robot3"]
        wait_until(lambda: (t := result_of(agent, task)).result.message == ""
                   and t.result.confidence == 1.0)
    finally:
        snmp.close()


def test_agent_from_the_example_config_loads():
    agent = Agent.from_config("examples/robot-mobinet.toml")
    assert agent.name == "robot2"
    plugin = agent.plugin("mobinet")
    assert (plugin.settings.host, plugin.settings.port) == ("127.0.0.1", 1162)


def test_a_new_watch_is_degraded_until_its_first_reading(bad_agent, make_agent):
    silent = bad_agent("silent")
    agent, _ = make_agent("robot2", silent.address, timeout=2.0)
    task = watch(agent, "link_quality", rate_hz=1)
    info = wait_until(lambda: info_of(agent, task))
    assert info.degraded and info.message == "waiting for the first reading"
    assert info.neighbors == []
    res = wait_until(lambda: (t := result_of(agent, task)).result and t)
    assert res.result.state == TaskState.RUNNING and res.result.message == "monitoring at 1 Hz"


def test_every_field_names_its_source_and_table(served, net, make_agent):
    agent, _ = make_agent("robot2", served["robot2"])
    tasks = {p: watch(agent, p) for p in PREPOSITIONS}
    where = f"snmp 127.0.0.1:{served['robot2'][1]}"
    expected = {
        "neighbor_list": {"neighbors": f"{where} NHDP-MIB nhdpDiscIfSetTable"},
        "link_quality": {"neighbors": f"{where} NHDP-MIB nhdpDiscIfSetTable"},
        "path_cost": {"routes": f"{where} OLSRv2-MIB olsrv2TibRoutingSetTable"},
        "network_topology": {"links": f"{where} OLSRv2-MIB olsrv2TibRouterTopologySetTable",
                             "articulation_points": "computed from links"},
        "node_position": {"positions": f"{where} ERNI-MOBINET-MIB erniPositionTable"},
    }
    for prep, task in tasks.items():
        info = fresh(agent, task, lambda i: i.provenance)
        assert info.provenance["node"] == f"{where} ERNI-MOBINET-MIB erniNodeName"
        assert set(info.provenance) == {"node", *expected[prep]}, prep
        for name, source in expected[prep].items():
            assert info.provenance[name].startswith(source), (prep, info.provenance[name])


def test_without_a_write_community_no_pose_is_written(served, net, make_agent, caplog):
    caplog.set_level(logging.WARNING)
    agent, plugin = make_agent("robot2", served["robot2"], write_community=None)
    task = watch(agent, "neighbor_list")
    with agent.transaction() as tx:
        tx.add(Pose(robot="robot2", x=99.0, y=9.0))
    fresh(agent, task, lambda i: i.neighbors)
    assert plugin.resource.stats["writes"] == 0
    assert net.view("robot2").position_updates == 0
    assert any("no write_community" in r.getMessage() for r in caplog.records)


def test_a_standing_robot_is_written_once_and_a_moving_one_at_most_once_per_interval(served, net, make_agent):
    agent, plugin = make_agent("robot2", served["robot2"], write_interval=0.3)
    with agent.transaction() as tx:
        tx.add(Pose(robot="robot2", x=10.0, y=1.0))
    wait_until(lambda: net.view("robot5").positions["robot2"].x == 10.0)
    pose = agent.query(Pose, where=lambda p: p.robot == "robot2")[0]
    for i in range(5):   # standing: new SIPs, the same place within the dead-band (2 cm, 1 degree)
        pose = pose.evolve(x=10.0 + 0.003 * i, theta=math.radians(0.1 * i), stamp=pose.stamp + 0.1)
        with agent.transaction() as tx:
            tx.change(pose)
    # Poses wake the plugin again (the interval is over: a run looked at those collected) and none waits
    wait_until(lambda: plugin.poses.wakes and scheduler_idle(plugin), timeout=10)
    assert plugin._written is not None and plugin._written.x == 10.0, "a standing robot is not written again"
    assert net.view("robot2").position_updates == 1
    t0 = time.monotonic()
    runs = plugin.runs
    for i in range(1, 31):   # moving 10 cm a Pose: written at the start and then once per interval
        pose = pose.evolve(x=10.0 + 0.1 * i, stamp=pose.stamp + 0.1)
        with agent.transaction() as tx:
            tx.change(pose)
        wait_until(lambda: scheduler_idle(plugin))  # a run for each Pose, were they not collected
    wait_until(lambda: net.view("robot1").positions["robot2"].x == pytest.approx(13.0))  # the newest, in the end
    elapsed = time.monotonic() - t0
    assert 2 <= net.view("robot2").position_updates <= 2 + math.ceil(elapsed / 0.3)
    # meanwhile the Poses collected without running the plugin for each (30 of them)
    assert plugin.runs - runs <= 3 + 2 * math.ceil(elapsed / 0.3), (plugin.runs - runs, elapsed)
    assert plugin.resource.stats["write_errors"] == 0


def test_a_standing_robots_keepalive_poses_do_not_run_the_plugin(served, net, make_agent):
    """A standing robot's Pose is published again every second with nothing but a newer stamp: no
    run of MobiNet for it (it has nothing to write); a Pose that moved runs it and is written."""
    agent, plugin = make_agent("robot2", served["robot2"], write_interval=0.0)
    with agent.transaction() as tx:
        tx.add(Pose(robot="robot2", x=10.0, y=1.0))
    wait_until(lambda: net.view("robot5").positions["robot2"].x == 10.0)
    wait_until(lambda: scheduler_idle(plugin), timeout=10)
    pose = agent.query(Pose, where=lambda p: p.robot == "robot2")[0]
    runs = plugin.runs
    for _ in range(10):
        pose = pose.evolve(stamp=pose.stamp + 1.0)
        with agent.transaction() as tx:
            tx.change(pose)
        wait_until(lambda: scheduler_idle(plugin), timeout=10)
    assert plugin.runs == runs
    with agent.transaction() as tx:
        tx.change(pose.evolve(x=11.0, stamp=pose.stamp + 1.0))
    wait_until(lambda: net.view("robot5").positions["robot2"].x == 11.0)
    assert net.view("robot2").position_updates == 2


def test_a_steady_network_is_republished_only_at_the_keepalive(served, net, make_agent):
    """Readings that change nothing but the stamp cost no transaction; a change is published at once.
    The keep-alive is a minute here (its most), so "at once" and "at the keep-alive" stay far apart
    however loaded the machine: within it, readings of a steady network are one NetInfo, and a
    change is published within a 20 s progress bound."""
    agent, plugin = make_agent("robot3", served["robot3"], netinfo_keepalive=60.0)
    topo = watch(agent, "network_topology", rate_hz=20.0)
    fresh(agent, topo, timeout=30)
    first, polls = info_of(agent, topo), plugin._polls[topo.uid]
    wait_until(lambda: plugin._polls[topo.uid] - polls >= 15, timeout=30, message="not 15 readings in 30 s at 20 Hz")
    wait_until(lambda: scheduler_idle(plugin))  # the last reading is published (or not)
    readings = plugin._polls[topo.uid] - polls
    assert info_of(agent, topo).stamp == first.stamp, f"a steady network republished within {readings} readings"
    before = set(info_of(agent, topo).articulation_points)
    net.move("robot5", 150.0, 40.0)  # robot5 comes next to robot3 and robot4: robot4 is no cut vertex now
    t1 = time.monotonic()
    fresh(agent, topo, lambda i: set(i.articulation_points) != before, timeout=30)
    assert time.monotonic() - t1 < 20.0  # published when it changed, not at the keep-alive a minute on


def test_a_netinfo_removed_by_another_plugin_is_made_afresh_without_error(served, net, make_agent, caplog):
    """Seen once after a robot's kill -9 and restart: a reading arrived for a watch whose NetInfo
    another plugin had removed, and the change raised inside the hand-off. It is published anew."""
    agent, plugin = make_agent("robot2", served["robot2"])
    task = watch(agent, "neighbor_list", rate_hz=50)
    first = fresh(agent, task, lambda i: i.neighbors)
    with agent.transaction() as tx:
        tx.remove(first)
    again = wait_until(lambda: info_of(agent, task), timeout=5)
    assert again.uid == first.uid
    fresh(agent, task, lambda i: i.neighbors)
    assert not [r for r in caplog.records if r.levelname == "ERROR"]
