"""Drawing helpers shared by the experiments' figures: the world, robots, and tidy axes."""

from __future__ import annotations

import math
from typing import Any

import numpy as np
from numpy.typing import NDArray

from erni.sim.world import World

COLORS = ["#1f77b4", "#d62728", "#2ca02c", "#9467bd", "#ff7f0e", "#8c564b", "#e377c2", "#17becf"]


def color(i: int) -> str:
    """The i-th colour of the experiments' palette."""
    return COLORS[i % len(COLORS)]


def draw_world(ax: Any, world: World) -> None:
    """Draw walls, bounds and polygons as dark lines and circles as grey discs."""
    from matplotlib.patches import Circle, Polygon

    first = True
    for a, b in world.segments():
        (x1, y1), (x2, y2) = a, b
        ax.plot([x1, x2], [y1, y2], color="#333333", lw=2.5, solid_capstyle="butt",
                label="wall" if first else None, zorder=2)
        first = False
    for i, c in enumerate(world.circle):
        ax.add_patch(Circle(c.center, c.radius, facecolor="#9e9e9e", edgecolor="#424242", lw=1.2,
                            label="obstacle" if i == 0 else None, zorder=2))
    for poly in world.polygon:
        ax.add_patch(Polygon(poly.points, closed=True, facecolor="#bdbdbd", edgecolor="#424242", zorder=2))


def map_axes(ax: Any, title: str) -> None:
    """Equal-scale x/y axes in metres with a light grid."""
    ax.set_aspect("equal", adjustable="box")
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")
    ax.set_title(title)
    ax.grid(True, color="#e0e0e0", lw=0.6)


def time_axes(ax: Any, title: str, ylabel: str) -> None:
    """A time axis in seconds with a light grid."""
    ax.set_xlabel("time (s)")
    ax.set_ylabel(ylabel)
    ax.set_title(title)
    ax.grid(True, color="#e0e0e0", lw=0.6)


def headings(ax: Any, pos: NDArray[np.float64], th: NDArray[np.float64], length: float, **kw: Any) -> None:
    """Draw each robot's heading as a short arrow."""
    ax.quiver(pos[:, 0], pos[:, 1], np.cos(th) * length, np.sin(th) * length, angles="xy",
              scale_units="xy", scale=1, width=0.0025, headwidth=3.5, headlength=4, **kw)


def range_circle(ax: Any, x: float, y: float, r: float, **kw: Any) -> None:
    """Draw a dashed circle of radius r (a communication or sensing range)."""
    a = np.linspace(0, 2 * math.pi, 120)
    ax.plot(x + r * np.cos(a), y + r * np.sin(a), ls="--", lw=0.8, **kw)


def draw_table(fig: Any, rows: list[Any], caption: str = "") -> None:
    """Draw the paper-vs-ours table (a list of `Compare`) across `fig`; inputs in grey italics."""
    import textwrap

    from erni.sim.experiments import _fmt

    ax = fig.add_subplot(1, 1, 1)
    ax.axis("off")
    if caption:
        ax.set_title(caption, loc="left", fontsize=8.5, color="#333333")
    widths = [0.27, 0.16, 0.13, 0.05, 0.39]
    chars = [52, 30, 24, 8, 80]  # wrap each column at about this many characters (font 7.5)
    cells = []
    for r in rows:
        texts = [r.quantity + (" (input)" if r.kind == "input" else ""), _fmt(r.paper), _fmt(r.ours), r.unit, r.how]
        cells.append(["\n".join(textwrap.wrap(str(t), c)) or "" for t, c in zip(texts, chars)])
    lines = [1] + [max(c.count("\n") + 1 for c in row) for row in cells]
    table = ax.table(cellText=cells, colLabels=["quantity", "paper", "ours", "unit", "how ours was obtained"],
                     colLoc="left", cellLoc="left", loc="upper center", colWidths=widths)
    table.auto_set_font_size(False)
    table.set_fontsize(7.5)
    unit = 1.0 / sum(lines)
    for (row, _col), cell in table.get_celld().items():
        cell.set_edgecolor("#cccccc")
        cell.set_height(unit * lines[row])
        if row == 0:
            cell.set_text_props(weight="bold")
            cell.set_facecolor("#eeeeee")
        elif rows[row - 1].kind == "input":
            cell.set_text_props(color="#777777", style="italic")


def table_lines(rows: list[Any]) -> int:
    """How many text lines the table of `rows` takes (its header included), as `draw_table` wraps them."""
    import textwrap

    from erni.sim.experiments import _fmt

    chars = [52, 30, 24, 8, 80]
    total = 1
    for r in rows:
        texts = [r.quantity + (" (input)" if r.kind == "input" else ""), _fmt(r.paper), _fmt(r.ours), r.unit, r.how]
        total += max(max(1, len(textwrap.wrap(str(t), c))) for t, c in zip(texts, chars))
    return total
