"""The shipped checkpoints (policies/checkpoints/) load and act validly in their environment."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from policies.agents import TrainedAgent
from sim.config import AreaConfig
from sim.envs import FapContinuousEnv, FapDiscreteEnv
from sim.scenarios import generate_scenarios

SHIPPED = Path(__file__).resolve().parents[2] / "policies" / "checkpoints"
AREA = AreaConfig()


@pytest.mark.parametrize("name", ["ddqn-gen10k", "ddpg-gen10k"])
def test_shipped_checkpoint_has_its_metadata(name: str) -> None:
    assert (SHIPPED / f"{name}.zip").is_file()
    agent = TrainedAgent.load(SHIPPED / f"{name}.zip", AREA, device="cpu")
    assert agent.name == name
    assert agent.metadata["algorithm"] == name.split("-")[0]
    assert agent.metadata["strategy"] == "gen10k"
    assert agent.metadata["n_users"] == 3
    assert agent.metadata["wall_time_s"] > 0


def test_shipped_checkpoints_are_small_and_hold_no_replay_buffer() -> None:
    zips = sorted(SHIPPED.glob("*.zip"))
    assert sum(p.stat().st_size for p in zips) < 20 * 1024 * 1024
    assert not list(SHIPPED.glob("*replay*"))


def test_shipped_ddqn_picks_only_valid_moves() -> None:
    agent = TrainedAgent.load(SHIPPED / "ddqn-gen10k.zip", AREA, device="cpu")
    env = FapDiscreteEnv(generate_scenarios(3, 3, seed=7, area=AREA))
    for episode in range(3):
        obs, info = env.reset(seed=episode)
        for _ in range(15):
            action = agent.act(obs, info)
            assert isinstance(action, int)
            assert info["action_mask"][action]
            obs, _, _, _, info = env.step(action)
            assert not info["refused_move"]


def test_shipped_ddpg_acts_inside_the_unit_cube() -> None:
    agent = TrainedAgent.load(SHIPPED / "ddpg-gen10k.zip", AREA, device="cpu")
    env = FapContinuousEnv(generate_scenarios(3, 3, seed=7, area=AREA))
    for episode in range(3):
        obs, info = env.reset(seed=episode)
        for _ in range(5):
            action = agent.act(obs, info)
            assert action.shape == (3,)
            assert np.all(np.isfinite(action))
            assert np.all((action >= 0.0) & (action <= 1.0))
            obs, *_ = env.step(action)
