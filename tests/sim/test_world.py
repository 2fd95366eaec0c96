"""The world: presets, settings from the command line, flight, the move rule, users in motion."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from sim.config import AreaConfig
from sim.envs import FapContinuousEnv, FapDiscreteEnv
from sim.errors import InputError
from sim.flight import Flight, fly
from sim.geometry import MOVES, move_target, valid_moves, zone_index, zone_position
from sim.observation import build_observation
from sim.scenarios import Scenario, generate_scenarios
from sim.users import UserDynamics
from sim.world import PAPER, Demand, Mobility, World, get_world, world_with

AREA = AreaConfig()


def test_presets() -> None:
    paper, loop, moving = (get_world(n) for n in ("paper", "closed-loop", "closed-loop-moving"))
    assert paper.flight.teleports and paper.reports.age_steps == 0 and not paper.users_change
    assert paper.static_start == "placement"
    # The loop's autopilot: speed caps, 2.5 m/s² both ways, a decision 0.05 s on the way.
    assert loop.flight == Flight(10.0, 3.0, 2.5, 0.05)
    assert loop.reports.age_steps == 0 and loop.static_start == "home" and not loop.users_change
    assert moving.users_change and moving.mobility.model == "random-waypoint"
    with pytest.raises(InputError, match="world: must be one of paper, closed-loop"):
        get_world("mars")


def test_settings_parse_and_bad_ones_name_the_field() -> None:
    world = world_with(
        get_world("closed-loop"),
        [
            "flight.accel_mps2=none",
            "flight.latency_s=0",
            "flight.horizontal_mps=5",
            "flight.vertical_mps=none",
            "mobility.model=group",
            "mobility.speed_mps=5,15",
            "reports.age_steps=2",
            "home=100,200,50",
            "stochastic=false",
        ],
    )
    assert world.name == "closed-loop*"
    assert world.flight == Flight(5.0, None)
    assert world.mobility.model == "group" and world.mobility.speed_mps == (5.0, 15.0)
    assert world.reports.age_steps == 2 and world.home == (100.0, 200.0, 50.0)
    assert world.stochastic is False
    bad = {
        "flight.horizontal_mps=0": "flight.horizontal_mps: must be > 0",
        "flight.horizontal_mps=-3": "flight.horizontal_mps: must be > 0",
        "flight.speed=3": "world.flight.speed: unknown setting",
        "colour=red": "world.colour: unknown setting",
        "mobility.model=teleport": "mobility.model: must be one of",
        "mobility.speed_mps=3": "world.mobility.speed_mps: cannot read",
        "reports.age_steps=-1": "reports.age_steps",
        "home=900,0,25": "home: ",
        "step_s=0": "step_s: must be > 0",
        "demand.step_rate_per_s=x": "world.demand.step_rate_per_s: cannot read",
        "novalue": "expected key=value",
    }
    for setting, message in bad.items():
        with pytest.raises(InputError, match=message.replace("*", r"\*")):
            world_with(PAPER, [setting])


def test_flight_caps_horizontal_and_vertical_speed_separately() -> None:
    flight = Flight(10.0, 3.0)
    np.testing.assert_allclose(fly([0, 0, 25], [100, 0, 100], flight, 1.0), [10, 0, 28])
    np.testing.assert_allclose(fly([0, 0, 25], [3, 4, 26], flight, 1.0), [3, 4, 26])
    np.testing.assert_allclose(fly([0, 0, 25], [300, 400, 25], flight, 2.0), [12, 16, 25])
    np.testing.assert_allclose(
        fly([0, 0, 25], [300, 400, 90], Flight(None, None), 1.0), [300, 400, 90]
    )


@settings(max_examples=60, deadline=None)
@given(
    start=st.tuples(st.floats(0, 500), st.floats(0, 500), st.floats(25, 100)),
    target=st.tuples(st.floats(0, 500), st.floats(0, 500), st.floats(25, 100)),
)
def test_flight_never_overshoots_and_never_exceeds_the_limits(start, target) -> None:
    after = fly(np.array(start), np.array(target), Flight(10.0, 3.0), 1.0)
    assert np.hypot(*(after[:2] - start[:2])) <= 10.0 + 1e-9
    assert abs(after[2] - start[2]) <= 3.0 + 1e-9
    gap_before = np.abs(np.array(target) - np.array(start))
    assert np.all(np.abs(np.array(target) - after) <= gap_before + 1e-9)


def test_moves_apply_to_the_zone_the_vehicle_is_in() -> None:
    vehicle = np.array([262.0, 240.0, 31.0])  # zone (10, 9), level 0, between zone centres
    index = zone_index(vehicle, AREA)
    mask = valid_moves(vehicle, AREA)
    assert mask.sum() == 10  # lowest of four levels: not down 1, down 5 or up 5
    for move in range(len(MOVES)):
        target, refused = move_target(move, vehicle, AREA)
        assert refused == (not mask[move])
        landing = index + MOVES[move] if mask[move] else index
        np.testing.assert_array_equal(target, zone_position(landing, AREA))
    corner = np.array([5.0, 5.0, 25.0])
    mask = valid_moves(corner, AREA)
    assert mask[0] and not mask[2] and not mask[6]  # stay; not west, not down
    target, refused = move_target(2, corner, AREA)
    assert refused and np.array_equal(target, zone_position(np.array([0, 0, 0]), AREA))


def test_a_vehicle_that_keeps_moving_east_flies_east_at_full_speed() -> None:
    world = replace(get_world("closed-loop"), flight=Flight(10.0, 3.0))  # no acceleration limit
    env = FapDiscreteEnv(generate_scenarios(2, 3, seed=1), world=world)
    _, info = env.reset(seed=0, options={"uav_xyz_m": [12.5, 250.0, 25.0]})
    start = info["uav_xyz_m"]
    for _ in range(10):
        _, _, _, _, info = env.step(1)  # east 1, every step
    np.testing.assert_allclose(info["uav_xyz_m"] - start, [100.0, 0.0, 0.0])


def test_an_accelerating_vehicle_that_keeps_moving_east_speeds_up_and_keeps_going() -> None:
    """With the loop's acceleration a move one zone on each period speeds up by about 2.5 m/s a
    period and then keeps going east, braking for a target never more than two zones ahead."""
    env = FapDiscreteEnv(generate_scenarios(2, 3, seed=1), world=get_world("closed-loop"))
    _, info = env.reset(seed=0, options={"uav_xyz_m": [12.5, 250.0, 25.0]})
    start = info["uav_xyz_m"]
    east = [float(start[0])]
    for _ in range(14):
        _, _, _, _, info = env.step(1)  # east 1, every step
        east.append(float(info["uav_xyz_m"][0]))
        assert info["uav_xyz_m"][1:] == pytest.approx(start[1:])
    steps = np.diff(east)
    assert steps[0] < 1.25  # from rest at 2.5 m/s², the first 0.05 s still holding
    np.testing.assert_allclose(np.diff(steps[:3]), 2.5, atol=0.01)
    assert np.all(steps <= 10.0 + 1e-9) and np.mean(steps[-8:]) > 7.0


def test_the_closed_loop_decision_sees_the_report_of_the_period_that_just_ended() -> None:
    scenarios = generate_scenarios(2, 3, seed=2)
    env = FapContinuousEnv(scenarios, world=replace(get_world("closed-loop"), stochastic=False))
    _, first = env.reset(seed=0)
    observation, _, _, _, info = env.step(np.array([1.0, 1.0, 0.0], dtype=np.float32))
    np.testing.assert_array_equal(info["reports"].delay_s, info["delay_s"])
    assert not np.array_equal(info["delay_s"], first["delay_s"])
    np.testing.assert_array_equal(
        observation, build_observation(info["uav_xyz_m"], info["reports"], AREA)
    )


def test_an_older_report_is_shown_when_the_world_says_so() -> None:
    scenarios = generate_scenarios(2, 3, seed=2)
    world = world_with(replace(get_world("closed-loop"), stochastic=False), ["reports.age_steps=1"])
    env = FapContinuousEnv(scenarios, world=world)
    _, first = env.reset(seed=0)
    observation, _, _, _, info = env.step(np.array([1.0, 1.0, 0.0], dtype=np.float32))
    # The report shown is the reset step's (its delays at the start position), while the
    # distance map is built where the vehicle is now.
    np.testing.assert_array_equal(info["reports"].delay_s, first["delay_s"])
    assert not np.array_equal(info["delay_s"], first["delay_s"])
    np.testing.assert_array_equal(
        observation, build_observation(info["uav_xyz_m"], info["reports"], AREA)
    )


def test_every_policy_meets_the_same_users() -> None:
    """User motion and demand do not depend on what the vehicle does."""
    world = get_world("closed-loop-moving")
    scenario = generate_scenarios(1, 6, seed=3)[0]
    tracks = []
    for action in ([0.0, 0.0, 0.0], [1.0, 1.0, 1.0]):
        env = FapContinuousEnv([scenario], world=world)
        env.reset(seed=5)
        users = [env.step(np.array(action, dtype=np.float32))[4]["users_xy_m"] for _ in range(30)]
        tracks.append(np.array(users))
    np.testing.assert_array_equal(tracks[0], tracks[1])
    assert np.ptp(tracks[0], axis=0).max() > 5.0  # they did walk


@pytest.mark.parametrize("model", ["random-waypoint", "group"])
def test_walking_users_stay_inside_and_keep_their_speed(model: str) -> None:
    rng = np.random.default_rng(1)
    xy = rng.uniform(0, 500, (8, 2))
    mobility = Mobility(model=model, speed_mps=(1.0, 2.0), pause_s=(0.0, 2.0))
    users = UserDynamics(xy, np.full(8, 5e6), mobility, Demand(), AREA, rng)
    previous = users.xy_m.copy()
    for _ in range(300):
        users.advance(1.0, rng)
        assert np.all((users.xy_m >= 0) & (users.xy_m <= 500))
        assert np.all(np.hypot(*(users.xy_m - previous).T) <= 2.0 + 1e-9)
        previous = users.xy_m.copy()
    if model == "group":  # offsets kept while nobody hits the edge: spread stays bounded
        assert np.ptp(users.xy_m, axis=0).max() <= np.ptp(xy, axis=0).max() + 1e-9


def test_demand_steps_and_quiet_users_come_back() -> None:
    rng = np.random.default_rng(2)
    base = np.array([10e6, 20e6, 10e6])
    demand = Demand(step_rate_per_s=0.2, quiet_rate_per_s=0.2, quiet_s=(2.0, 4.0))
    users = UserDynamics(np.full((3, 2), 100.0), base, Mobility(), demand, AREA, rng)
    seen_quiet = seen_changed = False
    for _ in range(200):
        users.advance(1.0, rng)
        load = users.load_bps
        assert np.count_nonzero(load) >= 1  # someone always talks
        active = load > 0
        ratio = load[active] / base[active]
        assert np.all((ratio >= 0.25 - 1e-9) & (ratio <= 4.0 + 1e-9))
        seen_quiet |= bool(np.any(~active))
        seen_changed |= bool(np.any(np.abs(ratio - 1) > 1e-6))
    assert seen_quiet and seen_changed
    assert np.count_nonzero(users.load_bps) >= 1


def test_static_users_draw_nothing() -> None:
    """With static users the users never touch a generator: the paper's episodes keep their
    random streams (fading only), and an episode repeats exactly from its seed."""
    scenario = Scenario("s", np.array([[50.0, 60.0], [400.0, 300.0]]), np.array([30e6, 10e6]))
    rng = np.random.default_rng(9)
    state = rng.bit_generator.state
    users = UserDynamics(scenario.users_xy_m, scenario.load_bps, Mobility(), Demand(), AREA, rng)
    users.advance(1.0, rng)
    assert rng.bit_generator.state == state
    env = FapDiscreteEnv([scenario], world=World())
    env.reset(seed=4)
    rewards = [env.step(1)[1] for _ in range(5)]
    env2 = FapDiscreteEnv([scenario], world=World())
    env2.reset(seed=4)
    assert rewards == [env2.step(1)[1] for _ in range(5)]
