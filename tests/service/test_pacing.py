"""Setpoints paced while the autopilot does not hold the envelope's speed limit
(:func:`service.link_safety.paced_setpoint`): never further ahead than a vehicle at the limit
may be given, always on the way to the route's setpoint."""

from __future__ import annotations

import math

import pytest

from service.link_safety import PACE_LEAD_S, paced_setpoint
from sitl_mock.kinematics import Limits, Vec3, velocity_towards


def test_a_setpoint_within_the_lead_streams_as_it_is() -> None:
    assert paced_setpoint((0.0, 0.0, 20.0), (2.0, 1.0, 30.0), 4.0, 2.5) == (2.0, 1.0, 30.0)


def test_a_far_setpoint_is_brought_to_the_lead_on_the_way_to_it() -> None:
    here, there = (10.0, 20.0, 20.0), (70.0, 100.0, 40.0)
    paced = paced_setpoint(here, there, 4.0, 2.5)
    lead_m = min(4.0 * PACE_LEAD_S, 4.0**2 / (2 * 2.5))
    assert math.hypot(paced[0] - here[0], paced[1] - here[1]) == pytest.approx(lead_m)
    # On the straight way: the same share of each coordinate's way, height included.
    shares = [(p - a) / (b - a) for p, a, b in zip(paced, here, there, strict=True)]
    assert shares == pytest.approx([shares[0]] * 3) and 0 < shares[0] < 1


def test_a_straight_climb_is_not_held_back() -> None:
    assert paced_setpoint((5.0, 5.0, 10.0), (5.0, 5.0, 60.0), 4.0, 2.5) == (5.0, 5.0, 60.0)


@pytest.mark.parametrize("max_speed_mps", [1.0, 2.0, 4.0, 7.0, 10.0, 15.0])
@pytest.mark.parametrize("accel_mps2", [1.0, 2.5])
def test_a_vehicle_flying_at_its_own_speed_towards_it_keeps_to_the_limit(
    max_speed_mps: float, accel_mps2: float
) -> None:
    """ArduPilot's square-root position controller (the mock's), allowed 20 m/s and braking at
    up to the pacing's 2.5 m/s², asks for no more than the limit towards a paced setpoint."""
    limits = Limits(20.0, 5.0, 5.0, accel_mps2, accel_mps2)
    paced = paced_setpoint((0.0, 0.0, 30.0), (400.0, 300.0, 30.0), max_speed_mps, 2.5)
    velocity = velocity_towards(Vec3(0.0, 0.0, -30.0), Vec3(paced[1], paced[0], -30.0), limits)
    assert math.hypot(velocity.n, velocity.e) <= max_speed_mps + 1e-9
