"""The world's accelerating flight (:mod:`sim.dynamics`, ``World.fly_period``) against the
autopilot simulator's vehicle, and in the environments.

The parity test flies the simulator's ArduPilot vehicle (the state machine, stepped at its 50 Hz)
through a sequence of position targets, each reaching it ``latency_s`` into its decision period,
and the world through the same targets: the positions at every period's end must agree."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest

from sim.config import AreaConfig
from sim.dynamics import PHYSICS_DT_S, fly_accelerating
from sim.envs import FapContinuousEnv
from sim.errors import InputError
from sim.flight import Flight, fly_many
from sim.scenarios import generate_scenarios
from sim.vector_env import FapVectorEnv
from sim.world import CLOSED_LOOP, World, get_world, world_with
from sitl_mock.flavours import ARDUPILOT
from sitl_mock.setpoints import FRAME_LOCAL_NED, POSITION_ONLY_MASK
from tests.sitl_mock.test_vehicle import ardupilot_airborne

LIMITS = {"max_h_mps": 10.0, "max_v_mps": 3.0, "accel_h_mps2": 2.5, "accel_v_mps2": 2.5}


def _world_to_ned(xyz: np.ndarray) -> tuple[float, float, float]:
    """The test's frame map: world x east, y north, z up; NED north, east, down."""
    return float(xyz[1]), float(xyz[0]), -float(xyz[2])


def test_the_world_flies_as_the_simulators_vehicle_period_by_period():
    assert ARDUPILOT is not None
    vehicle = ardupilot_airborne(20.0)
    previous = np.array([[0.0, 0.0, 20.0]])  # the target both start from
    result = vehicle.set_position_target_local(
        FRAME_LOCAL_NED, POSITION_ONLY_MASK, *_world_to_ned(previous[0]), 0, 0, 0, 0
    )
    assert result == "accepted", result
    for _ in range(500):
        vehicle.step(PHYSICS_DT_S)
    n, e, d = vehicle.position
    position = np.array([[e, n, -d]])
    velocity = np.array([[vehicle.velocity.e, vehicle.velocity.n, -vehicle.velocity.d]])
    latency_s = 0.1
    targets = [(60.0, 30.0, 35.0)] * 3 + [(-20.0, 50.0, 25.0)] * 2 + [(5.0, -40.0, 60.0)] * 6
    targets += [(5.0, -40.0, 21.0)] * 16  # down at 3 m/s, braking at 2.5 m/s²
    for target in targets:
        goal = np.array([target])
        for i in range(round(1.0 / PHYSICS_DT_S)):
            if i == round(latency_s / PHYSICS_DT_S):
                result = vehicle.set_position_target_local(
                    FRAME_LOCAL_NED, POSITION_ONLY_MASK, *_world_to_ned(goal[0]), 0, 0, 0, 0
                )
                assert result == "accepted", result
            vehicle.step(PHYSICS_DT_S)
        position, velocity = fly_accelerating(
            position, velocity, previous, goal, duration_s=1.0, latency_s=latency_s, **LIMITS
        )
        previous = goal
        n, e, d = vehicle.position
        assert position[0] == pytest.approx([e, n, -d], abs=1e-6)
        assert velocity[0] == pytest.approx(
            [vehicle.velocity.e, vehicle.velocity.n, -vehicle.velocity.d], abs=1e-6
        )
    # Both arrive (the sequence is flown, not only started).
    assert math.dist(position[0], (5.0, -40.0, 21.0)) < 1.0


def test_from_rest_the_vehicle_accelerates_over_several_periods():
    world = replace(CLOSED_LOOP, flight=Flight(10.0, 3.0, 2.5))
    position, velocity = np.array([[250.0, 250.0, 25.0]]), np.zeros((1, 3))
    target = np.array([[50.0, 250.0, 25.0]])
    moved = []
    for _ in range(6):
        before = position[0].copy()
        position, velocity = world.fly_period(position, velocity, target, target)
        moved.append(float(np.linalg.norm(position[0] - before)))
    # 2.5 m/s²: 1.25 m in the first second, then 2.5 m more each second until the 10 m/s cap.
    assert moved[0] == pytest.approx(1.25, abs=0.01)
    assert moved[1] == pytest.approx(3.75, abs=0.01)
    assert moved[5] == pytest.approx(10.0, abs=0.01)
    assert np.all(np.diff(moved) >= -1e-9)


def test_latency_keeps_the_vehicle_on_its_previous_target_for_that_long():
    flight = Flight(10.0, 3.0, latency_s=0.4)
    world = replace(CLOSED_LOOP, flight=flight)
    start = np.array([[100.0, 100.0, 50.0]])
    east, north = np.array([[200.0, 100.0, 50.0]]), np.array([[100.0, 200.0, 50.0]])
    flown, velocity = world.fly_period(start, np.zeros((1, 3)), east, north)
    # 0.4 s east at 10 m/s, then 0.6 s toward the new target: the capped flight, no inertia.
    turn_x, turn_y = 100.0 - 104.0, 200.0 - 100.0
    scale = 6.0 / math.hypot(turn_x, turn_y)
    assert flown[0] == pytest.approx([104.0 + turn_x * scale, 100.0 + turn_y * scale, 50.0])
    assert np.all(velocity == 0.0)


def test_without_acceleration_or_latency_the_period_is_the_capped_flight_exactly():
    world = CLOSED_LOOP
    rng = np.random.default_rng(4)
    positions = rng.uniform([0, 0, 25], [500, 500, 100], (20, 3))
    targets = rng.uniform([0, 0, 25], [500, 500, 100], (20, 3))
    flown, velocity = replace(world, flight=Flight(10.0, 3.0)).fly_period(
        positions, np.zeros((20, 3)), positions, targets
    )
    assert np.array_equal(flown, fly_many(positions, targets, Flight(10.0, 3.0), 1.0))
    assert not velocity.any()


@pytest.mark.parametrize(
    ("setting", "message"),
    [
        ("flight.accel_mps2=-1", "must be > 0"),
        ("flight.vertical_mps=none", "needs both speed caps"),
        ("flight.latency_s=-0.1", "must be >= 0"),
    ],
)
def test_bad_flight_settings_are_refused_naming_the_field(setting: str, message: str):
    with pytest.raises(InputError, match=message) as caught:
        world_with(get_world("closed-loop"), [setting])
    assert str(caught.value).startswith("world.flight.") or "flight." in str(caught.value)


def test_acceleration_needs_both_speed_caps():
    with pytest.raises(InputError, match="needs both speed caps"):
        Flight(None, 3.0, 2.5)


def _accelerating_world() -> World:
    return replace(CLOSED_LOOP, flight=Flight(10.0, 3.0, 2.5, 0.1), episode_steps=12)


def test_the_single_and_the_vector_environment_fly_the_same_accelerating_track():
    world = _accelerating_world()
    area = AreaConfig()
    scenarios = generate_scenarios(2, 3, seed=5, area=area)
    single = FapContinuousEnv(scenarios[:1], world=world)
    vector = FapVectorEnv(2, "continuous", scenarios[:1], world=world)
    start = np.array([250.0, 250.0, 25.0])
    single.reset(seed=1, options={"scenario": scenarios[0], "uav_xyz_m": start})
    vector.reset(seed=1, options={"scenarios": scenarios[:1] * 2, "uav_xyz_m": [start, start]})
    rng = np.random.default_rng(2)
    for _ in range(world.episode_steps - 1):  # the vector env resets itself at the last one
        action = rng.uniform(0, 1, 3)
        single.step(action)
        vector.step(np.stack([action, action]))
        assert vector.uav_xyz_m[0] == pytest.approx(single.uav_xyz_m, abs=1e-9)
        assert vector.uav_velocity_mps[1] == pytest.approx(single.uav_velocity_mps, abs=1e-9)
    assert np.linalg.norm(single.uav_velocity_mps) > 0.0
