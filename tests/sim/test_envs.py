"""The Gymnasium environments and the observation builder."""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env
from hypothesis import given, settings
from hypothesis import strategies as st

from sim.config import AreaConfig
from sim.envs import (
    CONTINUOUS_ENV_ID,
    DISCRETE_ENV_ID,
    MOVES,
    FapContinuousEnv,
    FapDiscreteEnv,
    position_to_action,
)
from sim.flight import Flight
from sim.geometry import unit_to_m
from sim.observation import UserReports, build_observation
from sim.scenarios import Scenario, generate_scenarios
from sim.world import World

AREA = AreaConfig()
SCENARIOS = generate_scenarios(5, 3, seed=11)


@pytest.mark.parametrize("env_id", [DISCRETE_ENV_ID, CONTINUOUS_ENV_ID])
def test_registered_envs_pass_gymnasium_checks(env_id):
    env = gym.make(env_id)
    check_env(env.unwrapped, skip_render_check=True)
    obs, _ = env.reset(seed=1)
    assert env.observation_space.contains(obs)
    env.close()


def run_episode(env, seed, actions):
    obs, _ = env.reset(seed=seed)
    trace = [obs]
    rewards = []
    for a in actions:
        obs, reward, _, truncated, _ = env.step(a)
        trace.append(obs)
        rewards.append(reward)
    return np.array(trace), np.array(rewards), truncated


def test_same_seed_same_episode_and_other_seed_differs():
    actions = [1, 3, 5, 0, 7, 6, 8, 2, 4] * 11 + [0]
    a = run_episode(FapDiscreteEnv(SCENARIOS), 5, actions)
    b = run_episode(FapDiscreteEnv(SCENARIOS), 5, actions)
    c = run_episode(FapDiscreteEnv(SCENARIOS), 6, actions)
    np.testing.assert_array_equal(a[0], b[0])
    np.testing.assert_array_equal(a[1], b[1])
    assert not np.array_equal(a[1], c[1])


def test_episode_is_t_steps_with_utility_rewards():
    env = FapDiscreteEnv(SCENARIOS)
    _, rewards, truncated = run_episode(env, 0, [0] * 100)
    assert truncated
    assert rewards.shape == (100,)
    assert np.all((rewards >= 0) & (rewards <= 1))


def test_specialization_cycles_scenarios_in_order():
    env = FapContinuousEnv(SCENARIOS)
    seen = []
    for _ in range(7):
        _, info = env.reset(seed=0)
        seen.append(info["scenario_id"])
    assert seen == [s.id for s in SCENARIOS] + [SCENARIOS[0].id, SCENARIOS[1].id]


def test_generated_scenarios_differ_per_episode():
    env = FapDiscreteEnv(world=World(stochastic=False))
    env.reset(seed=3)
    users_a = env.scenario.users_xy_m.copy()
    env.reset()
    assert not np.array_equal(users_a, env.scenario.users_xy_m)


@settings(max_examples=40, deadline=None)
@given(seed=st.integers(0, 10_000), picks=st.lists(st.integers(0, 1000), min_size=30, max_size=30))
def test_masks_never_allow_leaving_the_volume(seed, picks):
    env = FapDiscreteEnv(SCENARIOS, World(stochastic=False, home="random"))
    _, info = env.reset(seed=seed)
    for pick in picks:
        mask = info["action_mask"]
        np.testing.assert_array_equal(mask, env.action_masks())
        assert mask[0]  # staying is always allowed
        valid = np.flatnonzero(mask)
        _, _, _, _, info = env.step(int(valid[pick % valid.size]))
        x, y, z = info["uav_xyz_m"]
        assert 0 <= x <= AREA.size_x_m and 0 <= y <= AREA.size_y_m
        assert AREA.z_min_m <= z <= AREA.z_max_m
    before = info["uav_xyz_m"]
    for a in np.flatnonzero(~env.action_masks()):
        _, _, _, _, info = env.step(int(a))
        assert info["refused_move"]
        np.testing.assert_array_equal(info["uav_xyz_m"], before)


def test_action_masks_before_reset_say_reset_first():
    """As Gymnasium's own order check does for ``step()``: the mask depends on where the
    episode starts, so asking for it before ``reset()`` is a clear error (Gymnasium's
    ``ResetNeeded``, also a ``RuntimeError``), not an ``AttributeError``."""
    env = gym.make(DISCRETE_ENV_ID)
    for error in (gym.error.ResetNeeded, RuntimeError):
        with pytest.raises(error, match=r"call reset\(\) first"):
            env.unwrapped.action_masks()
    env.reset(seed=0)
    mask = env.unwrapped.action_masks()
    assert mask.shape == (len(MOVES),) and mask.dtype == bool and mask[0]


def test_discrete_moves_go_where_they_say():
    env = FapDiscreteEnv(SCENARIOS, World(stochastic=False))
    _, info = env.reset(seed=0)
    start = info["uav_xyz_m"]
    _, _, _, _, info = env.step(7)  # east 5 zones
    np.testing.assert_allclose(info["uav_xyz_m"] - start, MOVES[7] * AREA.zone_m)


def test_bad_actions_raise_clear_errors():
    discrete = FapDiscreteEnv(SCENARIOS)
    discrete.reset(seed=0)
    for bad in (13, -1, 2.5, "up"):
        with pytest.raises(ValueError, match="action"):
            discrete.step(bad)
    continuous = FapContinuousEnv(SCENARIOS)
    continuous.reset(seed=0)
    for bad in ([1.2, 0.5, 0.5], [0.5, np.nan, 0.5], [0.1, 0.2], [-0.3, 0.0, 0.0]):
        with pytest.raises(ValueError, match="action"):
            continuous.step(np.array(bad))


def test_continuous_actions_map_onto_the_volume():
    for action in ([0, 0, 0], [1, 1, 1], [0.25, 0.5, 0.75]):
        xyz = unit_to_m(np.array(action, dtype=float), AREA)
        np.testing.assert_allclose(position_to_action(xyz, AREA), action, atol=1e-6)
    np.testing.assert_allclose(unit_to_m(np.array([1.0, 1.0, 1.0]), AREA), [500, 500, 100])


def test_speed_limit_makes_moves_take_time():
    env = FapContinuousEnv(SCENARIOS, World(stochastic=False, flight=Flight(10.0, None)))
    _, info = env.reset(seed=0, options={"uav_xyz_m": [0.0, 0.0, 25.0]})
    _, _, _, _, info = env.step(np.array([1.0, 0.0, 0.0], dtype=np.float32))
    np.testing.assert_allclose(info["uav_xyz_m"], [10.0, 0.0, 25.0])
    np.testing.assert_allclose(info["target_xyz_m"], [500.0, 0.0, 25.0])


def test_moving_towards_a_far_heavy_user_pays():
    """The environment rewards traffic-aware placement: near the heavy user beats the centre."""
    scenario = Scenario("s", np.array([[20.0, 20.0], [480.0, 480.0]]), np.array([38e6, 2e6]))
    env = FapContinuousEnv([scenario], World(stochastic=False))
    env.reset(seed=0)
    _, centre, *_ = env.step(position_to_action(np.array([250.0, 250.0, 25.0]), AREA))
    env.reset(seed=0)
    _, heavy, *_ = env.step(position_to_action(np.array([60.0, 60.0, 25.0]), AREA))
    assert heavy > centre + 0.1


def test_observation_maps():
    reports = UserReports(
        x_m=np.array([10.0, 12.0, 490.0]),
        y_m=np.array([10.0, 20.0, 260.0]),
        offered_bps=np.array([10e6, 10e6, 20e6]),
        throughput_bps=np.array([10e6, 5e6, 20e6]),
        delay_s=np.array([0.1, 0.3, 0.0]),
        plr=np.array([0.0, 0.5, 0.0]),
    )
    obs = build_observation(np.array([12.5, 12.5, 25.0]), reports, AREA)
    assert obs.shape == (6, 20, 20) and obs.dtype == np.float32
    assert obs.min() >= 0.0 and obs.max() <= 1.0
    assert np.unravel_index(np.argmin(obs[0]), obs[0].shape) == (0, 0)
    assert obs[1, 0, 0] == pytest.approx(1 - 2 / 3)  # two of three users in zone (0, 0)
    assert obs[1, 19, 10] == pytest.approx(1 - 1 / 3)
    assert obs[2, 19, 10] == pytest.approx(0.5)  # half the offered load
    assert obs[3, 0, 0] == pytest.approx(1 - 15 / 40)
    assert obs[4, 0, 0] == pytest.approx(1 - 0.2)  # mean delay 0.2 s over 1 s
    assert obs[5, 0, 0] == pytest.approx(0.75)
    empty = np.ones((20, 20), dtype=bool)
    empty[0, 0] = empty[19, 10] = False
    assert np.all(obs[1:, empty] == 1.0)


def test_env_observation_is_the_shared_builder():
    env = FapDiscreteEnv(SCENARIOS, World(stochastic=False))
    obs, info = env.reset(seed=0)
    s = env.scenario
    reports = UserReports(
        s.users_xy_m[:, 0],
        s.users_xy_m[:, 1],
        s.load_bps,
        info["throughput_bps"],
        info["delay_s"],
        info["plr"],
    )
    np.testing.assert_array_equal(obs, build_observation(info["uav_xyz_m"], reports, AREA))
