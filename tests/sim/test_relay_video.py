"""Paper 000, Figure 6: a video-like stream through one relay, its loss and delay against the relay's
position; on the loopback tier the loss is the radio model's, and says so; on the real-mesh tier
(namespaces, babeld) the kernel drops the frames and forwards through the relay."""

from __future__ import annotations

import csv

import pytest

from erni.sim import experiments, netns, ns3_channel
from erni.sim.scenario import find_scenario, load_scenario


def test_the_stream_loses_least_with_the_relay_between_and_labels_the_loss_an_input(tmp_path):
    sc = load_scenario(find_scenario("relay-video"))
    sc = sc.model_copy(update={"strategy": {**sc.strategy, "positions": [2.0, 8.0, 14.0], "seconds": 0.4}})
    result = experiments.run("relay-video", sc)
    _, lost, _ = result.series["relay/packet_loss"]
    assert lost[0] == 1.0 and lost[2] == 1.0  # one hop out of range (12 m): nothing arrives
    assert 0.5 < lost[1] < 1.0  # 8 m each: the model's 1 - (4/9)^2 = 0.80, drawn per datagram
    _, delay, _ = result.series["relay/delay_median"]
    assert delay[1] > 0
    rows = {r.quantity: r for r in result.rows}
    assert rows["lowest loss where"].kind == "input" and rows["loss of a hop"].kind == "input"
    assert rows["delay against the relay's position"].kind == "measured"
    result.plot(tmp_path / "fig.png")
    result.write_csv(tmp_path / "numbers.csv")
    quantities = {r["quantity"] for r in csv.DictReader((tmp_path / "numbers.csv").open()) if r["section"] == "series"}
    assert {"packet_loss", "frame_loss", "model_loss", "delay_median"} <= quantities


@pytest.mark.netns
@pytest.mark.skipif(bool(netns.unavailable_reason()), reason="real-mesh tier unavailable")
def test_on_the_real_mesh_the_loss_grows_as_the_relay_leaves_the_middle(tmp_path):
    sc = load_scenario(find_scenario("relay-video"))
    sc = sc.model_copy(update={"strategy": {**sc.strategy, "positions": [8.0, 11.0, 13.0], "seconds": 2.0,
                                            "netns_settle": 1.0, "netns_route_wait": 3.0}})
    result = experiments.run("relay-video", sc, netns=True)
    assert "babeld" in result.mode_note
    _, lost, _ = result.series["relay/packet_loss"]
    _, model, _ = result.series["relay/model_loss"]
    assert model == pytest.approx([0.8, 0.92, 1.0], abs=0.01)  # applied: 45 % x 45 %, 10 % x 80 %, out of range
    assert lost[0] < 1.0  # in the middle datagrams arrive through the relay, on babeld's route
    assert lost[0] < lost[1] and lost[2] == 1.0  # more lost off the middle; 13 m from S: no link at all
    _, kernel, _ = result.series["relay/kernel_loss_sr"]
    assert 0.3 < kernel[0] < 0.8  # the kernel dropped S -> R frames in the middle (55 % applied)
    _, delay, _ = result.series["relay/delay_median"]
    assert delay[0] > 0
    rows = {r.quantity: r for r in result.rows}
    assert rows["loss of a hop"].kind == "input" and rows["lowest loss where"].kind == "measured"
    result.plot(tmp_path / "fig.png")
    result.write_csv(tmp_path / "numbers.csv")
    quantities = {r["quantity"] for r in csv.DictReader((tmp_path / "numbers.csv").open()) if r["section"] == "series"}
    assert {"packet_loss", "model_loss", "refused", "kernel_loss_sr", "routed", "delay_median"} <= quantities


@pytest.mark.netns
@pytest.mark.skipif(bool(netns.unavailable_reason()) or bool(ns3_channel.unavailable_reason()),
                    reason="real-mesh tier or ns-3 unavailable")
def test_on_the_ns3_channel_the_loss_is_measured_and_the_relay_between_the_ends_carries_the_stream(tmp_path):
    # S-D 16 m, R = 12 m: the middle's hops are 8 m each; 2 m from S the far hop is 14 m, where ns-3 delivers
    # next to nothing (the radio model: nothing); a light stream, so the MAC's queue does not decide
    sc = load_scenario(find_scenario("relay-video"))
    sc = sc.model_copy(update={"radio": sc.radio.model_copy(update={"channel": "ns3"}),
                               "strategy": {**sc.strategy, "positions": [8.0, 2.0], "fps": 5.0, "seconds": 4.0,
                                            "netns_settle": 1.0, "netns_route_wait": 3.0}})
    result = experiments.run("relay-video", sc, netns=True)
    assert "ns-3" in result.mode_note
    _, lost, _ = result.series["relay/packet_loss"]
    assert lost[0] < 0.9 and lost[0] < lost[1]  # through the relay in the middle; far less beside an end
    _, delay, _ = result.series["relay/delay_median"]
    assert delay[0] > 0.5  # airtime and the MAC: slower than the kernel's forwarding alone (~0.1 ms)
    _, retried, _ = result.series["relay/mac_retry_limit"]
    assert all(0.0 <= r <= 1.0 for r in retried)  # the MAC's counts of ns-3, as shares of its frames
    rows = {r.quantity: r for r in result.rows}
    assert rows["the channel"].kind == "input" and rows["lowest loss where"].kind == "measured"
    result.plot(tmp_path / "fig.png")
