"""Point-mass kinematics of a multicopter: speed and acceleration limits, a square-root position
controller, braking distance, and the geofence shape. Pure functions of plain values, no state.

Vectors are NED (north, east, down) in metres or m/s.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import NamedTuple

GRAVITY_MPS2 = 9.80665
POSITION_GAIN_PER_S = 1.0
"""Gain of the square-root position controller (ArduPilot's default position P is 1.0)."""


class Vec3(NamedTuple):
    """A NED vector: north, east, down."""

    n: float
    e: float
    d: float


ZERO = Vec3(0.0, 0.0, 0.0)


@dataclass(frozen=True)
class Limits:
    """How fast the vehicle may go and change speed."""

    max_speed_h_mps: float
    max_speed_up_mps: float
    max_speed_down_mps: float
    accel_h_mps2: float
    accel_v_mps2: float


def sqrt_controller_mps(error_m: float, gain_per_s: float, accel_mps2: float) -> float:
    """Speed towards a point ``error_m`` away: linear near it, constant-deceleration braking far
    (ArduPilot's ``sqrt_controller``; continuous, and never asks for more than ``accel_mps2``)."""
    linear_limit_m = accel_mps2 / gain_per_s**2
    if error_m <= linear_limit_m:
        return gain_per_s * error_m
    return math.sqrt(2.0 * accel_mps2 * (error_m - linear_limit_m / 2.0))


def wrap_pi(angle_rad: float) -> float:
    """``angle_rad`` folded into [-pi, pi)."""
    return (angle_rad + math.pi) % (2.0 * math.pi) - math.pi


def velocity_towards(position: Vec3, target: Vec3, limits: Limits) -> Vec3:
    """The velocity that brings ``position`` to ``target`` as fast as the limits allow."""
    dn, de, dd = target.n - position.n, target.e - position.e, target.d - position.d
    dist_h = math.hypot(dn, de)
    speed_h = min(
        limits.max_speed_h_mps,
        sqrt_controller_mps(dist_h, POSITION_GAIN_PER_S, limits.accel_h_mps2),
    )
    vn, ve = (dn / dist_h * speed_h, de / dist_h * speed_h) if dist_h > 1e-9 else (0.0, 0.0)
    speed_v = sqrt_controller_mps(abs(dd), POSITION_GAIN_PER_S, limits.accel_v_mps2)
    vd = (
        min(speed_v, limits.max_speed_down_mps)
        if dd > 0
        else -min(speed_v, limits.max_speed_up_mps)
    )
    return Vec3(vn, ve, vd)


def clamp_velocity(velocity: Vec3, limits: Limits) -> Vec3:
    """``velocity`` within the horizontal and vertical speed limits."""
    n, e, d = velocity
    speed_h = math.hypot(n, e)
    if speed_h > limits.max_speed_h_mps:
        n, e = n * limits.max_speed_h_mps / speed_h, e * limits.max_speed_h_mps / speed_h
    d = max(-limits.max_speed_up_mps, min(limits.max_speed_down_mps, d))
    return Vec3(n, e, d)


def accelerate(velocity: Vec3, desired: Vec3, limits: Limits, dt_s: float) -> Vec3:
    """The velocity after ``dt_s`` of changing ``velocity`` towards ``desired`` at the
    acceleration limits (horizontal as a vector, vertical separately)."""
    dn, de = desired.n - velocity.n, desired.e - velocity.e
    dv_h = math.hypot(dn, de)
    max_dv_h = limits.accel_h_mps2 * dt_s
    if dv_h > max_dv_h:
        dn, de = dn * max_dv_h / dv_h, de * max_dv_h / dv_h
    max_dv_v = limits.accel_v_mps2 * dt_s
    dd = max(-max_dv_v, min(max_dv_v, desired.d - velocity.d))
    return Vec3(velocity.n + dn, velocity.e + de, velocity.d + dd)


def stopping_point(position: Vec3, velocity: Vec3, limits: Limits) -> Vec3:
    """Where the vehicle comes to rest if it brakes now (what a hold mode holds); never below
    the ground (down <= 0)."""
    speed_h = math.hypot(velocity.n, velocity.e)
    scale_h = speed_h / (2.0 * limits.accel_h_mps2)  # braking distance v²/2a along v
    scale_v = abs(velocity.d) / (2.0 * limits.accel_v_mps2)
    return Vec3(
        position.n + velocity.n * scale_h,
        position.e + velocity.e * scale_h,
        min(0.0, position.d + velocity.d * scale_v),
    )


@dataclass(frozen=True)
class Fence:
    """A cylinder around home: ``radius_m`` horizontally, ``alt_max_m`` up (None: unbounded)."""

    radius_m: float | None
    alt_max_m: float | None

    def clamp(self, point: Vec3) -> Vec3:
        """The nearest point to ``point`` inside the fence (``point`` itself if inside)."""
        n, e, d = point
        if self.radius_m:
            dist = math.hypot(n, e)
            if dist > self.radius_m:
                n, e = n * self.radius_m / dist, e * self.radius_m / dist
        if self.alt_max_m and -d > self.alt_max_m:
            d = -self.alt_max_m
        return Vec3(n, e, d)

    def contains(self, point: Vec3) -> bool:
        return self.clamp(point) == point
