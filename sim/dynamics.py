"""The vehicle's flight as the loop flies it: acceleration limits and the decision's latency.

A decision period of the world (:meth:`sim.world.World.fly_period`) is flown here when the
world's :class:`~sim.flight.Flight` has acceleration limits. The vehicle is a point mass whose
velocity follows a commanded velocity under those limits, the commanded velocity toward the
setpoint coming from a square-root position controller (ArduPilot's ``sqrt_controller``, gain
:data:`POSITION_GAIN_PER_S`): proportional near the setpoint, constant-deceleration braking
further away, capped by the horizontal and vertical speed limits. Positions are integrated with
the trapezoid rule every :data:`PHYSICS_DT_S`. This is exactly what the autopilot simulator
(``sitl_mock/kinematics.py``, stepped at 50 Hz by ``sitl_mock/server.py``) flies, whose
constants follow ArduPilot's defaults; ``tests/sim/test_dynamics.py`` holds the two to each other
step by step, so that a policy learns in the world the way the loop will fly it.

The latency: for the first ``latency_s`` of a period the vehicle still flies toward the previous
target (the time from the report to the new setpoint reaching the autopilot), then toward the
new one. Velocity carries over from period to period; the caller keeps it.

Frames: the world's area frame (x, y on the ground, z up), metres and m/s. The vertical limit is
the same up and down (the world's ``vertical_mps``; the simulator's defaults are equal too).
Numba kernels over rows (one vehicle per row), so the vector environments fly all theirs at once.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

POSITION_GAIN_PER_S = 1.0
"""Gain of the square-root position controller (ArduPilot's default position P; the simulator's)."""
PHYSICS_DT_S = 0.02
"""Integration step: the autopilot simulator's physics rate (50 Hz)."""


@njit(cache=True, nogil=True)
def _sqrt_speed(error_m: float, accel_mps2: float) -> float:
    linear_limit_m = accel_mps2 / POSITION_GAIN_PER_S**2
    if error_m <= linear_limit_m:
        return POSITION_GAIN_PER_S * error_m
    return math.sqrt(2.0 * accel_mps2 * (error_m - linear_limit_m / 2.0))


@njit(cache=True, nogil=True)
def _fly_rows(
    position: np.ndarray,
    velocity: np.ndarray,
    previous: np.ndarray,
    target: np.ndarray,
    latency_steps: int,
    steps: int,
    dt_s: float,
    max_h_mps: float,
    max_v_mps: float,
    accel_h_mps2: float,
    accel_v_mps2: float,
) -> None:
    """Fly every row ``steps`` integration steps in place: toward ``previous`` for the first
    ``latency_steps``, then toward ``target``."""
    max_dv_h = accel_h_mps2 * dt_s
    max_dv_v = accel_v_mps2 * dt_s
    for e in range(position.shape[0]):
        x, y, z = position[e, 0], position[e, 1], position[e, 2]
        vx, vy, vz = velocity[e, 0], velocity[e, 1], velocity[e, 2]
        for i in range(steps):
            goal = previous if i < latency_steps else target
            dx, dy, dz = goal[e, 0] - x, goal[e, 1] - y, goal[e, 2] - z
            # The commanded velocity (the simulator's velocity_towards).
            dist_h = math.hypot(dx, dy)
            speed_h = min(max_h_mps, _sqrt_speed(dist_h, accel_h_mps2))
            if dist_h > 1e-9:
                wx, wy = dx / dist_h * speed_h, dy / dist_h * speed_h
            else:
                wx, wy = 0.0, 0.0
            speed_v = min(_sqrt_speed(abs(dz), accel_v_mps2), max_v_mps)
            wz = speed_v if dz > 0 else -speed_v
            # Reached under the acceleration limits (the simulator's accelerate).
            ax, ay = wx - vx, wy - vy
            dv_h = math.hypot(ax, ay)
            if dv_h > max_dv_h:
                ax, ay = ax * max_dv_h / dv_h, ay * max_dv_h / dv_h
            az = max(-max_dv_v, min(max_dv_v, wz - vz))
            nx, ny, nz = vx + ax, vy + ay, vz + az
            # Trapezoid rule, as the simulator integrates.
            x += 0.5 * (vx + nx) * dt_s
            y += 0.5 * (vy + ny) * dt_s
            z += 0.5 * (vz + nz) * dt_s
            vx, vy, vz = nx, ny, nz
        position[e, 0], position[e, 1], position[e, 2] = x, y, z
        velocity[e, 0], velocity[e, 1], velocity[e, 2] = vx, vy, vz


def fly_accelerating(
    position_m: np.ndarray,
    velocity_mps: np.ndarray,
    previous_target_m: np.ndarray,
    target_m: np.ndarray,
    *,
    duration_s: float,
    latency_s: float,
    max_h_mps: float,
    max_v_mps: float,
    accel_h_mps2: float,
    accel_v_mps2: float,
) -> tuple[np.ndarray, np.ndarray]:
    """Where each vehicle (rows of (E, 3) arrays) is, and how fast it goes, after
    ``duration_s``: toward ``previous_target_m`` for ``latency_s``, then toward ``target_m``
    (module doc). New arrays; the inputs are not changed. Durations are whole
    :data:`PHYSICS_DT_S` steps (rounded)."""
    position = np.array(position_m, dtype=float).reshape(-1, 3)
    velocity = np.array(velocity_mps, dtype=float).reshape(-1, 3)
    previous = np.ascontiguousarray(previous_target_m, dtype=float).reshape(-1, 3)
    target = np.ascontiguousarray(target_m, dtype=float).reshape(-1, 3)
    steps = max(1, round(duration_s / PHYSICS_DT_S))
    latency_steps = min(steps, round(latency_s / PHYSICS_DT_S))
    dt_s = duration_s / steps
    _fly_rows(
        position, velocity, previous, target, latency_steps, steps, dt_s,
        max_h_mps, max_v_mps, accel_h_mps2, accel_v_mps2,
    )  # fmt: skip
    return position, velocity
