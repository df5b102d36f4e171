"""Relay positioning between a source and a destination (paper 000, section 5.2).

A relay robot moves on the straight line between a source S and a destination D, one
decision per period, toward the side whose link is worse, until the two link qualities
(delivery ratios 0..1) differ by at most `tolerance`. With links that fade with distance the
balance point is the middle of S-D; n relays in a chain settle at equal spacing
(`chain_slots`, the paper's d = 2 (n_node - 1) with the spacing chosen by the line length).

Inputs (pure, numpy): `pos`, `source`, `destination`: (2,) points (m); `q_source`,
`q_destination`: link qualities 0..1 (None = no link: treated as 0); `gain`: metres moved per
unit of quality imbalance; `min_step` / `max_step`: bounds of one move (m).
Output of `relay_step`: `RelayMove` (target point (2,), signed move along S->D in m, the
imbalance q_destination - q_source, balanced flag).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from erni.blackboard.errors import UsageError


@dataclass(frozen=True)
class RelayMove:
    """One relay decision."""

    target: NDArray[np.float64]  # (2,) point on the S-D segment to move to (m)
    along: float                 # signed move along S -> D (m): negative = toward the source
    imbalance: float             # q_destination - q_source
    balanced: bool               # |imbalance| <= tolerance: hold position


def project(pos: ArrayLike, source: ArrayLike, destination: ArrayLike) -> tuple[NDArray[np.float64], float]:
    """Return (nearest point on segment S-D to pos, its fraction 0..1 from S)."""
    p, s, d = (np.asarray(a, dtype=float).reshape(2) for a in (pos, source, destination))
    sd = d - s
    length2 = float(sd @ sd)
    if length2 < 1e-12:
        return s.copy(), 0.0
    t = float(np.clip((p - s) @ sd / length2, 0.0, 1.0))
    return s + t * sd, t


def relay_step(pos: ArrayLike, source: ArrayLike, destination: ArrayLike, q_source: float | None,
               q_destination: float | None, *, tolerance: float = 0.05, gain: float = 4.0,
               min_step: float = 0.1, max_step: float = 1.0) -> RelayMove:
    """Return the relay's next target on S-D: toward the worse link, or hold when balanced."""
    qs = 0.0 if q_source is None else float(q_source)
    qd = 0.0 if q_destination is None else float(q_destination)
    for name, q in (("q_source", qs), ("q_destination", qd)):
        if not 0.0 <= q <= 1.0:
            raise UsageError(f"{name}: expected a link quality in 0..1, got {q!r}")
    if not tolerance > 0 or not 0 < min_step <= max_step:
        raise UsageError("relay_step: expected tolerance > 0 and 0 < min_step <= max_step")
    s, d = (np.asarray(a, dtype=float).reshape(2) for a in (source, destination))
    on_line, t = project(pos, s, d)
    length = float(np.hypot(*(d - s)))
    imbalance = qd - qs
    if abs(imbalance) <= tolerance or length < 1e-9:
        return RelayMove(on_line, 0.0, imbalance, True)
    step = min(max_step, max(min_step, gain * abs(imbalance)))
    # shorten the worse link: q_destination > q_source means the source link is worse -> toward S
    along = -step if imbalance > 0 else step
    t_new = float(np.clip(t + along / length, 0.0, 1.0))
    return RelayMove(s + t_new * (d - s), (t_new - t) * length, imbalance, False)


def chain_slots(source: ArrayLike, destination: ArrayLike, n: int) -> NDArray[np.float64]:
    """Return (n, 2) equally spaced relay positions strictly between S and D (k / (n + 1))."""
    if n < 0:
        raise UsageError(f"n: expected a number of relays >= 0, got {n}")
    s, d = (np.asarray(a, dtype=float).reshape(2) for a in (source, destination))
    frac = np.arange(1, n + 1) / (n + 1)
    slots: NDArray[np.float64] = s + frac[:, None] * (d - s)
    return slots


def distance_quality(distance: ArrayLike, R: float, clean: float) -> NDArray[np.float64]:
    """A fading link model for tests and kinematic runs: 1 up to `clean` m, falling to 0 at R."""
    dist = np.asarray(distance, dtype=float)
    if not 0 <= clean < R:
        raise UsageError("distance_quality: expected 0 <= clean < R")
    quality: NDArray[np.float64] = np.clip((R - dist) / (R - clean), 0.0, 1.0)
    return quality
