"""The vectorised environment: the single environment's episodes, as one batch."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
from gymnasium.vector import AutoresetMode
from gymnasium.wrappers.vector import RecordEpisodeStatistics

from sim.config import AreaConfig
from sim.envs import FapContinuousEnv, FapDiscreteEnv
from sim.flight import Flight, fly, fly_many
from sim.geometry import (
    MOVES,
    move_target,
    move_targets,
    unit_to_m,
    unit_to_m_many,
    valid_moves,
    valid_moves_many,
    zone_index,
    zone_indices,
    zone_position,
    zone_positions,
)
from sim.scenarios import ScenarioSampler, generate_scenarios
from sim.vector_env import FapVectorEnv
from sim.world import CLOSED_LOOP, CLOSED_LOOP_MOVING, PAPER, ReportModel

AREA = AreaConfig()
SCENARIOS = generate_scenarios(5, 3, seed=11)
SINGLE = {"discrete": FapDiscreteEnv, "continuous": FapContinuousEnv}


def volume_points(rng: np.random.Generator, n: int) -> np.ndarray:
    """Points of the volume, a third of them on zone edges and levels, some on its faces."""
    low, high = [0.0, 0.0, AREA.z_min_m], [AREA.size_x_m, AREA.size_y_m, AREA.z_max_m]
    points = rng.uniform(low, high, (n, 3))
    edges = rng.integers(0, 21, (n // 3, 3)) * AREA.zone_m
    points[: n // 3] = np.clip(edges + np.array([0.0, 0.0, AREA.z_min_m]), low, high)
    points[n // 3 : n // 3 + 20] = rng.choice([low, high], 20)  # corners
    return points


def test_batched_targets_and_flight_equal_the_scalar_functions():
    rng = np.random.default_rng(0)
    here, there = volume_points(rng, 3000), volume_points(rng, 3000)
    index = zone_indices(here, AREA)
    assert np.array_equal(index, [zone_index(p, AREA) for p in here])
    assert np.array_equal(zone_positions(index, AREA), [zone_position(i, AREA) for i in index])
    assert np.array_equal(valid_moves_many(here, AREA), [valid_moves(p, AREA) for p in here])
    moves = rng.integers(0, len(MOVES), len(here))
    targets, refused = move_targets(moves, here, AREA)
    scalar = [move_target(int(m), p, AREA) for m, p in zip(moves, here, strict=True)]
    assert np.array_equal(targets, [t for t, _ in scalar])
    assert np.array_equal(refused, [r for _, r in scalar])
    assert refused.any() and not refused.all()
    for rows in (1, 3, 8):  # a fleet's few rows take the scalar path: the same numbers
        few, few_moves = here[:rows], moves[:rows]
        assert np.array_equal(zone_indices(few, AREA), index[:rows])
        few_targets, few_refused = move_targets(few_moves, few, AREA)
        assert np.array_equal(few_targets, targets[:rows])
        assert np.array_equal(few_refused, refused[:rows])
    edge = np.array([[np.nan, 1.0, 30.0], [1e300, -1e300, np.inf]])  # the array way's clipping
    with np.errstate(invalid="ignore"):  # numpy's cast of nan and inf, clipped afterwards
        assert np.array_equal(zone_indices(edge, AREA), [zone_index(p, AREA) for p in edge])
    actions = rng.uniform(-0.2, 1.2, (len(here), 3))
    coords = unit_to_m_many(actions, AREA)
    assert np.array_equal(coords, [unit_to_m(a, AREA) for a in actions])
    for flight in (Flight(10.0, 3.0), Flight(None, None), Flight(None, 3.0), Flight(4.0, None)):
        for goal in (there, coords, targets):
            flown = fly_many(here, goal, flight, 1.5)
            assert np.array_equal(
                flown, [fly(p, g, flight, 1.5) for p, g in zip(here, goal, strict=True)]
            ), flight
            for rows in (1, 3, 8):  # a fleet's few rows take the scalar path: the same floats
                assert np.array_equal(fly_many(here[:rows], goal[:rows], flight, 1.5), flown[:rows])


def run_both(kind, world, scenarios, n_envs, steps, seed, options=None, single_scenarios=None):
    """Step a vector env and one single env per environment with the same actions; compare
    rewards, observations, truncations and the final observations, across autoresets."""
    vector = FapVectorEnv(n_envs, kind, scenarios, world)
    single_scenarios = single_scenarios or [scenarios] * n_envs
    singles = [SINGLE[kind](single_scenarios[e], world) for e in range(n_envs)]
    obs, info = vector.reset(seed=seed, options=options)
    for e, single in enumerate(singles):
        single_options = None
        if options:
            single_options = {"scenario": options["scenarios"][e]}
            single_options["users_seed"] = options["users_seeds"][e]
        single_obs, single_info = single.reset(seed=seed + e, options=single_options)
        assert np.array_equal(obs[e], single_obs)
        assert info["scenario_id"][e] == single_info["scenario_id"]
    rng = np.random.default_rng(seed)
    ends = 0
    for _ in range(steps):
        if kind == "discrete":
            actions = rng.integers(0, len(MOVES), n_envs)  # some refused
        else:
            actions = rng.uniform(0.0, 1.0, (n_envs, 3)).astype(np.float32)
        obs, rewards, terminated, truncated, info = vector.step(actions)
        assert not terminated.any()
        for e, single in enumerate(singles):
            single_obs, reward, _, single_truncated, single_info = single.step(actions[e])
            assert reward == rewards[e]
            assert single_truncated == truncated[e]
            np.testing.assert_array_equal(single_info["uav_xyz_m"], info_row(info, "uav_xyz_m", e))
            if single_truncated:
                assert np.array_equal(info["final_obs"][e], single_obs)
                single_obs, single_info = single.reset()
                assert info["scenario_id"][e] == single_info["scenario_id"]
            assert np.array_equal(obs[e], single_obs)
            if kind == "discrete":
                assert np.array_equal(info["action_mask"][e], single_info["action_mask"])
                assert np.array_equal(vector.action_masks()[e], single.action_masks())
        ends += int(truncated[0])
    assert ends >= 1  # the comparison went through an autoreset
    return vector


def info_row(info, key, e):
    """Row e of a batched info key, from the final step's info when episodes just ended."""
    return info.get("final_info", info)[key][e]


WORLDS = {
    "paper": PAPER,
    "closed-loop": CLOSED_LOOP,
    "closed-loop-moving": CLOSED_LOOP_MOVING,
    # Random homes, an older report and noisy positions draw from each environment's generator.
    "noisy-random-home": replace(
        CLOSED_LOOP_MOVING, home="random", reports=ReportModel(age_steps=2, position_noise_m=5.0)
    ),
}


@pytest.mark.parametrize("kind", ["discrete", "continuous"])
@pytest.mark.parametrize("world_name", list(WORLDS))
def test_expected_mode_equals_the_single_env_per_environment(kind, world_name):
    world = replace(WORLDS[world_name], stochastic=False, episode_steps=6)
    sampler = ScenarioSampler(users=(2, 4))  # user counts differ: several step_many groups
    vector = run_both(kind, world, sampler, 5, 14, seed=7)
    assert len(vector._groups) > 1


@pytest.mark.parametrize("kind", ["discrete", "continuous"])
def test_given_scenarios_and_users_seeds_align_with_the_single_env(kind):
    world = replace(CLOSED_LOOP_MOVING, stochastic=False, episode_steps=4)
    options = {"scenarios": SCENARIOS[:3], "users_seeds": [5, 6, 7]}
    # After the given ones, environment e takes the e-th scenario of each round of the list.
    rounds = [[SCENARIOS[(e + 3 * k) % 5] for k in range(5)] for e in range(3)]
    run_both(kind, world, SCENARIOS, 3, 9, seed=2, options=options, single_scenarios=rounds)


def test_a_list_of_scenarios_is_cycled_across_environments_and_episodes():
    world = replace(PAPER, stochastic=False, episode_steps=2)
    vector = FapVectorEnv(3, "continuous", SCENARIOS, world)
    _, info = vector.reset(seed=0)
    assert list(info["scenario_id"]) == [s.id for s in SCENARIOS[:3]]
    actions = np.full((3, 3), 0.5)
    vector.step(actions)
    _, _, _, truncated, info = vector.step(actions)
    assert truncated.all()
    assert list(info["scenario_id"]) == [s.id for s in (*SCENARIOS[3:], SCENARIOS[0])]
    assert list(info["final_info"]["scenario_id"]) == [s.id for s in SCENARIOS[:3]]


def test_masks_refusals_and_spaces():
    world = replace(CLOSED_LOOP, home="random", stochastic=False)
    vector = FapVectorEnv(8, "discrete", SCENARIOS, world)
    obs, info = vector.reset(seed=3)
    assert vector.observation_space.contains(obs)
    assert vector.single_observation_space.shape == obs.shape[1:]
    assert vector.action_space.shape == (8,) and vector.single_action_space.n == len(MOVES)
    rng = np.random.default_rng(1)
    for _ in range(20):
        masks = vector.action_masks()
        assert np.array_equal(masks, info["action_mask"])
        assert np.array_equal(masks, valid_moves_many(vector.uav_xyz_m, AREA))
        assert masks[:, 0].all()
        actions = rng.integers(0, len(MOVES), 8)
        before = vector.uav_xyz_m.copy()
        obs, _, _, _, info = vector.step(actions)
        assert vector.observation_space.contains(obs)
        refused = ~masks[np.arange(8), actions]
        assert np.array_equal(info["refused_move"], refused)
        zones = zone_positions(zone_indices(before, AREA), AREA)
        assert np.array_equal(info["target_xyz_m"][refused], zones[refused])
    continuous = FapVectorEnv(2, "continuous", SCENARIOS)
    assert continuous.action_space.shape == (2, 3)
    with pytest.raises(AttributeError, match="action_masks"):
        continuous.action_masks()


def test_autoreset_is_same_step_and_gymnasium_wrappers_count_episodes():
    world = replace(CLOSED_LOOP, episode_steps=3)
    vector = FapVectorEnv(4, "discrete", SCENARIOS, world)
    assert vector.metadata["autoreset_mode"] is AutoresetMode.SAME_STEP
    env = RecordEpisodeStatistics(vector)
    env.reset(seed=0)
    total = np.zeros(4)
    for step in range(1, 7):
        obs, rewards, terminated, truncated, info = env.step(np.zeros(4, dtype=np.int64))
        total += rewards
        assert not terminated.any()
        assert truncated.all() == (step % 3 == 0)
        if step % 3:
            assert "final_obs" not in info
            continue
        assert info["_final_obs"].all() and info["_final_info"].all()
        assert all(o.shape == obs.shape[1:] for o in info["final_obs"])
        assert not np.array_equal(np.stack(info["final_obs"]), obs)  # obs: the new episodes'
        assert info["final_info"]["_action_mask"].all()
        assert np.allclose(info["episode"]["r"], total) and (info["episode"]["l"] == 3).all()
        total[:] = 0.0
    assert vector._steps == 0


def test_stochastic_seeds_reproduce():
    def rewards(seed):
        vector = FapVectorEnv(3, "discrete", SCENARIOS, replace(CLOSED_LOOP, episode_steps=5))
        vector.reset(seed=seed)
        return np.array([vector.step(np.full(3, 1))[1] for _ in range(6)])

    assert np.array_equal(rewards(4), rewards(4))
    assert not np.array_equal(rewards(4), rewards(5))


def test_bad_actions_and_arguments_raise_one_line_errors():
    discrete = FapVectorEnv(3, "discrete", SCENARIOS)
    with pytest.raises(RuntimeError, match="reset"):
        discrete.step(np.zeros(3, dtype=np.int64))
    discrete.reset(seed=0)
    bad_moves = [[0, 1, 13], [0, -1, 2], [0.0, 1.0, 2.0], [True, False, True], [0, 1], "up"]
    for bad in [*bad_moves, np.zeros((3, 13), dtype=np.int64)]:
        with pytest.raises(ValueError, match=r"^action: ") as caught:
            discrete.step(np.asarray(bad) if not isinstance(bad, str) else bad)
        assert "\n" not in str(caught.value)
    continuous = FapVectorEnv(2, "continuous", SCENARIOS)
    continuous.reset(seed=0)
    for bad in (
        [[0.5, 0.5, 0.5]],
        [[0.5, 0.5, np.nan]] * 2,
        [[0, 0, 1.5]] * 2,
        "up",
        [[0.5] * 2] * 2,
    ):
        with pytest.raises(ValueError, match=r"^action: ") as caught:
            continuous.step(bad)
        assert "\n" not in str(caught.value)
    for args, name in (((0,), "num_envs"), ((2, "grid"), "kind")):
        with pytest.raises(ValueError, match=name):
            FapVectorEnv(*args)
    with pytest.raises(ValueError, match="world"):
        FapVectorEnv(2, world=[PAPER, CLOSED_LOOP])
    with pytest.raises(ValueError, match="users_seeds"):
        discrete.reset(options={"users_seeds": [1]})
