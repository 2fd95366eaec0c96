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


@pytest.mark.parametrize(("name", "algorithm"), [("ddqn-dr", "ddqn"), ("ddpg-residual-dr", "ddpg")])
def test_shipped_checkpoint_has_its_metadata(name: str, algorithm: str) -> None:
    assert (SHIPPED / f"{name}.zip").is_file()
    agent = TrainedAgent.load(SHIPPED / f"{name}.zip", AREA, device="cpu")
    assert agent.name == name
    assert agent.metadata["algorithm"] == algorithm
    assert agent.metadata["strategy"] == "gen10k"
    assert agent.metadata["families"] == ["exponential", "uniform", "hotspots", "corners"]
    assert agent.metadata["users"] == [1, 15]
    assert 0 < agent.metadata["wall_time_s"] <= 900  # issue 13: at most 15 min on 2 cores
    assert agent.metadata["training_command"].startswith("OMP_NUM_THREADS=1 tupa train")


def test_shipped_checkpoints_are_small_and_hold_no_replay_buffer() -> None:
    zips = sorted(SHIPPED.glob("*.zip"))
    assert sum(p.stat().st_size for p in zips) < 20 * 1024 * 1024
    assert not list(SHIPPED.glob("*replay*"))


def test_shipped_ddqn_picks_only_valid_moves() -> None:
    agent = TrainedAgent.load(SHIPPED / "ddqn-dr.zip", AREA, device="cpu")
    env = FapDiscreteEnv(generate_scenarios(3, 3, seed=7, area=AREA))
    for episode in range(3):
        obs, info = env.reset(seed=episode)
        for _ in range(15):
            action = agent.act(obs, info)
            assert isinstance(action, int)
            assert info["action_mask"][action]
            obs, _, _, _, info = env.step(action)
            assert not info["refused_move"]


def test_shipped_ddpg_acts_inside_the_unit_cube_near_the_load_weighted_placement() -> None:
    """Residual actions: every target lies within the residual radius of the load-weighted
    placement of the reported users, inside the volume."""
    from policies.baselines import ReportedUsers, make_policy

    agent = TrainedAgent.load(SHIPPED / "ddpg-residual-dr.zip", AREA, device="cpu")
    radius_m = agent.metadata["residual_radius_m"]
    weighted = make_policy("load-weighted", AREA)
    env = FapContinuousEnv(generate_scenarios(3, 8, seed=7, area=AREA, family="hotspots"))
    for episode in range(3):
        obs, info = env.reset(seed=episode)
        for _ in range(5):
            action = agent.act(obs, info)
            assert action.shape == (3,)
            assert np.all(np.isfinite(action))
            assert np.all((action >= 0.0) & (action <= 1.0))
            prior = weighted.place(ReportedUsers.of(info["reports"]))
            obs, _, _, _, info = env.step(action)
            gap = np.abs(info["target_xyz_m"][:2] - prior[:2])
            assert np.all(gap <= radius_m + 1e-6)
