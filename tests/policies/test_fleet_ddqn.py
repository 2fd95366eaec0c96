"""The paper's DDQN for a fleet (policies/training/fleet_training.py): one masked Double DQN shared
by the UAVs, its masks reaching the learner through the SuperSuit bridge, a checkpoint that moves
each UAV by one of the 13 moves from its own zone (never out of the volume), for any K."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from policies.learned.fleet_checkpoint import FleetCheckpointPolicy
from policies.training.fleet_training import (
    FleetTrainConfig,
    make_fleet_vec_env,
    train_fleet,
)
from sim.config import AreaConfig
from sim.errors import InputError
from sim.fleet_env import FleetParallelEnv
from sim.geometry import MOVES, zone_indices
from tests.helpers import tiny_preset

AREA = AreaConfig()
TINY_DDQN = tiny_preset("ddqn", learning_starts=32, batch_size=16)


def _config(out: Path, **over: object) -> FleetTrainConfig:
    fields: dict = {
        "n_uavs": 2,
        "episodes": 5,
        "out_dir": out,
        "algorithm": "ddqn",
        "preset": TINY_DDQN,
        "users": (10, 12),
        "command": "test",
        "progress": False,
    }
    return FleetTrainConfig(**{**fields, **over})


def test_the_bridge_hands_the_learner_each_agents_current_mask(tmp_path: Path) -> None:
    vec = make_fleet_vec_env(_config(tmp_path / "r", n_fleets=2))
    vec.seed(3)
    vec.reset()
    for _ in range(12):  # through an episode's end (10 steps): the next one's masks
        masks = np.stack(vec.env_method("action_masks"))
        assert masks.shape == (4, 13) and masks.dtype == bool and masks.any(axis=1).all()
        actions = np.array([np.flatnonzero(m)[-1] for m in masks])  # the last valid move
        vec.step(actions)
    vec.close()


@pytest.mark.training
def test_a_ddqn_fleet_trains_and_moves_each_uav_from_its_own_zone(tmp_path: Path) -> None:
    metadata = train_fleet(_config(tmp_path / "run"))
    on_disk = json.loads((tmp_path / "run" / "model.json").read_text())
    assert on_disk["algorithm"] == metadata["algorithm"] == "ddqn"
    assert on_disk["action"] == "moves" and on_disk["fleet"] is True
    policy = FleetCheckpointPolicy.load(tmp_path / "run", AREA)
    for k in (1, 3, 4):  # any K
        env = FleetParallelEnv(n_uavs=k, action_kind="discrete")
        observations, _ = env.reset(seed=k)
        joint = np.stack([observations[a] for a in env.possible_agents])
        here = env.uav_xyz_m.copy()
        with pytest.raises(InputError, match="uav_xyz_m"):
            policy.targets(joint)
        targets = policy.targets(joint, env.reports, here)
        assert targets.shape == (k, 3)
        # Each UAV moved by one of the 13 moves from its zone (or was pushed apart by the
        # separation rule, which moves a target by at most a little more than 10 m).
        steps = zone_indices(targets, AREA) - zone_indices(here, AREA)
        for step, target, start in zip(steps, targets, here, strict=True):
            assert any((step == move).all() for move in MOVES) or (
                np.linalg.norm(target - start) <= 5 * AREA.zone_m + 15.0
            )


def test_residual_actions_are_ddpgs() -> None:
    with pytest.raises(InputError, match="--action: residual actions are DDPG's"):
        _config(Path("unused"), action="residual")
