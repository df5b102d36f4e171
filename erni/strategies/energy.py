"""Energy model of a wheeled robot (paper 000, section 5.3): power and energy from speeds or tracks.

Standing still a robot draws P0 = 8.568 W; moving at speed v (m/s) it draws
Pmov(v) = 11.55 v + 14.838 W. All functions are pure and vectorised over numpy arrays.

- `power(v)`: speeds (m/s, any shape; the sign is ignored) -> power (W), same shape.
- `energy(v, dt)`: speeds sampled every `dt` seconds (last axis = time) -> energy (J).
- `track_energy(t, x, y)`: a track (times in s, positions in m) -> (energy J, distance m),
  with the speed of each interval taken as its straight-line distance over its duration.
- `EnergyMeter`: the same sums accumulated one pose at a time (for a running robot).

Units: metres, seconds, watts, joules. A speed below `MOVING` (1 mm/s) counts as standing.
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import ArrayLike, NDArray

from erni.blackboard.errors import UsageError

P0 = 8.568          # W, standing (standby mode)
PMOV_SLOPE = 11.55  # W per m/s
PMOV_BASE = 14.838  # W, moving at (almost) zero speed
MOVING = 1e-3       # m/s: slower than this is standing


def power(v: ArrayLike) -> NDArray[np.float64]:
    """Power drawn (W) at speeds `v` (m/s): P0 standing, 11.55|v| + 14.838 moving."""
    speed = np.abs(np.asarray(v, dtype=float))
    watts: NDArray[np.float64] = np.where(speed < MOVING, P0, PMOV_SLOPE * speed + PMOV_BASE)
    return watts


def energy(v: ArrayLike, dt: float) -> NDArray[np.float64] | np.float64:
    """Energy (J) of speeds sampled every `dt` s along the last axis (one value per robot).

    One robot's speeds (1-D) give a scalar, several robots' (N, T) an array (N,).
    """
    if not dt > 0:
        raise UsageError(f"dt: expected a positive sampling period (s), got {dt!r}")
    joules: NDArray[np.float64] | np.float64 = power(v).sum(axis=-1) * dt
    return joules


def track_energy(t: ArrayLike, x: ArrayLike, y: ArrayLike) -> tuple[float, float]:
    """Return (energy J, distance m) of one robot's track sampled at increasing times `t`."""
    ta, xa, ya = (np.asarray(a, dtype=float) for a in (t, x, y))
    if not (ta.ndim == xa.ndim == ya.ndim == 1 and len(ta) == len(xa) == len(ya)):
        raise UsageError("track_energy: t, x and y must be 1-D arrays of the same length")
    if len(ta) < 2:
        return 0.0, 0.0
    dt = np.diff(ta)
    if np.any(dt < 0):
        raise UsageError("track_energy: times must not decrease")
    step = np.hypot(np.diff(xa), np.diff(ya))
    with np.errstate(divide="ignore", invalid="ignore"):
        speed = np.where(dt > 0, step / np.where(dt > 0, dt, 1.0), 0.0)
    return float((power(speed) * dt).sum()), float(step.sum())


class EnergyMeter:
    """Accumulates a robot's energy (J), distance (m) and moving time (s) from successive poses."""

    def __init__(self) -> None:
        self.energy_j = 0.0
        self.distance_m = 0.0
        self.moving_s = 0.0
        self.elapsed_s = 0.0
        self._last: tuple[float, float, float] | None = None

    def update(self, t: float, x: float, y: float) -> None:
        """Add the interval since the previous pose (times in s must not go back; resets if they do)."""
        if self._last is not None:
            t0, x0, y0 = self._last
            dt = t - t0
            if dt > 0:
                step = math.hypot(x - x0, y - y0)
                speed = step / dt
                self.energy_j += float(power(speed)) * dt
                self.distance_m += step
                self.elapsed_s += dt
                if speed >= MOVING:
                    self.moving_s += dt
            elif dt < 0:
                self._last = (t, x, y)
                return
        self._last = (t, x, y)

    def values(self, until: float | None = None) -> dict[str, float]:
        """The totals as result values: energy_j, distance_m, moving_s, elapsed_s (rounded).

        With `until` (a time on the poses' clock), the robot is taken to have stood where its last
        pose put it from that pose to `until`, at standby power: a standing robot's poses come
        only as keep-alives, and the time since the last one was spent all the same."""
        energy, elapsed = self.energy_j, self.elapsed_s
        if until is not None and self._last is not None and until > self._last[0]:
            rest = until - self._last[0]
            energy += P0 * rest
            elapsed += rest
        return {"energy_j": round(energy, 2), "distance_m": round(self.distance_m, 3),
                "moving_s": round(self.moving_s, 2), "elapsed_s": round(elapsed, 2)}
