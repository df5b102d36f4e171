"""The ns-3 channel of the real-mesh tier: namespaces' own sockets through ns-3's 802.11a ad-hoc network.

Runs where namespaces can be made (the `netns` mark) and Debian's libns3-dev, g++ and
pkg-config are installed (CI installs them); the channel program is built on first use.
"""

from __future__ import annotations

import shutil
import statistics

import pytest

from erni.cli import main
from erni.sim import experiments, ns3_channel
from erni.sim.manet import RadioModel
from erni.sim.netns import Mesh, NetnsError
from erni.sim.scenario import find_scenario, load_scenario

pytestmark = pytest.mark.netns

needs_ns3 = pytest.mark.skipif(ns3_channel.unavailable_reason() is not None,
                               reason=str(ns3_channel.unavailable_reason()))


@needs_ns3
def test_frames_cross_at_short_range_not_beyond_reach_and_follow_a_node_that_moves(tmp_path):
    # range 10 m: b 5 m from a (well inside), c 60 m away (ns-3's loss puts it 27 dB below the
    # wifi preamble detection threshold at that distance), then c is moved beside a
    mesh = Mesh(["a", "b", "c"], tmp_path, channel="ns3", range_m=10.0).create()
    try:
        assert mesh.ns3 is not None and mesh.ns3.alive
        mesh.apply({}, {"a": (0.0, 0.0), "b": (5.0, 0.0), "c": (60.0, 0.0)})
        near, far = mesh.udp_flows([("a", "b"), ("a", "c")], count=50, interval=0.01, size=200)
        assert near >= 45, near   # unicast with 802.11 retries: all but the rare loss
        assert far == 0, far
        mesh.apply({}, {"c": (0.0, 4.0)})  # what the team's feed does as a robot drives
        (moved,) = mesh.udp_flows([("a", "c")], count=50, interval=0.01, size=200)
        assert moved >= 45, moved
        assert mesh.ns3.lag.probes > 0  # the real-time simulator reports its lag
        assert mesh.ns3.mac.sent >= 100  # ...and the frames the kernels handed to it
        with pytest.raises(NetnsError, match="nftables radio"):
            mesh.cut("a", "b")  # faults by rule are the nftables channel's
    finally:
        mesh.destroy()
    assert mesh.leftovers() == []
    assert mesh.ns3 is None


@needs_ns3
def test_the_pure_ns3_run_of_the_same_channel_delivers_near_and_not_far():
    program = ns3_channel.binary()
    assert ns3_channel.pure_run(program, 5.0, 50, 0.01, 200, range_m=10.0) == (50, 50)
    assert ns3_channel.pure_run(program, 60.0, 50, 0.01, 200, range_m=10.0) == (50, 0)



@needs_ns3
def test_the_reach_a_team_gets_makes_ns3_deliver_what_the_radio_model_says_at_its_edge_and_middle():
    # the default radio: none beyond 10 m, the weakest counted link (0.1) at 10 m, 0.3 at 8.8 m, all
    # up to 6 m; ns-3 at the reach a team asks for, by its own pure runs (2 seeds of 400 datagrams)
    program, comm = ns3_channel.binary(), 10.0
    model = RadioModel(comm, 6.0, 0.1)

    def delivered(d: float) -> float:
        runs = [ns3_channel.pure_run(program, d, 400, 0.01, 500, range_m=ns3_channel.reach(comm), seed=s)
                for s in (1, 2)]
        return sum(r for _, r in runs) / sum(n for n, _ in runs)

    assert 0.05 <= delivered(comm) <= 0.16          # the model counts 0.1 as the weakest link
    assert abs(delivered(model.range_for(0.3)) - 0.3) <= 0.08
    assert delivered(6.0) >= 0.9
    assert delivered(1.2 * comm) <= 0.03            # and beyond the model's range, next to nothing

def test_a_missing_ns3_is_one_line_naming_the_packages(monkeypatch, capsys):
    real = shutil.which
    monkeypatch.setattr(shutil, "which", lambda tool: None if tool == "g++" else real(tool))
    reason = ns3_channel.unavailable_reason()
    assert reason is not None and "apt install libns3-dev g++ pkg-config" in reason and "\n" not in reason
    with pytest.raises(ns3_channel.Ns3Unavailable, match="libns3-dev"):
        ns3_channel.binary()
    assert main(["sim", "--netns", "--channel", "ns3", "--headless"]) == 2
    err = capsys.readouterr().err
    assert "--channel ns3 needs ns-3: apt install libns3-dev g++ pkg-config" in err and "\n" not in err.strip()


@needs_ns3
def test_more_nodes_than_keep_real_time_are_refused_with_the_figure(capsys):
    robots = ns3_channel.MAX_NODES  # with the control node, one more than the channel carries
    assert main(["sim", "--netns", "--channel", "ns3", "--headless", "--robots", str(robots)]) == 2
    err = capsys.readouterr().err
    assert f"{robots + 1} nodes" in err and f"at most {ns3_channel.MAX_NODES}" in err


def test_channel_without_netns_is_refused(capsys):
    assert main(["sim", "--channel", "ns3", "--headless"]) == 2
    assert "add --netns" in capsys.readouterr().err


@needs_ns3
@pytest.mark.slow
def test_a_team_on_the_ns3_channel_takes_a_task_two_hops_out_and_ctrl_c_removes_everything(tmp_path):
    import os
    import re
    import signal
    import subprocess
    import sys

    from erni.sim import netns
    from tests.netns.test_sim_netns_cli import launch, namespaces, tag_of

    proc, lines = launch(tmp_path, "--robots", "2", "--headless", "--channel", "ns3")
    tag = tag_of(lines)
    try:
        text = "\n".join(lines)
        assert "ns3 channel" in text
        # robot2 is 11 m from the control node on mesh-line: its tasks go through robot1 on babeld's routes
        via = re.search(r"erni task --via (\S+)", text).group(1)
        env = {**os.environ, "ERNI_IDENTITY": re.search(r"export ERNI_IDENTITY=(\S+)", text).group(1)}
        done = subprocess.run([sys.executable, "-m", "erni", "task", "--via", via, "robot2", "BotMotion", "turn",
                               "angle=30", "--wait"], capture_output=True, text=True, env=env, timeout=90)
        assert done.returncode == 0 and "succeeded" in done.stdout.lower(), done.stdout + done.stderr
        channel = [int(p) for p in netns._ip("netns", "pids", f"erni-{tag}").split()]
        assert channel  # the ns-3 process runs in the segment's namespace
    finally:
        proc.send_signal(signal.SIGINT)
        out, _ = proc.communicate(timeout=60)
    assert proc.returncode == 0, out
    assert namespaces(tag) == []
    for pid in channel:
        assert not os.path.exists(f"/proc/{pid}") or "zombie" in open(f"/proc/{pid}/status").read().lower()


@needs_ns3
def test_a_killed_launcher_takes_the_ns3_process_and_its_taps_along_and_clean_stale_removes_the_rest(tmp_path):
    import os
    import signal
    import subprocess
    import sys
    import textwrap

    from erni.blackboard.testing import wait_until
    from erni.sim import netns

    launcher = subprocess.Popen([sys.executable, "-c", textwrap.dedent(f"""
        import signal
        from erni.sim.netns import Mesh
        mesh = Mesh(["a", "b"], {str(tmp_path)!r}, channel="ns3").create()
        print(mesh.tag, mesh.ns3.proc.pid, flush=True)
        signal.pause()  # until the test kills it
    """)], stdout=subprocess.PIPE, text=True)
    assert launcher.stdout is not None
    tag, pid = launcher.stdout.readline().split()
    assert os.path.exists(f"/proc/{pid}")
    os.kill(launcher.pid, signal.SIGKILL)
    launcher.wait(10)
    # the kernel kills the channel with its launcher; the TAPs close with it
    wait_until(lambda: not os.path.exists(f"/proc/{pid}") or "zombie" in open(f"/proc/{pid}/status").read().lower(),
               timeout=15)
    wait_until(lambda: "mesh0" not in netns._ip("-o", "link", "show", netns=f"erni-{tag}-a", check=False),
               timeout=15)
    assert tag in netns.clean_stale()
    assert not [n for n in netns._namespaces() if n.startswith(f"erni-{tag}")]


def test_a_scenario_chooses_the_channel_and_a_wrong_one_is_refused_with_the_choices(tmp_path):
    from erni.sim.scenario import ScenarioError, load_scenario

    path = tmp_path / "s.toml"
    path.write_text('name = "s"\n[radio]\ncomm_range = 8.0\nlossless_range = 5.0\nchannel = "ns3"\n')
    assert load_scenario(path).radio.channel == "ns3"
    path.write_text('name = "s"\n[radio]\nchannel = "netem"\n')
    with pytest.raises(ScenarioError, match="nftables.*ns3"):
        load_scenario(path)
    assert Mesh(["a"], tmp_path, channel="ns3", range_m=8.0).channel == "ns3"
    with pytest.raises(NetnsError, match="nftables, ns3"):
        Mesh(["a"], tmp_path, channel="netem")


@needs_ns3
def test_a_channel_that_dies_is_reported_once_as_an_error(tmp_path, caplog):
    mesh = Mesh(["a", "b"], tmp_path, channel="ns3").create()
    try:
        assert mesh.ns3 is not None and mesh.ns3.proc is not None
        mesh.ns3.proc.kill()
        mesh.ns3.proc.wait(5)
        with caplog.at_level("ERROR", logger="erni.sim.ns3_channel"):
            mesh.apply({}, {"a": (1.0, 0.0)})
            mesh.apply({}, {"a": (2.0, 0.0)})
        errors = [r.getMessage() for r in caplog.records if r.levelname == "ERROR"]
        assert len(errors) == 1 and "the ns-3 channel exited" in errors[0], errors
        assert not mesh.ns3.alive
    finally:
        mesh.destroy()
    assert mesh.leftovers() == []


@needs_ns3
def test_status_round_trips_cross_the_ns3_channel_between_agents_in_namespaces_of_their_own():
    # paper 002's round trips on the real-mesh tier: the robot agent and its consumer one hop apart on
    # ns-3's 802.11a; a compressed camera frame takes several frames of airtime, a sensor reading one
    sc = load_scenario(find_scenario("roundtrip"))
    sc = sc.model_copy(update={"radio": sc.radio.model_copy(update={"channel": "ns3"}),
                               "strategy": {**sc.strategy, "consumers": [1], "count": 12, "warmup": 3}})
    result = experiments.run("roundtrip", sc, netns=True)
    assert "ns-3" in result.mode_note and "namespace" in result.mode_note
    sensor, image = (result.series[f"1/{k}_rtt_ms"][1] for k in ("sensor", "image"))
    assert len(sensor) == 12 and len(image) == 12 and all(0.1 < x < 1000 for x in sensor + image)
    assert statistics.median(image) > statistics.median(sensor)
    rows = {r.quantity: r for r in result.rows}
    assert "802.11a" in str(rows["data path"].ours) and rows["data path"].kind == "input"


def test_the_channel_option_of_an_experiment_needs_the_real_mesh_tier(capsys):
    assert main(["experiment", "relay-video", "--channel", "ns3", "--no-plot"]) == 2
    assert "--channel chooses the real-mesh tier's channel: add --netns" in capsys.readouterr().err
