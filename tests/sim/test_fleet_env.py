"""The fleet's environments: PettingZoo's and Gymnasium's API checks, one UAV is the single
environment, the fleet maps, separation on every set of targets, registration, bad input."""

from __future__ import annotations

from dataclasses import replace

import gymnasium as gym
import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env
from pettingzoo.test import api_test, parallel_api_test
from pettingzoo.utils.conversions import parallel_to_aec

import sim.envs  # noqa: F401 (registers the environments)
from sim.envs import FapContinuousEnv, FapDiscreteEnv
from sim.errors import InputError
from sim.fleet import FleetConfig
from sim.fleet_env import (
    FLEET_MAPS,
    FleetGymEnv,
    FleetParallelEnv,
    fleet_maps,
    parallel_env,
)
from sim.scenarios import Scenario, ScenarioSampler
from sim.world import World, get_world

MOVING = replace(get_world("closed-loop-moving"), episode_steps=12)


@pytest.mark.parametrize("kind", ["discrete", "continuous"])
def test_parallel_api(kind: str) -> None:
    parallel_api_test(parallel_env(n_uavs=3, action_kind=kind, world=MOVING), num_cycles=20)


@pytest.mark.parametrize("kind", ["discrete", "continuous"])
def test_the_turn_based_view_passes_the_aec_api_test(kind: str) -> None:
    """PettingZoo's AEC conversion (what its wrappers and SuperSuit build on) works; its test
    samples moves with the info's action mask, which Gymnasium wants as int8."""
    env = parallel_env(n_uavs=2, action_kind=kind, world=MOVING)
    api_test(parallel_to_aec(env), num_cycles=20)
    if kind == "discrete":
        _, infos = env.reset(seed=0)
        assert all(info["action_mask"].dtype == np.int8 for info in infos.values())


@pytest.mark.parametrize("kind", ["discrete", "continuous"])
def test_gymnasium_wrapper_passes_check_env(kind: str) -> None:
    check_env(FleetGymEnv(2, kind, world=MOVING), skip_render_check=True)


def test_registered_with_gymnasium() -> None:
    env = gym.make("tupa/FleetDiscrete-v0", n_uavs=4, world=MOVING)
    observation, info = env.reset(seed=1)
    assert observation.shape == (4, FLEET_MAPS, 20, 20)
    assert env.action_space == gym.spaces.MultiDiscrete([13] * 4)
    assert info["action_mask"].shape == (4 * 13,)
    env = gym.make("tupa/FleetContinuous-v0", n_uavs=2, world=MOVING)
    assert env.action_space.shape == (2, 3)


@pytest.mark.parametrize(
    ("fleet_kind", "single_env"), [("discrete", FapDiscreteEnv), ("continuous", FapContinuousEnv)]
)
def test_one_uav_flies_as_the_single_environment(fleet_kind: str, single_env: type) -> None:
    """Same seed, same actions: the same rewards and the same six maps, bit for bit."""
    world = replace(get_world("closed-loop-moving"), episode_steps=15)
    assert_one_uav_flies_as_the_single_environment(
        fleet_kind, single_env, world, ScenarioSampler(families=("mixture",), users=(5, 30)), 15
    )


def assert_one_uav_flies_as_the_single_environment(
    fleet_kind: str, single_env: type, world: World, sampler: ScenarioSampler, steps: int
) -> None:
    """A fleet of one and the single environment, same seed, same random actions for ``steps``
    steps: the same rewards, truncations, six maps and UAV positions, bit for bit; the fleet's
    agent gone at the end of the episode."""
    fleet = FleetParallelEnv(1, fleet_kind, scenarios=sampler, world=world)
    single = single_env(sampler, world=world)
    obs_f, _ = fleet.reset(seed=11)
    obs_s, _ = single.reset(seed=11)
    np.testing.assert_array_equal(obs_f["uav_0"][:6], obs_s)
    rng = np.random.default_rng(0)
    for _ in range(steps):
        if fleet_kind == "discrete":
            action = int(rng.integers(0, 13))
        else:
            action = rng.uniform(0, 1, 3).astype(np.float32)
        obs_f, rewards, _, truncations, infos = fleet.step({"uav_0": action})
        obs_s, reward, _, truncated, info = single.step(action)
        assert rewards["uav_0"] == reward
        np.testing.assert_array_equal(infos["uav_0"]["uav_xyz_m"], info["uav_xyz_m"])
        np.testing.assert_array_equal(obs_f["uav_0"][:6], obs_s)
        assert truncations["uav_0"] == truncated
    assert fleet.agents == []


def test_fleet_maps_show_the_other_uavs_and_who_serves_whom() -> None:
    world = get_world("paper")
    uavs = np.array([[12.5, 12.5, 25.0], [112.5, 12.5, 25.0], [112.5, 12.5, 50.0]])
    users = np.array([[10.0, 10.0], [15.0, 20.0], [110.0, 10.0], [300.0, 300.0]])
    association = np.array([0, 1, 1, 2])
    maps = fleet_maps(uavs, users, association, world)
    assert maps.shape == (3, 3, 20, 20) and maps.dtype == np.float32
    # Agent 0: the two others share zone (4, 0); nobody else is in its own zone.
    assert maps[0, 0, 4, 0] == pytest.approx(0.0) and maps[0, 0, 0, 0] == 1.0
    # Agent 1: agent 2 in its zone (1 of 2 others), agent 0 at (0, 0).
    assert maps[1, 0, 4, 0] == pytest.approx(0.5) and maps[1, 0, 0, 0] == pytest.approx(0.5)
    # Zone (0, 0): user 0 served by 0, user 1 by 1 (both in zone (0, 0)).
    assert maps[0, 1, 0, 0] == pytest.approx(0.75) and maps[0, 2, 0, 0] == pytest.approx(0.75)
    assert maps[1, 1, 0, 0] == pytest.approx(0.75) and maps[1, 2, 0, 0] == pytest.approx(0.75)
    assert maps[2, 1, 12, 12] == pytest.approx(0.75) and maps[0, 2, 12, 12] == pytest.approx(0.75)
    assert maps[2, 1, 0, 0] == 1.0 and maps[2, 2, 0, 0] == pytest.approx(0.5)


def test_targets_are_separated_and_vehicles_never_come_too_close() -> None:
    scenario = Scenario("one", np.array([[250.0, 250.0], [260.0, 250.0]]), np.array([1e6, 1e6]))
    world = replace(get_world("closed-loop"), episode_steps=30)
    env = FleetParallelEnv(3, "continuous", scenarios=[scenario], world=world)
    env.reset(seed=0)
    same = np.array([0.5, 0.5, 0.0], dtype=np.float32)  # all three want the same point
    for _ in range(30):
        _, _, _, _, infos = env.step(dict.fromkeys(env.agents, same))
        targets = np.stack([infos[a]["target_xyz_m"] for a in env.possible_agents])
        for points in (targets, env.uav_xyz_m):
            gap = points[:, None] - points[None]
            distance = np.sqrt((gap**2).sum(-1)) + np.diag(np.full(3, np.inf))
            assert distance.min() >= 10.0 * (1 - 1e-12)
    assert np.allclose(env.uav_xyz_m, targets)  # they got there, apart


def test_starts_are_separated_and_zone_points_for_moves() -> None:
    env = FleetParallelEnv(8, "discrete", world=MOVING)
    env.reset(seed=3)
    xy = env.uav_xyz_m[:, :2]
    assert np.all((xy / 25.0) % 1.0 == 0.5)  # zone centres
    assert len({tuple(p) for p in env.uav_xyz_m}) == 8


def test_fleet_infos_carry_the_fleet_metrics() -> None:
    env = FleetParallelEnv(2, "discrete", world=MOVING)
    _, infos = env.reset(seed=5)
    for key in (
        "utility",
        "uav_utility",
        "served_fraction",
        "jain_fairness",
        "min_throughput_bps",
        "handovers",
        "action_mask",
    ):
        assert key in infos["uav_0"]
    assert infos["uav_0"]["utility"] == infos["uav_1"]["utility"]
    assert infos["uav_0"]["users_served"] + infos["uav_1"]["users_served"] == len(
        env.users.load_bps
    )


def test_bad_input() -> None:
    with pytest.raises(InputError, match=r"^n_uavs: must be an integer in 1\.\.8"):
        FleetParallelEnv(9)
    with pytest.raises(InputError, match=r"^n_uavs:"):
        FleetParallelEnv(0)
    with pytest.raises(InputError, match=r"^separation_m:"):
        FleetParallelEnv(2, fleet=FleetConfig(n_uavs=2, separation_m=0.0))
    with pytest.raises(InputError, match=r"^n_uavs: 3 disagrees with the fleet's 2"):
        FleetParallelEnv(3, fleet=FleetConfig(n_uavs=2))
    assert FleetParallelEnv(fleet=FleetConfig(n_uavs=5)).n_uavs == 5
    with pytest.raises(InputError, match=r"^action_kind:"):
        FleetParallelEnv(2, "teleport")
    env = FleetParallelEnv(2, "discrete", world=MOVING)
    env.reset(seed=0)
    with pytest.raises(ValueError, match="actions: no action for uav_1"):
        env.step({"uav_0": 0})
    with pytest.raises(ValueError, match="action: must be an integer"):
        env.step({"uav_0": 0, "uav_1": 13})


def test_a_fleet_draws_each_episodes_world_from_a_list_as_the_single_environment_does() -> None:
    """Worlds that differ in their channel environment: each episode runs in one of them, with
    that environment's fleet model and, from a source by environment, that environment's
    scenarios; the single environment draws the same worlds from the same seeds."""
    from sim.envs import ScenarioCycle, ScenariosByEnvironment
    from sim.world import world_with

    worlds = [world_with(MOVING, {"environment": e}) for e in ("open", "urban")]
    area = worlds[0].area
    scenarios = {
        e: Scenario(f"{e}-users", np.array([[50.0 + i, 60.0]]), np.array([1e6 * (i + 1)]))
        for i, e in enumerate(("open", "urban"))
    }
    source = ScenariosByEnvironment({e: ScenarioCycle([s]) for e, s in scenarios.items()})
    fleet = FleetParallelEnv(n_uavs=2, action_kind="continuous", scenarios=source, world=worlds)
    single = FapContinuousEnv(scenarios=source, world=worlds)
    seen = []
    for seed in range(12):
        fleet.reset(seed=seed)
        single.reset(seed=seed)
        environment = fleet.world.area.environment
        assert single.world.area.environment == environment
        assert fleet.model.area.environment == environment
        assert fleet.scenario is scenarios[environment]
        assert fleet.area.size_x_m == area.size_x_m
        seen.append(environment)
    assert set(seen) == {"open", "urban"}


def test_a_fleets_worlds_must_share_the_area_and_be_some() -> None:
    with pytest.raises(ValueError, match=r"^world: the list of worlds is empty"):
        FleetParallelEnv(n_uavs=2, world=[])
    larger = replace(MOVING, area=replace(MOVING.area, size_x_m=MOVING.area.size_x_m * 2))
    with pytest.raises(ValueError, match=r"^world: the worlds of one environment must share"):
        FleetParallelEnv(n_uavs=2, world=[MOVING, larger])
