"""The battery reserve: when the service ends the placement and sends the vehicle home.

The vehicle reports its remaining charge (SYS_STATUS ``battery_remaining``, %). The service
measures how fast it drains while flying (:class:`DrainEstimate`: the slope over the last
``window_s``) and works out what flying home from where the vehicle is would take
(:func:`return_needs_pct`: the horizontal distance at ``return_speed_mps``, the descent at
``descent_speed_mps`` and its last ``land_slow_alt_m`` at ``land_speed_mps``, plus
``margin_s``). When the charge left is no more than that plus the
configured ``reserve_pct`` (what should be left on landing), :func:`reserve_reached` says why,
and the link commands the return (MAV_CMD_NAV_RETURN_TO_LAUNCH) and lets go of the vehicle
(:mod:`service.control`: the autopilot has it; only an operator hands it back). A reserve above
the autopilot's own low-battery failsafe level (PX4 ``BAT_LOW_THR`` 15 %, the mock's 10 %)
returns the vehicle before that failsafe has to.

Until ``min_window_s`` of flight has been measured, the drain is taken as
``assumed_drain_pct_per_s`` (a multirotor's 20-minute pack: 0.083 %/s) or the measured one,
whichever is larger. Pure functions and one small stateful estimator; no I/O.
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass


@dataclass(frozen=True)
class BatteryConfig:
    """The reserve and what the return is assumed to take."""

    reserve_pct: float | None = 20.0
    """Charge to be left on landing, %; None: the service never sends the vehicle home (the
    autopilot's own failsafe still does)."""
    return_speed_mps: float = 5.0
    """Horizontal speed of the return (ArduCopter WPNAV_SPEED / RTL_SPEED, PX4 MPC_XY_CRUISE)."""
    descent_speed_mps: float = 1.5
    """Descent speed of the landing (ArduCopter WPNAV_SPEED_DN, PX4 MPC_Z_VEL_MAX_DN)."""
    land_speed_mps: float = 0.5
    """Descent speed of the landing's last ``land_slow_alt_m`` (ArduCopter LAND_SPEED 50 cm/s
    below LAND_ALT_LOW; PX4 MPC_LAND_SPEED 0.7 m/s)."""
    land_slow_alt_m: float = 10.0
    """Height above home below which the landing slows (ArduCopter LAND_ALT_LOW 10 m)."""
    margin_s: float = 20.0
    """Added to the return's time (climb to the return altitude, the landing's slow end)."""
    window_s: float = 120.0
    min_window_s: float = 20.0
    assumed_drain_pct_per_s: float = 100.0 / (20 * 60)

    def __post_init__(self) -> None:
        if self.reserve_pct is not None and not (0 <= self.reserve_pct < 100):
            raise ValueError(f"reserve_pct: must be in 0..100, got {self.reserve_pct!r}")
        for name in (
            "return_speed_mps",
            "descent_speed_mps",
            "land_speed_mps",
            "window_s",
            "min_window_s",
        ):
            value = getattr(self, name)
            if not (math.isfinite(value) and value > 0):
                raise ValueError(f"{name}: must be a positive number, got {value!r}")


class DrainEstimate:
    """How fast the charge drops while flying, from the readings of the last ``window_s``."""

    def __init__(self, config: BatteryConfig) -> None:
        self.config = config
        self._samples: deque[tuple[float, float]] = deque()

    def add(self, time_s: float, remaining_pct: float) -> None:
        """A reading taken while flying; a higher one than before (a new pack) starts afresh."""
        if self._samples and remaining_pct > self._samples[-1][1] + 5.0:
            self._samples.clear()
        self._samples.append((time_s, remaining_pct))
        while self._samples and time_s - self._samples[0][0] > self.config.window_s:
            self._samples.popleft()

    def reset(self) -> None:
        self._samples.clear()

    @property
    def measured_pct_per_s(self) -> float | None:
        """The least-squares slope of the readings (positive: draining), once they span
        ``min_window_s``; else None."""
        if len(self._samples) < 2:
            return None
        t0 = self._samples[0][0]
        if self._samples[-1][0] - t0 < self.config.min_window_s:
            return None
        ts = [t - t0 for t, _ in self._samples]
        ps = [p for _, p in self._samples]
        mean_t, mean_p = sum(ts) / len(ts), sum(ps) / len(ps)
        var = sum((t - mean_t) ** 2 for t in ts)
        if var == 0:
            return None
        slope = sum((t - mean_t) * (p - mean_p) for t, p in zip(ts, ps, strict=True)) / var
        return max(0.0, -slope)

    @property
    def pct_per_s(self) -> float:
        """The drain used for the reserve: the measured one once the readings span
        ``min_window_s``, the assumed one before."""
        measured = self.measured_pct_per_s
        if measured is None:
            return self.config.assumed_drain_pct_per_s
        return measured


def return_needs_pct(
    drain_pct_per_s: float, distance_home_m: float, height_m: float, config: BatteryConfig
) -> float:
    """The charge (%) flying home from ``distance_home_m`` away and ``height_m`` up takes: the
    way home, the descent, its slow last metres, and the margin."""
    height_m = max(0.0, height_m)
    slow_m = min(height_m, config.land_slow_alt_m)
    time_s = (
        max(0.0, distance_home_m) / config.return_speed_mps
        + (height_m - slow_m) / config.descent_speed_mps
        + slow_m / config.land_speed_mps
        + config.margin_s
    )
    return drain_pct_per_s * time_s


def reserve_reached(
    remaining_pct: float,
    drain_pct_per_s: float,
    distance_home_m: float,
    height_m: float,
    config: BatteryConfig,
) -> str | None:
    """Why the vehicle must go home now (one line), or None while the charge suffices."""
    if config.reserve_pct is None:
        return None
    needs = return_needs_pct(drain_pct_per_s, distance_home_m, height_m, config)
    if remaining_pct > needs + config.reserve_pct:
        return None
    return (
        f"battery reserve reached: {remaining_pct:.0f} % left, flying home "
        f"({distance_home_m:.0f} m, {height_m:.0f} m up) takes ~{needs:.1f} % at "
        f"{drain_pct_per_s * 60:.2f} %/min, and {config.reserve_pct:g} % must be left on landing"
    )
