"""Discovery by beacons, the peer directory on the blackboard, liveness, static and learned peers."""

from __future__ import annotations

import re

from erni.blackboard import Agent, NetInfo, Task
from erni.blackboard.testing import wait_until
from erni.transport import Peer
from tests.transport.helpers import SkipClock, free_port, make_agent, settled


def peers(agent: Agent) -> dict[str, Peer]:
    return {p.name: p for p in agent.query(Peer)}


def test_agents_find_each_other_without_a_peer_list():
    port = free_port()
    agents = [make_agent(f"a{i}", port, role="robot" if i else "control", capabilities=[f"c{i}"])
              for i in range(3)]
    try:
        for agent in agents:
            wait_until(lambda agent=agent: sum(p.up for p in peers(agent).values()) == 2)
        seen = peers(agents[1])["a0"]
        assert seen.role == "control" and seen.capabilities == ["c0"]
        assert seen.address == "{}:{}".format(*agents[0].plugin("transport").address)
    finally:
        for a in agents:
            a.stop()


def test_silent_peer_is_marked_down_and_up_again_and_beacons_of_a_peer_up_are_not_checked():
    """Every agent broadcasts a signed beacon each period: with N peers up that would be N
    signature checks a period that change nothing. They are skipped while the peer is up, and a
    restarted peer is still found."""
    port = free_port()
    a, b = make_agent("a", port), make_agent("b", port)
    try:
        wait_until(lambda: peers(a).get("b") and peers(a)["b"].up)
        endpoint = a.plugin("transport").endpoint
        checked = endpoint.counters.get("received.beacons", 0)
        wait_until(lambda: endpoint.counters.get("received.beacons.known", 0) >= 5, timeout=5)
        # b's broadcasts (10 a second here) are heard, none checked: a's view of b rests on its session
        assert endpoint.counters.get("received.beacons", 0) - checked <= 1
        assert peers(a)["b"].up
        b.stop()
        wait_until(lambda: not peers(a)["b"].up, timeout=3)
        b = make_agent("b", port)
        wait_until(lambda: peers(a)["b"].up, timeout=3)
    finally:
        a.stop()
        b.stop()


def test_static_peer_list_works_with_discovery_off():
    a = make_agent("a", 0)
    addr = "{}:{}".format(*a.plugin("transport").address)
    b = make_agent("b", 0, peers=[f"a@{addr}"])
    try:
        wait_until(lambda: peers(a).get("b") and peers(a)["b"].up)  # a learns b from b's beacons
        task = Task(verb="BotMotion", preposition="stop", source="b", destination="a")
        with b.transaction() as tx:
            tx.add(task)
        wait_until(lambda: b.blackboard.get(task.uid).done)
    finally:
        a.stop()
        b.stop()


def test_addresses_learned_from_the_network_topology():
    port = free_port()
    # beacons go nowhere by default here: only addresses learned from NetInfo are tried
    a = make_agent("a", port, beacon_to=[])
    b = make_agent("b", port, beacon_to=[])
    try:
        assert not peers(a).get("b")
        a_addr = "{}:{}".format(*a.plugin("transport").address)
        with b.transaction() as tx:
            tx.add(NetInfo(node="b", kind="neighbor_list", neighbors=[{"name": "a", "address": a_addr}]))
        wait_until(lambda: peers(a).get("b") and peers(a)["b"].up)
    finally:
        a.stop()
        b.stop()


def test_a_learned_address_is_announced_to_only_until_its_agent_is_up():
    """Announcements are for agents not known yet. Once the agent at a learned address is up, its
    session carries the beacons; a learned address with nobody up there is still tried."""

    port = free_port()
    a = make_agent("a", port, beacon_to=[], announce_backoff=1)  # announce every period
    b = make_agent("b", port, beacon_to=[], announce_backoff=1)
    try:
        a_addr = "{}:{}".format(*a.plugin("transport").address)
        nobody = f"127.0.0.1:{free_port()}"
        endpoint = b.plugin("transport").endpoint
        announced: list[tuple[str, int]] = []
        announce = endpoint.announce

        def spy(addr, kind, body=None):  # type: ignore[no-untyped-def]
            announced.append(addr)
            return announce(addr, kind, body)

        endpoint.announce = spy  # type: ignore[method-assign]
        with b.transaction() as tx:
            tx.add(NetInfo(node="b", kind="neighbor_list", neighbors=[{"name": "a", "address": a_addr},
                                                                       {"name": "c", "address": nobody}]))
        wait_until(lambda: peers(b).get("a") and peers(b)["a"].up)
        settled(b)  # a run that began before a came up (and may have announced to it) is over
        announced.clear()
        # ten beacon periods: one announcement each (announce_backoff 1) to the address with nobody there
        wait_until(lambda: len(announced) >= 10, timeout=30)
        targets = {"{}:{}".format(*addr) for addr in announced}
        assert targets == {nobody}, targets
        assert peers(b)["a"].up
    finally:
        a.stop()
        b.stop()


def test_an_inbound_filter_fed_through_a_pipe_drops_traffic_between_unconnected_agents():
    import json
    import os

    from erni.blackboard import Task, TaskState
    from erni.sim.radio import RadioFilter, install

    def radio() -> tuple[RadioFilter, int]:
        read, write = os.pipe()
        return RadioFilter(read), write

    def tell(write: int, names: list[str]) -> None:
        os.write(write, (json.dumps(names) + "\n").encode())

    (radio_a, pipe_a), (radio_b, pipe_b) = radio(), radio()
    tell(pipe_a, ["b"])
    tell(pipe_b, ["a"])
    wait_until(lambda: radio_a.updates and radio_b.updates)
    port = free_port()
    a = make_agent("a", port, peer_timeout=0.5, start=False, role="control")  # it tasks b
    b = make_agent("b", port, peer_timeout=0.5, start=False)
    install(a, radio_a)
    install(b, radio_b)
    a.start()
    b.start()
    try:
        wait_until(lambda: peers(a).get("b") and peers(a)["b"].up)
        tell(pipe_a, [])  # b drives out of range
        tell(pipe_b, [])
        wait_until(lambda: not peers(a)["b"].up, timeout=3)
        task = Task(verb="BotMotion", preposition="stop", source="a", destination="b")
        a_counters, b_counters = a.plugin("transport").endpoint.counters, b.plugin("transport").endpoint.counters
        retries, unreachable = a_counters.get("retries", 0), b_counters.get("dropped.unreachable", 0)
        with a.transaction() as tx:
            tx.add(task)
        # the task went to b twice, unacknowledged, and b dropped what a sent it since: b's radio
        wait_until(lambda: a_counters.get("retries", 0) >= retries + 2
                   and b_counters.get("dropped.unreachable", 0) > unreachable, timeout=30)
        settled(b)
        assert not b.blackboard.contains(task.uid)
        tell(pipe_a, ["b"])  # back in range: the queued task gets through
        tell(pipe_b, ["a"])
        wait_until(lambda: a.blackboard.get(task.uid).state is TaskState.SUCCEEDED, timeout=5)
    finally:
        a.stop()
        b.stop()
        os.close(pipe_a)
        os.close(pipe_b)



def _spy_beacons(agent: Agent) -> list[tuple[float, str]]:
    """Record (time, receiver) of every in-session beacon `agent` sends from now on (sent for real)."""
    import time

    endpoint = agent.plugin("transport").endpoint
    sent: list[tuple[float, str]] = []
    send = endpoint.send

    def spy(addr, kind, body=None, **kw):  # type: ignore[no-untyped-def]
        if kind == "beacon":
            sent.append((time.monotonic(), kw.get("to") or ""))
        return send(addr, kind, body, **kw)

    endpoint.send = spy
    return sent


def test_quiet_peers_share_a_beacon_budget_and_their_receivers_wait_as_much_longer(caplog):
    """With more quiet peers than `beacon_fanout`, each is beaconed less often (the traffic no
    longer grows with the team) and says so in the beacon; its receivers scale their silence
    limit by the same factor, so nobody is marked down for it, and a dead agent still is."""
    import time

    port = free_port()
    a = make_agent("a", port, beacon_fanout=1)  # 4 quiet peers: one beacon to each every 0.4 s
    others = [make_agent(n, port) for n in "bcde"]
    try:
        wait_until(lambda: sum(p.up for p in peers(a).values()) == 4)
        for o in others:
            wait_until(lambda o=o: peers(o).get("a") and peers(o)["a"].up)
        sent = _spy_beacons(a)
        t0 = time.monotonic()

        def four_each() -> bool:  # nobody calls a down meanwhile (limit 0.6 s x 4 = 2.4 s)
            assert all(peers(o)["a"].up for o in others)
            return all(sum(to == o.name for _, to in sent) >= 4 for o in others)

        # four beacons to each peer (1.6 s at one to each every 0.4 s), far past the unscaled 0.6 s limit
        wait_until(four_each, timeout=30, interval=0.05)
        counted, window = len(sent), time.monotonic() - t0
        # at most about fanout / period = 10 a second, where a beacon to each peer each period was 44
        # (the window as long as it took: a loaded machine stretches it, and the beacons with it)
        assert counted <= window * 10 / 0.8 + 4, (counted, window)
        assert {to for _, to in sent} == set("bcde")  # every peer still gets its beacons
        assert all(o.plugin("transport").peers["a"].limit == 0.6 * 4 for o in others)
        assert all(getattr(o.plugin("transport").peers.get("b"), "limit", None) in (None, 0.6)  # fanout 16: unscaled
                   for o in others[1:])
        with caplog.at_level("WARNING"):
            a.stop()
            t_stop = time.monotonic()
            wait_until(lambda: not peers(others[0])["a"].up, timeout=30)
        assert time.monotonic() - t_stop > 0.6  # its scaled limit, not the plain 0.6 s
        # ... as b's transport says: down when a's silence passed 0.6 s x 4
        downs = [r.getMessage() for r in caplog.records if r.getMessage().startswith("peer a is down: not heard")]
        assert downs and all("(limit 2.4 s; " in d for d in downs), downs
    finally:
        for agent in [a, *others]:
            agent.stop()


def test_a_peer_that_gets_statuses_gets_no_beacons():
    """Any session frame tells a peer that the sender is alive: a robot sharing its Pose with the
    control node sends it no beacons meanwhile, and beacons again once it falls quiet.

    The beacon period is 1 s here (the test team's is 0.1 s), the Poses go every 30 ms: a pause of
    the test's thread on a loaded machine, which makes the robot quiet for a while, stays far
    shorter than a period of quiet that would rightly bring a beacon."""
    import time

    from erni.blackboard import Pose

    port = free_port()
    timings = {"beacon_period": 1.0, "peer_timeout": 4.0}
    robot, control = make_agent("r", port, **timings), make_agent("c", port, role="control", **timings)
    try:
        wait_until(lambda: peers(robot).get("c") and peers(robot)["c"].up, timeout=30)
        sent = _spy_beacons(robot)
        t0 = time.monotonic()
        pose = Pose(robot="r")
        with robot.transaction() as tx:
            tx.add(pose)
        while time.monotonic() - t0 < 4.0:
            pose = pose.evolve(x=pose.x + 0.1)
            with robot.transaction() as tx:
                tx.change(pose)
            # each Pose reaches the control node before the next goes (a robot's stream, not a burst)
            wait_until(lambda x=pose.x, uid=pose.uid: getattr(control.blackboard.get(uid), "x", None) == x, timeout=30)
        talking = [t for t, to in sent if to == "c" and t > t0 + 1.0]  # (one may have been due at the start)
        assert talking == []
        assert peers(control)["r"].up
        quiet = time.monotonic()
        wait_until(lambda: any(t > quiet for t, to in sent if to == "c"), timeout=30)
    finally:
        robot.stop()
        control.stop()


def test_broadcast_beacons_back_off_while_the_directory_stands_and_not_when_a_peer_is_down():
    import time

    port = free_port()
    a = make_agent("a", port)
    # alone: it keeps announcing every period (nobody has heard it yet)
    wait_until(lambda: a.plugin("transport").endpoint.counters.get("sent.announce", 0) >= 8)
    b = make_agent("b", port)
    try:
        wait_until(lambda: peers(a).get("b") and peers(a)["b"].up)
        bridge = a.plugin("transport")
        counters, presence = bridge.endpoint.counters, bridge.presence

        def numbered() -> int:  # the newest of b's beacons a heard: b (quiet toward a) sends one a period
            count = presence.peers["b"].beacon_count
            return count.last if count is not None else 0

        def periods(n: int) -> None:
            """Wait until b has beaconed a n times more: n beacon periods (as long as a loaded machine makes them)."""
            start = numbered()
            wait_until(lambda: numbered() >= start + n, timeout=60)

        wait_until(lambda: presence._announce_every >= 0.8 - 1e-9, timeout=30)  # the back-off reaches 8 periods
        before, t0 = counters.get("sent.announce", 0), time.monotonic()
        periods(24)
        standing, window = counters.get("sent.announce", 0) - before, time.monotonic() - t0
        # 24 at one a period; one every 8 periods (0.8 s, the next due a little early) in the window it took
        assert 1 <= standing <= 2 + window / 0.72, (standing, window)
        c = make_agent("c", port)  # a newcomer announces every period and is answered at once
        try:
            wait_until(lambda: peers(a).get("c") and peers(a)["c"].up, timeout=1.0)
        finally:
            c.stop()
        wait_until(lambda: not peers(a)["c"].up, timeout=3)
        before = counters.get("sent.announce", 0)
        periods(10)
        assert counters.get("sent.announce", 0) - before >= 7  # a peer down: every period again
    finally:
        a.stop()
        b.stop()


def test_statuses_received_and_peers_heard_do_not_run_the_transport_twice():
    """The transport commits each status it receives and each peer it hears; those commits are
    its own and must not run it once more (a control node gets ten Poses a second per robot)."""

    from erni.blackboard import Pose

    port = free_port()
    slow = {"beacon_period": 1.0, "peer_timeout": 4.0}  # few timer runs in the window
    robot, control = make_agent("r", port, **slow), make_agent("c", port, role="control", **slow)
    try:
        wait_until(lambda: peers(robot).get("c") and peers(robot)["c"].up, timeout=5)
        bridge = control.plugin("transport")
        pose = Pose(robot="r")
        with robot.transaction() as tx:
            tx.add(pose)
        wait_until(lambda: control.blackboard.get(pose.uid) is not None)
        runs, received = bridge.runs, bridge.endpoint.counters.get("received", 0)
        for _ in range(40):
            pose = pose.evolve(x=pose.x + 0.1)
            with robot.transaction() as tx:
                tx.change(pose)
            # each Pose is on the control node before the next goes: a frame a run, not a burst in one
            wait_until(lambda x=pose.x, uid=pose.uid: control.blackboard.get(uid).x == x, timeout=30)
        got = bridge.endpoint.counters.get("received", 0) - received
        assert got >= 30
        assert bridge.runs - runs <= got + 4, (bridge.runs - runs, got)  # one run per frame, not two
    finally:
        robot.stop()
        control.stop()


def test_a_configured_peer_that_only_talks_is_known_by_its_role_and_gets_shared_status():
    """b is configured with a's address; a learns b (and its role) from b's first beacon, then
    talks to b without beacons. b must take a's role from a's session frames: its status shared
    with robots would otherwise wait for a beacon that never comes while a talks."""

    from erni.blackboard import Pose

    shared = {"share": ["Pose"], "share_with_roles": ["robot"], "beacon_period": 5.0, "peer_timeout": 20.0}
    a = make_agent("a", 0, **shared)
    addr = "{}:{}".format(*a.plugin("transport").address)
    b = make_agent("b", 0, peers=[f"a@{addr}"], **shared)
    try:
        wait_until(lambda: peers(a).get("b") and peers(a)["b"].up)
        poses = {name: Pose(robot=name) for name in ("a", "b")}
        for agent in (a, b):
            with agent.transaction() as tx:
                tx.add(poses[agent.name])

        def b_pose_at_a():
            for agent in (a, b):  # both keep moving (a step each look): every change is shared again
                poses[agent.name] = poses[agent.name].evolve(x=poses[agent.name].x + 0.1)
                with agent.transaction() as tx:
                    tx.change(poses[agent.name])
            return a.blackboard.get(poses["b"].uid)

        wait_until(b_pose_at_a, timeout=3.0, interval=0.05,
                   message="b never shared its Pose with a (a's role unknown to b)")
        assert peers(b)["a"].role == "robot"
    finally:
        a.stop()
        b.stop()


def test_a_beacon_that_says_nothing_new_costs_no_run_and_still_keeps_its_peer_up():
    """Each agent of a team of N hears up to `beacon_fanout` in-session beacons a period. One from
    a peer that is up, saying what it said last, only marks the peer heard on the receive thread
    (no plugin run); the liveness pass keeps the Peer's `last_heard` on the board fresh, and a
    beacon that says something new (b degraded) still reaches the board."""
    import time

    port = free_port()
    a, b = make_agent("a", port), make_agent("b", port)
    try:
        wait_until(lambda: peers(a).get("b") and peers(a)["b"].up and peers(a)["b"].last_heard)
        bridge = a.plugin("transport")
        handled: list[str] = []
        received: list[str] = []
        handle, receive = bridge._handle, bridge._received

        def spy_handle(msg):
            if msg.kind == "beacon" and not msg.hint:
                handled.append(msg.sender)
            return handle(msg)

        def spy_received(msg):
            if msg.kind == "beacon" and not msg.hint:
                received.append(msg.sender)
            return receive(msg)

        bridge._handle = spy_handle
        bridge.endpoint.on_message = spy_received
        w0 = time.time()

        def fifteen_beacons() -> bool:  # 2.5 peer timeouts of b saying nothing new
            assert peers(a)["b"].up
            return received.count("b") >= 15  # b (quiet toward a) beacons it every 0.1 s

        wait_until(fifteen_beacons, timeout=30, interval=0.05)
        # and the Peer on the board moved on with them, though no run handled one: its last_heard is
        # refreshed by the liveness pass (frozen, it would stay where it was before the window)
        wait_until(lambda: peers(a)["b"].last_heard > w0 + 1.0, timeout=30)
        assert handled == []
        b.plugin("transport")._degraded = lambda: "journal full"  # what b's beacon says changes
        wait_until(lambda: peers(a)["b"].degraded == "journal full", timeout=3)
        assert "b" in handled
    finally:
        a.stop()
        b.stop()


def test_silences_are_looked_at_every_quarter_timeout_and_a_silent_peer_still_goes_down_at_its_limit(caplog):
    """The pass over every peer's silence is O(peers): in a team of fifty on one host it ran four
    times a beacon period in every agent. It runs every quarter peer timeout now, and earlier only
    when a peer's silence may reach its limit: a peer that stops is still marked down at once."""
    import time

    port = free_port()
    a, b = make_agent("a", port, peer_timeout=2.0), make_agent("b", port, peer_timeout=2.0)
    try:
        wait_until(lambda: peers(a).get("b") and peers(a)["b"].up)
        bridge = a.plugin("transport")
        looked: list[float] = []
        down_after = bridge.presence.down_after
        bridge.presence.down_after = lambda name: looked.append(time.monotonic()) or down_after(name)
        t0 = time.monotonic()
        wait_until(lambda: len(looked) >= 4, timeout=30)  # four quarter timeouts: twenty beacon periods
        n, window = len(looked), time.monotonic() - t0
        # about once every 0.5 s of the window, however long a loaded machine made it (four times a
        # beacon period would be 40 a second)
        assert n <= 2 + 2 * window, (n, window, looked)
        with caplog.at_level("WARNING"):
            b.stop()
            wait_until(lambda: not peers(a)["b"].up, timeout=30)
        # down for a silence past its own limit, the 2 s peer_timeout (on a link that loses nothing)
        (down,) = [r.getMessage() for r in caplog.records if r.getMessage().startswith("peer b is down:")]
        said = re.fullmatch(r"peer b is down: not heard for ([\d.]+) s \(limit 2\.0 s; .*\)", down)
        assert said and float(said[1]) >= 2.0, down
    finally:
        a.stop()
        b.stop()


def test_agents_running_insecure_are_up_by_their_beacons_alone():
    """The README's two-terminal example: two agents running insecure exchange nothing but beacons.
    Without sessions no frame is more authentic than a beacon, so each sees the other up, heard
    within a beacon period, and keeps it up while it beacons."""
    import time

    port = free_port()
    a, b = make_agent("a", port, echo=False, insecure=True), make_agent("b", port, echo=False, insecure=True)
    try:
        wait_until(lambda: peers(a).get("b") and peers(a)["b"].up and peers(b).get("a") and peers(b)["a"].up,
                   timeout=3)
        w0 = time.time()

        def heard_on() -> bool:  # up all along, 2.5 peer timeouts
            assert peers(a)["b"].up
            return peers(a)["b"].last_heard > w0 + 1.5

        # heard all along: last_heard moved on with b's beacons (the age of a reading would be the load's)
        wait_until(heard_on, timeout=30, interval=0.05)
    finally:
        a.stop()
        b.stop()


def test_a_peer_heard_only_by_its_signed_beacons_shows_when_it_was_heard():
    """A signed broadcast beacon is only a hint (it can be replayed): it never marks a peer up.
    But a peer not up shows when its beacon was last heard, not `never`."""
    import socket

    port = free_port()
    clock = SkipClock()  # a's: the test moves it on past b's down
    a, b = make_agent("a", port, echo=False, clock=clock), make_agent("b", port, echo=False)
    try:
        wait_until(lambda: peers(a).get("b") and peers(a)["b"].up)
        beacon = b""
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as sniff:
            sniff.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
            sniff.bind(("", port))
            sniff.settimeout(0.5)
            while not beacon:
                data, _ = sniff.recvfrom(65536)
                if data[4:5] == b"B" and b'"b"' in data:
                    beacon = data
        b.stop()
        wait_until(lambda: not peers(a)["b"].up, timeout=30)
        down_at = peers(a)["b"].last_heard
        address = a.plugin("transport").address
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as udp:
            clock.skip(0.2)  # the beacon comes a while after the down on a's clock: its arrival can be told apart
            sent_at = a.clock.wall()
            udp.sendto(beacon, address)
            wait_until(lambda: peers(a)["b"].last_heard > down_at + 0.1, timeout=30)
        seen = peers(a)["b"]
        assert not seen.up, "a beacon is a hint, never a sign of life"
        assert seen.last_heard >= sent_at - 0.01  # when this beacon came (not, say, when it was made)
    finally:
        a.stop()
        b.stop()
