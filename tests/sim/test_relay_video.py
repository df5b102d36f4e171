"""Paper 000, Figure 6 (first cut, loopback tier): a video-like stream through one relay, its loss
and delay against the relay's position; the loss is the radio model's, and says so."""

from __future__ import annotations

import csv

from erni.sim import experiments
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
