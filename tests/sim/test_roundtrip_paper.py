"""Table II of paper 002: all five consumer counts, images sent as the paper sends them, and where
the round trip's time goes."""

from __future__ import annotations

import numpy as np

from erni.sim import experiments
from erni.sim.experiments import roundtrip
from erni.sim.scenario import find_scenario, load_scenario


def test_the_scenario_measures_every_consumer_count_from_one_to_five():
    sc = load_scenario(find_scenario("roundtrip"))
    assert sc.strategy["consumers"] == [1, 2, 3, 4, 5]
    assert "image_bytes" not in sc.strategy  # frames are compressed camera frames, not random bytes


def test_a_frame_is_compressed_to_a_jpeg_each_consumer_decodes():
    frames = roundtrip.camera_frames(320, 240, seed=7)
    jpeg = roundtrip.compress(frames[0], 75)
    assert jpeg[:2] == b"\xff\xd8"  # a JPEG
    assert 2_000 < len(jpeg) < 0.5 * frames[0].nbytes  # compressed, and not to nothing
    assert roundtrip.decode(jpeg) == (320, 240)
    assert roundtrip.compress(frames[1], 75) != jpeg  # the scene changes from frame to frame


def measured(n: int, rng: np.random.Generator) -> roundtrip.Measured:
    rtt = {k: list(rng.normal(1.0 + 1.0 * n, 0.1, 30)) for k in ("sensor", "image")}
    stages = {k: {name: list(rng.normal(0.3 * (i + 1) * n, 0.05, 30)) for i, name in enumerate(roundtrip.STAGES)}
              for k in rtt}
    return roundtrip.Measured(n, rtt_ms=rtt, stages_ms=stages, lost={"sensor": 0, "image": 0}, image_bytes=8100.0)


def test_the_table_has_a_row_per_consumer_count_and_kind_and_says_where_the_time_goes():
    rng = np.random.default_rng(1)
    sc = load_scenario(find_scenario("roundtrip"))
    res = roundtrip._result(sc, experiments.EXPERIMENTS["roundtrip"], "agents", [measured(n, rng) for n in range(1, 6)],
                            30)
    rows = {r.quantity: r for r in res.rows}
    for n in range(1, 6):
        assert f"{n} consumer(s): other sensory data (pose, sonar, battery)" in rows
        image = rows[f"{n} consumer(s): image (320x240 JPEG, 8.1 kB, compressed when sent)"]
        assert image.paper == {1: "not measured", 2: "not measured", 3: "89.2 / 90.6", 4: "89.5 / 89.1",
                               5: "91.3 / 90.5"}[n]
    where = rows["5 consumer(s), image: where the time goes"]
    first, last, back, end = (float(v) for v in str(where.ours).split(" / "))
    assert first < last and back < end and where.kind == "measured"
    assert len([k for k in res.metrics if "median ms to" in k]) == 10
