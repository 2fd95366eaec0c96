"""The SB3 adapter over the vectorised environment: what SB3's agents expect of a VecEnv."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
from stable_baselines3.common.monitor import Monitor

from policies.learned.ddpg import IntervalTargetDDPG
from policies.learned.ddqn import MaskedDoubleDQN
from policies.training.vec_env import FapVecEnv, make_vec_env
from sim.scenarios import generate_scenarios
from sim.vector_env import FapVectorEnv
from sim.world import CLOSED_LOOP

SCENARIOS = generate_scenarios(6, 3, seed=5)
WORLD = replace(CLOSED_LOOP, episode_steps=4)


def test_steps_infos_and_episode_statistics_follow_sb3():
    env = make_vec_env("ddqn", SCENARIOS, WORLD, 3, seed=9)
    obs = env.reset()
    assert obs.shape == (3, *env.observation_space.shape)
    assert [info["action_mask"].tolist() for info in env.reset_infos] == (
        env.action_masks().tolist()
    )
    total = np.zeros(3)
    for step in range(1, 5):
        masks = np.stack(env.env_method("action_masks"))
        actions = np.array([np.flatnonzero(m)[-1] for m in masks])
        obs, rewards, dones, infos = env.step(actions)
        assert rewards.dtype == np.float32 and len(infos) == 3
        total += rewards
        assert dones.all() == (step == 4)
    for e, info in enumerate(infos):
        assert info["TimeLimit.truncated"]
        assert info["episode"]["l"] == 4 and info["episode"]["r"] == pytest.approx(total[e])
        assert info["terminal_observation"].shape == obs.shape[1:]
        assert not np.array_equal(info["terminal_observation"], obs[e])  # obs: the next episode
        assert np.array_equal(env.reset_infos[e]["action_mask"], env.action_masks()[e])
    assert len(env.episode_returns) == 3


def test_seed_attributes_and_methods():
    env = make_vec_env("ddpg", SCENARIOS, [WORLD], 2)
    env.seed(4)
    obs = env.reset()
    direct = FapVectorEnv(2, "continuous", SCENARIOS, WORLD)
    assert np.array_equal(obs, direct.reset(seed=4)[0])  # environment e seeded with 4 + e
    assert [s.id for s in env.get_attr("scenario")] == [s.id for s in SCENARIOS[:2]]
    assert np.array_equal(env.get_attr("uav_xyz_m", indices=1)[0], env.venv.uav_xyz_m[1])
    assert env.get_attr("kind") == ["continuous"] * 2
    assert env.env_is_wrapped(Monitor) == [True, True]
    assert not env.has_attr("action_masks")
    env.set_attr("model", env.venv.model)
    with pytest.raises(ValueError, match="set_attr"):
        env.set_attr("uav_xyz_m", np.zeros((2, 3)))
    assert env.scenarios is env.venv.scenarios
    with pytest.raises(ValueError, match="algorithm"):
        make_vec_env("ppo", SCENARIOS, WORLD, 2)
    env.close()


@pytest.mark.training
@pytest.mark.parametrize("algorithm", ["ddqn", "ddpg"])
def test_our_agents_learn_on_it(algorithm):
    env = make_vec_env(algorithm, SCENARIOS, WORLD, 4, seed=1)
    assert isinstance(env, FapVecEnv)
    agent_class = MaskedDoubleDQN if algorithm == "ddqn" else IntervalTargetDDPG
    model = agent_class(
        "MlpPolicy",
        env,
        learning_starts=50,
        buffer_size=400,
        batch_size=16,
        train_freq=4,
        seed=0,
        policy_kwargs={"net_arch": [16]},
    )
    model.learn(200)
    assert model.num_timesteps >= 200
    assert model._episode_num == len(env.episode_returns) >= 12
    if algorithm == "ddqn":  # the replay buffer stored each next state's valid moves
        stored = model.replay_buffer.next_action_masks[: model.replay_buffer.pos]
        assert stored[:, :, 0].all() and not stored.all()
