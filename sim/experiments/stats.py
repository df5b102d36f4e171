"""Summaries over repeated runs: means with Student-t confidence intervals, Wilson intervals for shares."""

from __future__ import annotations

import math
from collections.abc import Sequence


def mean_ci(values: Sequence[float], level: float = 0.95,
            bounds: tuple[float, float] | None = None) -> tuple[float, float, float]:
    """Return (mean, low, high) of the finite `values`: a Student-t interval (NaNs when empty),
    cut to `bounds` when the quantity has them (a share of time lies in 0..1)."""
    from scipy import stats

    xs = [float(v) for v in values if math.isfinite(v)]
    if not xs:
        return math.nan, math.nan, math.nan
    m = sum(xs) / len(xs)
    if len(xs) < 2:
        return m, math.nan, math.nan
    sd = math.sqrt(sum((x - m) ** 2 for x in xs) / (len(xs) - 1))
    half = float(stats.t.ppf(0.5 + level / 2, len(xs) - 1)) * sd / math.sqrt(len(xs))
    lo, hi = m - half, m + half
    if bounds is not None:
        lo, hi = max(bounds[0], lo), min(bounds[1], hi)
    return m, lo, hi


def wilson(successes: int, n: int, level: float = 0.95) -> tuple[float, float, float]:
    """Return (share, low, high): the Wilson score interval of `successes` out of `n`."""
    from scipy import stats

    if n <= 0:
        return math.nan, math.nan, math.nan
    z = float(stats.norm.ppf(0.5 + level / 2))
    p = successes / n
    denom = 1 + z * z / n
    centre = (p + z * z / (2 * n)) / denom
    half = z * math.sqrt(p * (1 - p) / n + z * z / (4 * n * n)) / denom
    return p, max(0.0, centre - half), min(1.0, centre + half)


def fmt_ci(m: float, lo: float, hi: float, digits: int = 2) -> str:
    """`m [lo, hi]` with `digits` decimals (just `m` when the interval is undefined)."""
    if not math.isfinite(lo):
        return f"{m:.{digits}f}"
    return f"{m:.{digits}f} [{lo:.{digits}f}, {hi:.{digits}f}]"
