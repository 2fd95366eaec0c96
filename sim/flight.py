"""How a vehicle flies toward its target at its speed caps: :class:`Flight` (the settings) and
straight flight (:func:`fly`, :func:`fly_point`, :func:`fly_many`). One code path for the world
(:meth:`sim.world.World.fly`), the flight inside an envelope (:mod:`sim.envelope.flight`), the
planners and the service's predictions; the flight under acceleration limits is
:mod:`sim.dynamics`'s.

Frames: the world's area frame (x, y on the ground, z up), metres, m/s and seconds.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from sim.errors import InputError
from sim.geometry import SCALAR_ROWS

__all__ = ["Flight", "fly", "fly_many", "fly_point"]


@dataclass(frozen=True)
class Flight:
    """How fast the vehicle reaches a target: ``None`` speeds mean it is there at once.

    Without an acceleration limit the vehicle flies at its speed caps from the first instant
    (:func:`fly`). With one (``accel_mps2``, horizontally and vertically alike, as the loop's
    autopilots' defaults; both speeds needed) it flies as the loop's autopilot does: a point mass
    under that limit, steered by a square-root position controller, its velocity carried from
    period to period (:mod:`sim.dynamics`). ``latency_s``: for that long after a decision the
    vehicle still flies toward the previous target (from the report to the new setpoint on the
    autopilot; at most the decision period: a decision reaches the vehicle within its own
    period).

    Inside a flight-safety envelope (:attr:`World.envelope`) the routes the link streams are
    flown: under the same acceleration limit and latency when the flight has one
    (:func:`sim.envelope.flight.fly_route_period`), else at the speed caps."""

    horizontal_mps: float | None = 10.0
    vertical_mps: float | None = 3.0
    accel_mps2: float | None = None
    latency_s: float = 0.0

    def __post_init__(self) -> None:
        for name in ("horizontal_mps", "vertical_mps"):
            value = getattr(self, name)
            if value is not None and not (math.isfinite(value) and value > 0):
                raise InputError(f"flight.{name}: must be > 0 (or none: no flight), got {value}")
        value = self.accel_mps2
        if value is not None and not (math.isfinite(value) and value > 0):
            raise InputError(
                f"flight.accel_mps2: must be > 0 (or none: no acceleration limit), got {value}"
            )
        if value is not None and (self.horizontal_mps is None or self.vertical_mps is None):
            raise InputError(
                "flight.accel_mps2: an acceleration limit needs both speed caps "
                "(flight.horizontal_mps and flight.vertical_mps; or set flight.accel_mps2=none)"
            )
        if not (math.isfinite(self.latency_s) and self.latency_s >= 0):
            raise InputError(f"flight.latency_s: must be >= 0, got {self.latency_s}")

    @property
    def teleports(self) -> bool:
        return self.horizontal_mps is None and self.vertical_mps is None

    @property
    def accelerates(self) -> bool:
        """Whether the flight has an acceleration limit (and carries a velocity)."""
        return self.accel_mps2 is not None

    @property
    def stateless(self) -> bool:
        """Whether a period's flight depends only on the position and the new target (no
        acceleration limits, no latency): :func:`fly`."""
        return not self.accelerates and self.latency_s == 0.0


def fly(
    position_m: np.ndarray, target_m: np.ndarray, flight: Flight, duration_s: float
) -> np.ndarray:
    """Straight toward ``target_m`` for ``duration_s``, horizontal and vertical speeds capped
    separately (as a multirotor's position controller does); at the target when in reach."""
    px, py, pz = (float(v) for v in position_m)
    x, y, z = (float(v) for v in target_m)
    return np.array(fly_point(px, py, pz, x, y, z, flight, duration_s))


def fly_point(
    px: float, py: float, pz: float, x: float, y: float, z: float, flight: Flight, duration_s: float
) -> tuple[float, float, float]:
    """:func:`fly` on Python floats: where a vehicle at (px, py, pz) ends, aiming at (x, y, z)."""
    if flight.horizontal_mps is not None:
        gap_x, gap_y = x - px, y - py
        distance = math.hypot(gap_x, gap_y)
        reach = flight.horizontal_mps * duration_s
        if distance > reach:
            x, y = px + gap_x * (reach / distance), py + gap_y * (reach / distance)
    if flight.vertical_mps is not None:
        reach_z = flight.vertical_mps * duration_s
        if abs(z - pz) > reach_z:
            z = pz + math.copysign(reach_z, z - pz)
    return x, y, z


def fly_many(
    position_m: np.ndarray, target_m: np.ndarray, flight: Flight, duration_s: float
) -> np.ndarray:
    """:func:`fly` of each row of ``position_m`` toward ``target_m`` (E, 3): the same floats.

    The horizontal distance is Python's ``math.hypot`` (as the scalar function's), one call per
    row: numpy's ``hypot`` rounds differently in the last bit now and then."""
    position = np.asarray(position_m, dtype=float)
    if len(position) <= SCALAR_ROWS:  # a fleet: Python floats
        rows = zip(position.tolist(), np.asarray(target_m, dtype=float).tolist(), strict=True)
        flown = [fly_point(*p, *t, flight, duration_s) for p, t in rows]
        return np.array(flown, dtype=float).reshape(len(position), 3)
    out = np.array(target_m, dtype=float)
    if flight.horizontal_mps is not None:
        gap_x = out[:, 0] - position[:, 0]
        gap_y = out[:, 1] - position[:, 1]
        distance = np.fromiter(
            map(math.hypot, gap_x.tolist(), gap_y.tolist()), dtype=float, count=len(out)
        )
        reach = flight.horizontal_mps * duration_s
        far = distance > reach
        if far.any():
            scale = reach / distance[far]
            out[far, 0] = position[far, 0] + gap_x[far] * scale
            out[far, 1] = position[far, 1] + gap_y[far] * scale
    if flight.vertical_mps is not None:
        reach_z = flight.vertical_mps * duration_s
        gap_z = out[:, 2] - position[:, 2]
        far = np.abs(gap_z) > reach_z
        if far.any():
            out[far, 2] = position[far, 2] + np.copysign(reach_z, gap_z[far])
    return out
