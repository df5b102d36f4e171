"""The experiments' figures print as a paper would: nothing clipped, whole-number ticks for counts,
panels of one time line on one time axis (drawn from made-up numbers: the layout is under test)."""

from __future__ import annotations

from typing import Any

import matplotlib
import numpy as np

matplotlib.use("Agg")
from matplotlib.backends.backend_agg import FigureCanvasAgg  # noqa: E402
from matplotlib.figure import Figure  # noqa: E402


def _render(draw: Any, width: float = 13.0, height: float = 7.5) -> Figure:
    fig = Figure(figsize=(width, height), dpi=110, layout="constrained")
    FigureCanvasAgg(fig)
    draw(fig)
    fig.canvas.draw()
    return fig


def _clipped(fig: Figure) -> list[str]:
    """Every panel (with its titles, labels, tick labels and legend) or figure text that reaches past
    the figure's edge."""
    r = fig.canvas.get_renderer()  # type: ignore[attr-defined]  # an Agg canvas (_render)
    box = fig.bbox
    out = []
    items = [(ax.get_title() or "panel", ax.get_tightbbox(r)) for ax in fig.axes]
    items += [(t.get_text(), t.get_window_extent(r)) for t in list(fig.texts) + [fig._suptitle] if t is not None]
    items += [("legend", lg.get_window_extent(r)) for lg in fig.legends]
    for name, e in items:
        if e is not None and (e.x0 < box.x0 - 1 or e.x1 > box.x1 + 1 or e.y0 < box.y0 - 1 or e.y1 > box.y1 + 1):
            out.append(name)
    return out


def test_the_response_figure_keeps_both_titles_inside():
    from erni.sim.experiments import response

    rng = np.random.default_rng(1)
    data = {p: [list(rng.normal(m, 1.0, 50)), list(rng.normal(m, 1.0, 50))]
            for p, m in (("raw", 5.2), ("poll", 10.7), ("notify", 10.7), ("remote", 12.6))}
    labels = {"raw": "raw (device layer)", "poll": "poll (blackboard, active wait)",
              "notify": "notify (subscription)", "remote": "remote notify (transport, other process)"}
    fig = _render(lambda f: response._draw(f, data, labels, 0.01))
    assert _clipped(fig) == []


def test_the_round_trip_axis_counts_whole_consumers():
    from erni.sim.experiments import roundtrip

    rng = np.random.default_rng(2)
    measured = [roundtrip.Measured(n, {k: list(rng.normal(2.0 * n, 0.3, 40)) for k in ("sensor", "image")})
                for n in (1, 3, 5)]
    fig = _render(lambda f: roundtrip._draw(f, measured, ["sensor", "image"]))
    assert _clipped(fig) == []
    ax = fig.axes[1]
    ticks = [t for t in ax.get_xticks() if ax.get_xlim()[0] <= t <= ax.get_xlim()[1]]
    assert ticks and all(float(t).is_integer() for t in ticks)
    assert {1, 3, 5} <= {int(t) for t in ticks}


def test_the_energy_figure_puts_power_and_battery_on_one_time_axis():
    from erni.sim.experiments import energy

    t = np.arange(0.0, 12.0, 0.05)
    v = np.clip(t, 0, 0.5) * (t < 10.5)
    whole_t = np.arange(-10.0, 40.0, 0.05)
    whole_v = np.interp(whole_t, t, v, left=0.0, right=0.0)
    batt = [(tt + 100.0, 12.9 - 0.1 * int((tt + 10) // 10)) for tt in np.arange(-10.0, 40.0, 1.0)]
    sweep = [(a, a * 0.95, 20.0, 30) for a in (0.1, 0.3, 0.5, 0.7, 0.9)]
    asked = [(0.0, 0.5, 10.5), (13.0, 0.1, 16.0), (17.0, 0.3, 20.0)]
    fig = _render(lambda f: energy._draw(f, t, v, 0.5, 5.0, sweep, batt, 100.0, whole_t, whole_v, asked))
    assert _clipped(fig) == []
    by_title = {ax.get_title(): ax for ax in fig.axes}
    power = next(ax for title, ax in by_title.items() if title.startswith("Power"))
    battery = next(ax for title, ax in by_title.items() if title.startswith("Battery"))
    assert power.get_shared_x_axes().joined(power, battery)
    assert power.get_xlim() == battery.get_xlim() and power.get_xlim()[0] <= -10.0 and power.get_xlim()[1] >= 39.0
