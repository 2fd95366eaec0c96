"""Shared-parameter fleet training (policies/training/fleet_training.py): a tiny run end to end, the
policy flying fleets of another size, evaluation, and the CLI's refusals."""

from __future__ import annotations

import json
import shlex
from dataclasses import replace
from itertools import combinations
from pathlib import Path

import numpy as np
import pytest

from policies.evaluation.fleet_evaluation import evaluate_fleet
from policies.learned.checkpoints import CheckpointError, load_checkpoint
from policies.learned.fleet_checkpoint import FleetCheckpointPolicy
from policies.placements.fleet_baselines import KMeansPlacement
from policies.training.fleet_training import (
    FleetTrainConfig,
    train_fleet,
)
from service.cli import main
from sim.config import AreaConfig
from sim.errors import InputError
from sim.fleet import FleetConfig
from sim.fleet_env import FleetParallelEnv
from sim.scenarios import generate_scenarios
from sim.world import get_world
from tests.helpers import tiny_preset
from tests.tiers import needs

AREA = AreaConfig()
TINY_PRESET = tiny_preset()
SHORT_WORLD = replace(get_world("closed-loop"), episode_steps=8)


@pytest.fixture(scope="module")
@needs("training")
def trained(tmp_path_factory) -> tuple[Path, dict]:
    out = tmp_path_factory.mktemp("fleet") / "run"
    config = FleetTrainConfig(
        n_uavs=2,
        episodes=8,
        out_dir=out,
        preset=TINY_PRESET,
        seed=3,
        users=(10, 20),
        n_fleets=2,
        command="test",
    )
    return out, train_fleet(config)


def test_training_writes_a_checkpoint_with_fleet_metadata(trained):
    out, metadata = trained
    assert (out / "model.zip").is_file()
    on_disk = json.loads((out / "model.json").read_text())
    assert on_disk["format"] == "tupa-checkpoint/1"
    assert on_disk["n_uavs_trained"] == metadata["n_uavs_trained"] == 2
    assert on_disk["observation_shape"] == [9, AREA.n_zones_x, AREA.n_zones_y]
    assert on_disk["algorithm"] == "ddpg" and on_disk["action"] == "coordinates"
    assert on_disk["world"]["name"] == "closed-loop"
    assert on_disk["command"] == "test" and on_disk["seed"] == 3
    # 8 fleet episodes × 10 decisions × 2 agents (SB3 may finish its last batch step).
    assert 160 <= on_disk["timesteps"] < 160 + 4


def test_a_fleet_checkpoint_is_refused_as_a_single_uav_one(trained):
    out, _ = trained
    with pytest.raises(CheckpointError, match="observation_shape"):
        load_checkpoint(out, AREA)
    model, meta = load_checkpoint(out, AREA, observation_shape=(9, AREA.n_zones_x, 20))
    assert list(model.observation_space.shape) == meta["observation_shape"]


@pytest.mark.parametrize("k", [2, 3])
def test_the_shared_policy_flies_fleets_of_any_size(trained, k):
    out, _ = trained
    policy = FleetCheckpointPolicy.load(out, AREA, separation_m=10.0)
    env = FleetParallelEnv(n_uavs=k, action_kind="continuous", world=SHORT_WORLD)
    rng = np.random.default_rng(k)
    observations, _ = env.reset(seed=k)
    for _ in range(4):
        joint = np.stack([observations[a] for a in env.possible_agents])
        # Random observations too: the policy must keep any answer separated and inside.
        for obs in (joint, rng.random(joint.shape, dtype=np.float32)):
            targets = policy.targets(obs)
            assert targets.shape == (k, 3)
            assert np.all(targets[:, :2] >= 0)
            assert np.all(targets[:, 0] <= AREA.size_x_m)
            assert np.all(targets[:, 1] <= AREA.size_y_m)
            assert np.all(targets[:, 2] >= AREA.z_min_m - 1e-9)
            assert np.all(targets[:, 2] <= AREA.z_max_m + 1e-9)
            for i, j in combinations(range(k), 2):
                assert np.linalg.norm(targets[i] - targets[j]) >= 10.0 - 1e-6
        observations, *_ = env.step_to(policy.targets(joint))


def test_the_policy_refuses_observations_of_the_wrong_shape(trained):
    out, _ = trained
    policy = FleetCheckpointPolicy.load(out, AREA)
    with pytest.raises(InputError, match="observations"):
        policy.targets(np.zeros((2, 6, 20, 20), dtype=np.float32))
    with pytest.raises(InputError, match="observations"):
        policy.targets(np.zeros((9, 9, 20, 20), dtype=np.float32))


def test_evaluation_returns_metrics_in_range(trained):
    out, _ = trained
    scenarios = generate_scenarios(2, 12, seed=5, family="hotspots", total_load_bps=120e6)
    policy = FleetCheckpointPolicy.load(out, AREA)
    for candidate in (policy, KMeansPlacement(3, AREA)):
        result = evaluate_fleet(candidate, scenarios, 3, SHORT_WORLD, replan_every=2)
        assert result["n_scenarios"] == 2 and len(result["utilities"]) == 2
        assert 0.0 <= result["mean_utility"] <= 1.0
        assert 0.0 <= result["mean_served_fraction"] <= 1.0
        assert 0.0 < result["mean_jain_fairness"] <= 1.0
        assert 0.0 <= result["mean_min_throughput_bps"] < 1e9
        assert np.isclose(result["mean_utility"], np.mean(result["utilities"]))


def test_evaluation_of_a_held_placement_matches_the_environment():
    """A placement held over the episode scores what stepping the env to it by hand gives."""
    scenario = generate_scenarios(1, 10, seed=8, family="uniform", total_load_bps=80e6)[0]
    placement = KMeansPlacement(2, AREA)
    result = evaluate_fleet(placement, [scenario], 2, SHORT_WORLD, replan_every=100, seed=4)
    env = FleetParallelEnv(action_kind="continuous", world=SHORT_WORLD, fleet=FleetConfig(2))
    env.reset(seed=4, options={"scenario": scenario})
    report = env.reports
    users = type("U", (), {})()
    users.users_xy_m = np.column_stack([report.x_m, report.y_m])
    users.load_bps = np.asarray(report.offered_bps)
    targets = placement.place(users)
    utilities = []
    while env.agents:
        _, rewards, *_ = env.step_to(targets)
        utilities.append(rewards["uav_0"])
    assert result["mean_utility"] == pytest.approx(np.mean(utilities))


def test_evaluation_refuses_bad_input(trained):
    scenarios = generate_scenarios(1, 5, seed=1)
    with pytest.raises(InputError, match="scenarios"):
        evaluate_fleet(KMeansPlacement(2, AREA), [], 2, SHORT_WORLD)
    with pytest.raises(InputError, match="replan_every"):
        evaluate_fleet(KMeansPlacement(2, AREA), scenarios, 2, SHORT_WORLD, replan_every=0)


@pytest.mark.parametrize(
    ("changes", "field"),
    [
        ({"n_uavs": 9}, "--uavs"),
        ({"n_uavs": 0}, "--uavs"),
        ({"algorithm": "sac"}, "--algo: fleets train with ddpg or ddqn"),
        ({"episodes": 0}, "--episodes"),
        ({"world": "moon"}, "world"),
        ({"families": ("nope",)}, "families"),
    ],
)
def test_config_refuses_bad_fields(tmp_path, changes, field):
    kwargs = {"n_uavs": 2, "episodes": 1, "out_dir": tmp_path / "o", **changes}
    with pytest.raises(InputError, match=field):
        FleetTrainConfig(**kwargs)


@pytest.mark.parametrize(
    ("extra", "message"),
    [
        (["--uavs", "9", "--algo", "ddpg"], "--uavs: must be in 1..8"),
        (["--uavs", "0", "--algo", "ddpg"], "--uavs: must be in 1..8"),
        (
            ["--uavs", "2", "--algo", "ddqn", "--action", "residual"],
            "--action: residual actions are DDPG's",
        ),
        (
            ["--uavs", "2", "--algo", "ddpg", "--action", "residual", "--residual-radius-m", "0"],
            "--residual-radius-m: must be > 0",
        ),
        (["--algo", "ddpg", "--residual-radius-m", "40"], "--residual-radius-m: for fleets only"),
        (["--algo", "ddpg", "--imitate", "4"], "--imitate: for fleets only"),
        (["--algo", "ddpg", "--workers", "2"], "--workers: for fleets only"),
        (["--algo", "ddpg", "--teacher", "local"], "--teacher: for fleets only"),
        (["--algo", "ddpg", "--symmetries"], "--symmetries: for fleets only"),
        (["--algo", "ddpg", "--dagger", "2"], "--dagger: for fleets only"),
        (
            ["--uavs", "3", "--algo", "ddpg", "--environment", "mars"],
            "--environment: must be among",
        ),
        (
            ["--uavs", "3", "--algo", "ddpg", "--environment", "open,urban"],
            "--environment: a fleet run trains in one environment, got 2",
        ),
        (
            ["--uavs", "3", "--algo", "ddpg", "--strategy", "spec", "--no-final-eval"],
            "--strategy, --no-final-eval: for single-UAV runs only",
        ),
        (
            ["--uavs", "2", "--algo", "ddpg", "--test-scenarios", "spec", "--queueing", "mac-only"],
            "--test-scenarios, --queueing: for single-UAV runs only",
        ),
        (
            ["--uavs", "2", "--algo", "ddpg", "--checkpoint-every", "7", "--save-replay-buffer"],
            "--checkpoint-every, --save-replay-buffer: for single-UAV runs only",
        ),
    ],
)
def test_cli_refuses_bad_fleet_sizes_and_writes_nothing(tmp_path, capsys, extra, message):
    out = tmp_path / "out"
    assert main(["train", *extra, "--episodes", "2", "--out", str(out)]) == 2
    err = capsys.readouterr().err.strip()
    assert message in err and "\n" not in err
    assert not out.exists()


@pytest.mark.training
def test_cli_trains_a_fleet(tmp_path, capsys, monkeypatch):
    import policies.training.fleet_training as fleet_training

    # The CLI's own preset is too big for a test: swap in the tiny one, keep everything else.
    monkeypatch.setattr(
        fleet_training.FleetTrainConfig,
        "chosen_preset",
        property(lambda self: TINY_PRESET),
    )
    out = tmp_path / "cli"
    argv = ["train", "--uavs", "3", "--algo", "ddpg", "--episodes", "2", "--out", str(out)]
    assert main([*argv, "--users", "8", "--world", "closed-loop", "--seed", "2"]) == 0
    meta = json.loads((out / "model.json").read_text())
    assert meta["n_uavs_trained"] == 3 and meta["users"] == [8, 8] and meta["seed"] == 2
    assert meta["command"] == shlex.join(
        ["tupa", *argv, "--users", "8", "--world", "closed-loop", "--seed", "2"]
    )
    assert "shared ddpg policy for 3 UAVs" in capsys.readouterr().out
    assert meta["train_environments"] == ["open"] == [meta["world"]["area"]["environment"]]
    assert main(argv) == 2  # a second run into the same directory is refused


@pytest.mark.training
def test_a_fleet_trains_in_the_environment_it_is_given(tmp_path, monkeypatch):
    """``--environment urban``: the fleets fly the urban channel in training, and the
    checkpoint says so (as a single-UAV one does)."""
    import policies.training.fleet_training as fleet_training

    monkeypatch.setattr(
        fleet_training.FleetTrainConfig, "chosen_preset", property(lambda self: TINY_PRESET)
    )
    built: list[FleetParallelEnv] = []
    original = fleet_training.FleetParallelEnv

    def recording(*args, **kwargs):
        built.append(original(*args, **kwargs))
        return built[-1]

    monkeypatch.setattr(fleet_training, "FleetParallelEnv", recording)
    out = tmp_path / "urban"
    argv = ["train", "--uavs", "2", "--algo", "ddpg", "--episodes", "1", "--users", "6"]
    assert main([*argv, "--environment", "urban", "--out", str(out), "--no-progress"]) == 0
    assert [env.world.area.environment for env in built] == ["urban"]
    assert built[0].model.area.environment == "urban"
    meta = json.loads((out / "model.json").read_text())
    assert meta["train_environments"] == ["urban"] == [meta["world"]["area"]["environment"]]


@pytest.mark.training
def test_cli_imitates_a_teacher_and_says_how_well_the_fit_went(tmp_path, capsys, monkeypatch):
    import policies.training.fleet_training as fleet_training

    monkeypatch.setattr(
        fleet_training.FleetTrainConfig, "chosen_preset", property(lambda self: TINY_PRESET)
    )
    out = tmp_path / "imitated"
    argv = ["train", "--uavs", "2", "--algo", "ddpg", "--action", "residual", "--imitate", "2"]
    extra = ["--teacher", "local", "--symmetries", "--episodes", "0", "--users", "6", "--out"]
    assert main([*argv, *extra, str(out), "--no-progress"]) == 0
    record = json.loads((out / "model.json").read_text())["imitation"]
    assert record["teacher"]["name"] == "local" and record["symmetries"] == 8
    said = capsys.readouterr().out
    assert f"fitted to {record['samples']} teacher decisions" in said
    assert f"zero action {record['zero_action_validation_mse']:.4f}" in said


@pytest.mark.training
def test_cli_imitates_the_teachers_moves_for_ddqn(tmp_path, capsys, monkeypatch):
    import policies.training.fleet_training as fleet_training

    monkeypatch.setattr(
        fleet_training.FleetTrainConfig, "chosen_preset", property(lambda self: TINY_PRESET)
    )
    out = tmp_path / "moves"
    argv = ["train", "--uavs", "2", "--algo", "ddqn", "--imitate", "2", "--dagger", "1"]
    assert main([*argv, "--episodes", "0", "--users", "6", "--out", str(out), "--no-progress"]) == 0
    meta = json.loads((out / "model.json").read_text())
    record = meta["imitation"]
    per_round = 2 * 2 * TINY_PRESET.train_episode_steps  # episodes × UAVs × steps
    assert meta["action"] == "moves" and record["samples"] == 2 * per_round
    assert [(r["round"], r["flown_by"], r["samples"]) for r in record["rounds"]] == [
        (0, "teacher", per_round),
        (1, "learner", 2 * per_round),
    ]
    assert record["dagger_rounds"] == 1 and sorted(p.name for p in out.iterdir()) == [
        "model.json",
        "model.zip",
    ]
    said = capsys.readouterr().out
    assert f"fitted to {record['samples']} teacher moves" in said
    assert f"validation accuracy {record['validation_accuracy']:.3f}" in said


@pytest.mark.training
def test_training_is_deterministic_given_the_seed(tmp_path):
    """Same seed, same network: the fleets' first reset and torch are both seeded."""
    decided = []
    for run in ("a", "b", "c"):
        config = FleetTrainConfig(
            n_uavs=2,
            episodes=8,
            out_dir=tmp_path / run,
            preset=TINY_PRESET,
            seed=5 if run != "c" else 6,
            users=(6, 6),
        )
        train_fleet(config)
        policy = FleetCheckpointPolicy.load(tmp_path / run, AREA)
        obs = np.random.default_rng(0).random((2, 9, 20, 20), dtype=np.float32)
        decided.append(policy.targets(obs))
    np.testing.assert_array_equal(decided[0], decided[1])
    assert not np.array_equal(decided[0], decided[2])


def test_the_update_ratio_is_kept_per_transition():
    from policies.training.fleet_training import _vector_preset
    from policies.training.presets import get_preset

    preset = get_preset("fast", "ddpg")  # one gradient step per 8 transitions
    assert (preset.train_freq, preset.gradient_steps) == (8, 1)
    two = _vector_preset(preset, 2)
    assert (two.train_freq, two.gradient_steps) == (4, 1)
    sixteen = _vector_preset(preset, 16)
    assert (sixteen.train_freq, sixteen.gradient_steps) == (1, 2)


def test_a_checkpoint_acting_otherwise_is_refused(trained):
    out, _ = trained
    policy = FleetCheckpointPolicy.load(out, AREA)
    with pytest.raises(InputError, match="action"):
        FleetCheckpointPolicy(policy.model, {**policy.metadata, "action": "moves"}, AREA)
    with pytest.raises(InputError, match="separation_m"):
        FleetCheckpointPolicy(policy.model, policy.metadata, AREA, separation_m=0.0)
