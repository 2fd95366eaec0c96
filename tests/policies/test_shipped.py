"""The shipped checkpoints (policies/checkpoints/) load and act validly in their environment."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from policies.adapters import CheckpointPolicy, trained_environments
from policies.interface import ReportedUsers
from policies.registry import make_placement
from sim.config import AreaConfig
from sim.envs import FapContinuousEnv
from sim.geometry import move_target, valid_moves, volume_bounds
from sim.scenarios import generate_scenarios
from sim.world import PAPER

SHIPPED = Path(__file__).resolve().parents[2] / "policies" / "checkpoints"
AREA = AreaConfig()


TOWNS = ["dense-urban", "highrise-urban", "suburban", "urban"]


@pytest.mark.parametrize(
    ("name", "algorithm", "environments"),
    [
        ("ddqn-dr", "ddqn", ["open"]),
        ("ddpg-residual-dr", "ddpg", ["open"]),
        ("ddpg-residual-towns", "ddpg", TOWNS),
    ],
)
def test_shipped_checkpoint_has_its_metadata(
    name: str, algorithm: str, environments: list[str]
) -> None:
    assert (SHIPPED / f"{name}.zip").is_file()
    area = AreaConfig(environment=environments[-1])
    agent = CheckpointPolicy.load(SHIPPED / f"{name}.zip", replace(PAPER, area=area), device="cpu")
    assert agent.name == name
    assert agent.metadata["algorithm"] == algorithm
    assert agent.metadata["strategy"] == "gen10k"
    assert agent.metadata["families"] == ["exponential", "uniform", "hotspots", "corners"]
    assert agent.metadata["users"] == [1, 15]
    assert trained_environments(agent.metadata) == environments
    assert agent.metadata["serving_only"] is True  # the networks only learning uses: zeroed
    assert agent.metadata["training_command"].split("tupa train")[0] in ("", "OMP_NUM_THREADS=1 ")
    if environments == ["open"]:  # issue 13's checkpoints: at most 15 min on 2 cores
        assert 0 < agent.metadata["wall_time_s"] <= 900


def test_shipped_checkpoints_are_small_and_hold_no_replay_buffer() -> None:
    zips = sorted(SHIPPED.glob("*.zip"))
    assert sum(p.stat().st_size for p in zips) < 20 * 1024 * 1024
    assert not list(SHIPPED.glob("*replay*"))


def test_shipped_ddqn_picks_only_valid_moves() -> None:
    agent = CheckpointPolicy.load(SHIPPED / "ddqn-dr.zip", device="cpu")
    env = FapContinuousEnv(generate_scenarios(3, 3, seed=7, area=AREA))
    for episode in range(3):
        _, info = env.reset(seed=episode)
        for _ in range(15):
            vehicle = info["uav_xyz_m"]
            allowed = np.flatnonzero(valid_moves(vehicle, AREA))
            reachable = {tuple(move_target(int(m), vehicle, AREA)[0]) for m in allowed}
            target = agent.decide(info["reports"], vehicle)
            assert tuple(target) in reachable
            _, _, _, _, info = env.step_to(target)


@pytest.mark.parametrize(
    ("name", "environment"), [("ddpg-residual-dr", "open"), ("ddpg-residual-towns", "urban")]
)
def test_shipped_ddpg_decides_near_the_load_weighted_placement(name: str, environment: str) -> None:
    """Residual actions: every target lies within the residual radius of the load-weighted
    placement of the reported users, inside the volume."""
    area = AreaConfig(environment=environment)
    world = replace(PAPER, area=area)
    agent = CheckpointPolicy.load(SHIPPED / f"{name}.zip", world, device="cpu")
    radius_m = agent.metadata["residual_radius_m"]
    weighted = make_placement("load-weighted", world)
    scenarios = generate_scenarios(3, 8, seed=7, area=area, family="hotspots")
    env = FapContinuousEnv(scenarios, world=world)
    lower, upper = volume_bounds(area)
    for episode in range(3):
        _, info = env.reset(seed=episode)
        for _ in range(5):
            target = agent.decide(info["reports"], info["uav_xyz_m"])
            assert target.shape == (3,)
            assert np.all((target >= lower) & (target <= upper))
            prior = weighted.place(ReportedUsers.of(info["reports"]))
            assert np.all(np.abs(target[:2] - prior[:2]) <= radius_m + 1e-6)
            _, _, _, _, info = env.step_to(target)


def test_ddqn_dr_is_refused_when_a_client_asks_to_serve_it_and_warned_about_otherwise(
    caplog: pytest.LogCaptureFixture,
) -> None:
    """Issue 42: the shipped DDQN dithers between zones on a real vehicle (its metadata says
    so, measured): ``PUT /v1/policy`` (a client, ``allowed_dirs`` given) is refused naming the
    reason; the operator's own ``--policy`` still serves it, with a warning."""
    from service.errors import InputError
    from service.policy_runtime import load_policy

    path = str(SHIPPED / "ddqn-dr.zip")
    with pytest.raises(InputError, match=r"^policy: ddqn-dr is not for serving: it dithers"):
        load_policy(path, allowed_dirs=[SHIPPED])
    with caplog.at_level("WARNING", logger="service.policy_runtime"):
        assert load_policy(path).name == "ddqn-dr"
    assert "which is not for serving: it dithers" in caplog.text
    assert load_policy(str(SHIPPED / "ddpg-residual-dr.zip"), allowed_dirs=[SHIPPED])
