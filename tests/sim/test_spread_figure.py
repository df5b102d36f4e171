"""The spread figure's range panels: drawn on the ranges' axis even when no run settled."""

from __future__ import annotations

import math

import matplotlib
import numpy as np

matplotlib.use("Agg")
from matplotlib.figure import Figure  # noqa: E402

from erni.sim.experiments import spread  # noqa: E402


def _run(variant: str, converged: float) -> spread.Run:
    pos = np.array([[[0.0, 0.0], [4.0, 0.0], [0.0, 4.0]]] * 2)
    return spread.Run(variant, np.array([0.0, 1.0]), pos, np.zeros((2, 3)), np.zeros((2, 3)), converged)


def test_the_time_to_converge_panel_keeps_the_ranges_axis_when_no_run_settled():
    sweep = [(r, _run(v, math.nan)) for r in (5.0, 6.0) for v in ("holonomic/physical", "nonholonomic/physical")]
    fig = Figure()
    top, bottom = fig.add_subplot(2, 1, 1), fig.add_subplot(2, 1, 2)
    spread._draw_sweep(top, bottom, sweep, 5.0)
    lo, hi = bottom.get_xlim()
    assert lo < 1.0 and hi > 1.2 and lo > 0.8 and hi < 1.4  # R / d = 1.0 and 1.2, not matplotlib's empty default
    assert any("no run settled" in t.get_text() for t in bottom.texts)
    settled = [(r, _run(v, 50.0)) for r, v in ((5.0, "holonomic/physical"), (6.0, "holonomic/physical"))]
    fig = Figure()
    top, bottom = fig.add_subplot(2, 1, 1), fig.add_subplot(2, 1, 2)
    spread._draw_sweep(top, bottom, settled, 5.0)
    assert not bottom.texts
