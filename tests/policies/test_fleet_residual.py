"""A fleet's residual actions (policies/learned/fleet_residual.py): zero is the prior (the
load-weighted k-means placement, each UAV taking its nearest share, or ``kmeans-scored`` flown from
where the fleet is), the wrapper keeps PettingZoo's API, targets are separated and inside the
volume, a residual fleet run trains and records its prior, and an untrained (zero-initialised)
residual policy flies exactly its prior."""

from __future__ import annotations

import json
from dataclasses import replace

import numpy as np
import pytest
from pettingzoo.test import parallel_api_test

from policies.evaluation.fleet_evaluation import evaluate_fleet
from policies.interface import ReportedUsers
from policies.learned.checkpoints import export_checkpoint
from policies.learned.fleet_checkpoint import FleetCheckpointPolicy, fleet_observation_shape
from policies.learned.fleet_residual import (
    KMeansPrior,
    ScoredPrior,
    fleet_residual_targets,
    make_prior,
)
from policies.learned.fleet_residual_env import FleetResidualActions
from policies.placements.fleet_baselines import KMeansPlacement
from policies.placements.fleet_scored import ScoredKMeansPlacement
from policies.training.fleet_training import (
    FleetTrainConfig,
    train_fleet,
)
from policies.training.training import zero_actor_output
from sim.config import AreaConfig
from sim.errors import InputError
from sim.fleet import FleetConfig
from sim.fleet_env import FleetParallelEnv
from sim.geometry import assign_targets, volume_bounds
from sim.observation import UserReports
from sim.scenarios import generate_scenarios
from sim.world import get_world
from tests.helpers import tiny_preset

AREA = AreaConfig()


def reports(seed: int = 0, n: int = 24) -> UserReports:
    rng = np.random.default_rng(seed)
    xy = rng.uniform(0, 500, (n, 2))
    load = rng.uniform(1e6, 1e7, n)
    return UserReports(xy[:, 0], xy[:, 1], load, load, np.full(n, 0.01), np.zeros(n))


def test_zero_is_the_kmeans_placement_each_uav_taking_its_nearest_share() -> None:
    r = reports()
    here = np.array([[450.0, 450.0, 30.0], [50.0, 50.0, 30.0], [50.0, 450.0, 30.0]])
    placed = KMeansPlacement(3, AREA, True, 10.0).place(ReportedUsers.of(r))
    got = fleet_residual_targets(np.zeros((3, 3)), r, here, AREA, 10.0)
    np.testing.assert_allclose(got, assign_targets(here, placed))
    # The same prior whoever asks, cached or not.
    cached = KMeansPrior(AREA, 10.0)
    for _ in range(2):
        np.testing.assert_allclose(
            fleet_residual_targets(np.zeros((3, 3)), r, here, AREA, 10.0, prior=cached), got
        )


def test_deltas_move_each_uav_within_the_radius_and_the_set_stays_safe() -> None:
    r = reports(1)
    here = np.array([[250.0, 250.0, 30.0], [260.0, 250.0, 30.0]])
    rng = np.random.default_rng(2)
    lower, upper = volume_bounds(AREA)
    zero = fleet_residual_targets(np.zeros((2, 3)), r, here, AREA, 10.0, radius_m=50.0)
    for _ in range(50):
        deltas = rng.uniform(-3, 3, (2, 3))  # clipped to [-1, 1]
        got = fleet_residual_targets(deltas, r, here, AREA, 10.0, radius_m=50.0)
        assert np.all(got >= lower - 1e-9) and np.all(got <= upper + 1e-9)
        assert np.linalg.norm(got[0] - got[1]) >= 10.0 - 1e-9
        assert np.all(np.abs(got[:, :2] - zero[:, :2]) <= 50.0 + 10.0 + 1e-6)  # + separation
    up = fleet_residual_targets(np.array([[0, 0, 1.0], [0, 0, -1.0]]), r, here, AREA, 10.0)
    assert up[0, 2] == pytest.approx(AREA.z_max_m) and up[1, 2] == pytest.approx(AREA.z_min_m)


def test_the_residual_fleet_keeps_pettingzoos_parallel_api() -> None:
    env = FleetResidualActions(FleetParallelEnv(n_uavs=3, action_kind="continuous"))
    parallel_api_test(env, num_cycles=20)
    env.reset(seed=0)
    with pytest.raises(ValueError, match="actions"):
        env.step({env.possible_agents[0]: np.zeros(3)})


TINY_PRESET = tiny_preset()


@pytest.mark.training
def test_a_residual_run_trains_and_untrained_it_flies_the_kmeans_baseline(tmp_path) -> None:
    config = FleetTrainConfig(
        n_uavs=2, episodes=6, out_dir=tmp_path / "run", preset=TINY_PRESET, seed=5,
        users=(10, 12), action="residual", command="test",
    )  # fmt: skip
    metadata = train_fleet(config)
    on_disk = json.loads((tmp_path / "run" / "model.json").read_text())
    assert on_disk["action"] == metadata["action"] == "residual"
    assert on_disk["residual_radius_m"] == 125.0
    policy = FleetCheckpointPolicy.load(tmp_path / "run", AREA)
    assert policy.residual_radius_m == 125.0
    with pytest.raises(InputError, match="reports, uav_xyz_m"):
        policy.targets(np.zeros((2, *policy.shape), dtype=np.float32))

    world = replace(get_world("closed-loop"), episode_steps=6)
    scenarios = generate_scenarios(3, 12, 9, family="hotspots", total_load_bps=60e6)
    trained = evaluate_fleet(policy, scenarios, 2, world)
    assert 0.0 < trained["mean_utility"] <= 1.0
    zero_actor_output(policy.model)  # the actor's output is 0: the k-means placement
    untrained = evaluate_fleet(policy, scenarios, 2, world)
    kmeans = evaluate_fleet(KMeansPlacement(2, AREA, True), scenarios, 2, world)
    np.testing.assert_allclose(untrained["utilities"], kmeans["utilities"], rtol=0, atol=1e-12)


def test_zero_on_the_scored_prior_is_kmeans_scored_flown_from_where_the_fleet_is() -> None:
    world = get_world("closed-loop")
    r = reports(3, 30)
    here = np.array([[450.0, 450.0, 30.0], [50.0, 50.0, 30.0], [50.0, 450.0, 30.0]])
    association = np.arange(30) % 3
    prior = make_prior("kmeans-scored", AREA, 10.0, world, score_steps=20)
    assert isinstance(prior, ScoredPrior)
    got = fleet_residual_targets(
        np.zeros((3, 3)), r, here, AREA, 10.0, prior=prior, association=association,
        flight=world.flight,
    )  # fmt: skip
    scored = ScoredKMeansPlacement(FleetConfig(n_uavs=3), AREA, world.network, world.utility, 20)
    expected = scored.place_from(ReportedUsers.of(r), here, association, world.flight)
    np.testing.assert_array_equal(got, expected)
    # Any K from one prior: a fleet of two is placed by a placement of two.
    two = prior.place_for(r, here[:2], association % 2, world.flight)
    assert two.shape == (2, 3)


def test_a_named_preset_takes_the_residual_changes_for_residual_actions() -> None:
    residual = FleetTrainConfig(n_uavs=2, episodes=1, out_dir="x", action="residual")
    absolute = FleetTrainConfig(n_uavs=2, episodes=1, out_dir="x")
    assert residual.chosen_preset.action_l2 > 0 == absolute.chosen_preset.action_l2
    assert residual.chosen_preset.action_noise_sigma > absolute.chosen_preset.action_noise_sigma


def test_a_prior_that_is_not_known_or_lacks_its_world_is_refused() -> None:
    with pytest.raises(InputError, match="prior: must be one of"):
        make_prior("oracle", AREA, 10.0)
    with pytest.raises(InputError, match="prior: kmeans-scored scores on a world"):
        make_prior("kmeans-scored", AREA, 10.0)
    with pytest.raises(InputError, match="--prior: the placement residual actions correct"):
        FleetTrainConfig(n_uavs=2, episodes=1, out_dir="x", prior="kmeans-scored")
    with pytest.raises(InputError, match="--prior: must be one of"):
        FleetTrainConfig(n_uavs=2, episodes=1, out_dir="x", action="residual", prior="what")
    with pytest.raises(InputError, match="--imitate: teaches residuals around"):
        FleetTrainConfig(
            n_uavs=2, episodes=0, out_dir="x", action="residual", prior="kmeans-scored",
            imitate=2,
        )  # fmt: skip


@pytest.mark.training
def test_a_run_on_the_scored_prior_records_it_and_untrained_flies_kmeans_scored(tmp_path) -> None:
    config = FleetTrainConfig(
        n_uavs=2, episodes=2, out_dir=tmp_path / "run", preset=TINY_PRESET, seed=5,
        users=(8, 10), action="residual", prior="kmeans-scored", residual_radius_m=30.0,
        command="test",
    )  # fmt: skip
    train_fleet(config)
    on_disk = json.loads((tmp_path / "run" / "model.json").read_text())
    assert (on_disk["prior"], on_disk["prior_score_steps"]) == ("kmeans-scored", 100)
    world = replace(get_world("closed-loop"), episode_steps=5)
    policy = FleetCheckpointPolicy.load(tmp_path / "run", AREA, world=world)
    assert isinstance(policy.prior, ScoredPrior) and policy.prior.score_steps == 100
    # Its serving copy (as the shipped fleet checkpoint is made) decides as it does.
    served = tmp_path / "served.zip"
    export_checkpoint(tmp_path / "run" / "model.zip", served, AREA, serving_only=True,
                      observation_shape=fleet_observation_shape(AREA))  # fmt: skip
    copy = FleetCheckpointPolicy.load(served, AREA, world=world)
    env = FleetParallelEnv(n_uavs=2, action_kind="continuous", world=world)
    observations, _ = env.reset(seed=1)
    joint = np.stack([observations[a] for a in env.possible_agents])
    here, seen = env.uav_xyz_m, env.reported_association
    np.testing.assert_array_equal(
        copy.targets(joint, env.reports, here, seen), policy.targets(joint, env.reports, here, seen)
    )
    zero_actor_output(policy.model)
    scenarios = generate_scenarios(2, 10, 4, family="hotspots", total_load_bps=60e6)
    untrained = evaluate_fleet(policy, scenarios, 2, world)
    scored = ScoredKMeansPlacement(FleetConfig(n_uavs=2), AREA, world.network, world.utility)
    flown = evaluate_fleet(scored, scenarios, 2, world, replan_every=1)
    np.testing.assert_allclose(untrained["utilities"], flown["utilities"], rtol=0, atol=1e-12)
