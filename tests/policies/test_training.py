"""DDQN masking and target, DDPG, checkpoints, training and resume (small, fast runs)."""

from __future__ import annotations

import json
import os
import pickle
import sys
import threading
import types
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import torch as th
from hypothesis import given, settings
from hypothesis import strategies as st

from policies.adapters import CheckpointPolicy
from policies.evaluation.evaluation import evaluate_policy
from policies.interface import ReportedUsers
from policies.learned.checkpoints import load_checkpoint, save_checkpoint
from policies.learned.ddqn import double_dqn_targets
from policies.registry import make_placement
from policies.training.presets import NetworkPreset, get_preset
from policies.training.training import TrainConfig, build_model, make_env, train
from service.cli import main
from sim.config import AreaConfig
from sim.errors import InputError
from sim.files import save_scenarios
from sim.geometry import move_target, valid_moves
from sim.scenarios import Scenario, generate_scenarios
from sim.world import PAPER

AREA = AreaConfig()
TINY_NET = NetworkPreset(channels=(8,), hidden=32, features_dim=32, dropout=0.0)


def tiny_preset(algorithm: str, **changes):
    base = get_preset("fast", algorithm)
    return replace(
        base, network=TINY_NET, buffer_size=5_000, learning_starts=64, batch_size=32, **changes
    )


@pytest.fixture(scope="module")
def test_file(tmp_path_factory) -> Path:
    path = tmp_path_factory.mktemp("data") / "test.json"
    save_scenarios(path, AREA, generate_scenarios(6, 3, seed=99))
    return path


def test_double_dqn_target_follows_the_formula():
    rewards = th.tensor([[0.5], [0.2], [1.0]])
    dones = th.tensor([[0.0], [0.0], [1.0]])
    online = th.tensor([[1.0, 3.0, 2.0], [5.0, 1.0, 0.0], [0.0, 0.0, 9.0]])
    target = th.tensor([[10.0, 20.0, 30.0], [7.0, 8.0, 9.0], [1.0, 1.0, 1.0]])
    masks = th.tensor([[True, True, True], [False, True, True], [True, True, True]])
    y = double_dqn_targets(rewards, dones, 0.9, online, target, masks)
    # Row 0: online argmax is action 1 → target value 20 (vanilla DQN would take max 30).
    # Row 1: action 0 is masked; online argmax among {1, 2} is 1 → target value 8.
    # Row 2: terminal → reward only.
    expected = th.tensor([[0.5 + 0.9 * 20.0], [0.2 + 0.9 * 8.0], [1.0]])
    th.testing.assert_close(y, expected)
    vanilla = rewards + (1 - dones) * 0.9 * target.max(dim=1, keepdim=True).values
    assert not th.allclose(y, vanilla)


@pytest.fixture(scope="module")
def random_ddqn(test_file):
    from sim.files import load_scenarios

    _, scenarios = load_scenarios(test_file)
    env = make_env("ddqn", scenarios, replace(PAPER, area=AREA))
    return build_model("ddqn", env, tiny_preset("ddqn"), seed=0, tensorboard_log=None)


@settings(max_examples=50, deadline=None)
@given(
    masks=st.lists(st.lists(st.booleans(), min_size=13, max_size=13), min_size=1, max_size=8),
    epsilon=st.sampled_from([0.0, 0.5, 1.0]),
    seed=st.integers(0, 1000),
)
def test_ddqn_never_picks_a_masked_move(random_ddqn, masks, epsilon, seed):
    masks = np.array(masks, dtype=bool)
    masks[:, 0] = True  # "stay" is always valid in the environment
    rng = np.random.default_rng(seed)
    obs = rng.random((len(masks), *random_ddqn.observation_space.shape), dtype=np.float32)
    actions = random_ddqn.masked_predict(obs, masks, epsilon=epsilon)
    assert np.all(masks[np.arange(len(masks)), actions])


def test_ddqn_acting_in_the_environment_respects_masks(random_ddqn):
    env = random_ddqn.get_env()
    random_ddqn.exploration_rate = 0.3
    random_ddqn._last_obs = env.reset()
    for _ in range(60):
        masks = np.stack(env.env_method("action_masks"))
        actions, _ = random_ddqn._sample_action(learning_starts=0)
        assert masks[0, actions[0]]
        random_ddqn._last_obs, *_ = env.step(actions)


def small_config(
    test_file: Path, out: Path, algorithm: str, episodes: int, **changes
) -> TrainConfig:
    return TrainConfig(
        algorithm=algorithm,
        strategy="spec",
        episodes=episodes,
        preset=tiny_preset(algorithm, **changes),
        seed=3,
        test_scenarios=test_file,
        out_dir=out,
        checkpoint_every=5,
        final_eval=False,
        progress=False,
    )


@pytest.fixture
def two_torch_threads():
    """torch on two threads for the test, as on the 2-core CI machine, whatever an earlier test
    left: the sweep's in-process trials set one thread (``policies/sweep/trial.py``), and this
    short training's result depends on the float reduction order that sets."""
    import torch

    before = torch.get_num_threads()
    torch.set_num_threads(2)
    yield
    torch.set_num_threads(before)


@pytest.mark.slow
@pytest.mark.training
@pytest.mark.usefixtures("two_torch_threads")
def test_short_ddqn_training_beats_a_random_walk(tmp_path):
    """On one scenario whose single heavy user is far from the start, a few hundred training
    steps teach the agent to move towards it; a random (valid) walk does not."""
    scenario = Scenario("corner", np.array([[30.0, 30.0]]), np.array([40e6]))
    path = tmp_path / "one.json"
    save_scenarios(path, AREA, [scenario])
    config = replace(
        small_config(path, tmp_path / "run", "ddqn", 40, train_episode_steps=20),
        preset=tiny_preset(
            "ddqn", train_episode_steps=20, train_start="centre", epsilon_decay_per_episode=0.1
        ),
    )
    train(config)
    # The run's TensorBoard writer is closed: its last events are on disk, its thread is gone.
    writers = [t for t in threading.enumerate() if "event_file_writer" in type(t).__module__]
    assert not writers
    assert list((tmp_path / "run" / "tb").rglob("events.out.tfevents.*"))
    agent = CheckpointPolicy.load(tmp_path / "run")

    class RandomWalk:
        """Random valid moves, as a policy deciding targets."""

        name = spec = "random"
        kind = "moves"

        def __init__(self):
            self.rng = np.random.default_rng(0)

        def begin_episode(self, users, world):
            return None

        def decide(self, reports, vehicle_xyz_m):
            move = int(self.rng.choice(np.flatnonzero(valid_moves(vehicle_xyz_m, AREA))))
            return move_target(move, vehicle_xyz_m, AREA)[0]

        def describe(self):
            return {"name": self.name}

    kwargs = {"world": replace(PAPER, episode_steps=20), "seed": 0, "progress": False}
    trained = evaluate_policy(agent, [scenario], **kwargs)["mean_utility"]
    random = evaluate_policy(RandomWalk(), [scenario], **kwargs)["mean_utility"]
    assert trained > random + 0.05


@pytest.mark.slow
@pytest.mark.training
def test_checkpoint_round_trip_and_resume_continues_the_step_counter(tmp_path, test_file):
    out = tmp_path / "run"
    first = train(small_config(test_file, out, "ddqn", 10))
    assert first["episodes"] == 10
    assert first["timesteps"] == 10 * 30
    meta = json.loads((out / "model.json").read_text())
    assert meta["algorithm"] == "ddqn" and meta["observation_shape"] == [6, 20, 20]
    model, loaded_meta = load_checkpoint(out / "model.zip", AREA)
    assert loaded_meta["episodes"] == 10
    obs = np.random.default_rng(0).random((4, 6, 20, 20), dtype=np.float32)
    masks = np.ones((4, 13), dtype=bool)
    original = CheckpointPolicy.load(out).model
    np.testing.assert_array_equal(
        model.masked_predict(obs, masks), original.masked_predict(obs, masks)
    )

    resumed = train(replace(small_config(test_file, out, "ddqn", 16)), resume=True)
    assert resumed["episodes"] == 16
    assert resumed["timesteps"] == 16 * 30  # the counter continued, it did not restart


@pytest.mark.slow
@pytest.mark.training
def test_ddpg_trains_and_acts_inside_the_volume(tmp_path, test_file):
    out = tmp_path / "ddpg"
    meta = train(small_config(test_file, out, "ddpg", 6))
    assert meta["algorithm"] == "ddpg"
    agent = CheckpointPolicy.load(out)
    result = evaluate_policy(
        agent, generate_scenarios(2, 3, seed=5), replace(PAPER, episode_steps=5), progress=False
    )
    for row in result["scenarios"]:
        x, y, z = row["uav_xyz_m"]
        assert 0 <= x <= 500 and 0 <= y <= 500 and 25 <= z <= 100


def test_ddpg_critic_is_not_linear_in_the_action(test_file):
    """With no dense layer after the action joins the features, Q is linear in the action and
    the actor is driven to a corner of the volume; the presets put ReLU layers there."""
    from sim.files import load_scenarios

    _, scenarios = load_scenarios(test_file)
    for name in ("paper", "fast"):
        preset = replace(get_preset(name, "ddpg"), network=TINY_NET, buffer_size=1_000)
        env = make_env("ddpg", scenarios, replace(PAPER, area=AREA))
        model = build_model("ddpg", env, preset, seed=0, tensorboard_log=None)
        q_net = model.critic.q_networks[0]
        assert sum(isinstance(m, th.nn.ReLU) for m in q_net) == len(preset.critic_hidden) >= 1
        obs = th.as_tensor(env.reset(seed=0)[0][None])
        actions = th.linspace(0.0, 1.0, 21)[:, None].repeat(1, 3) * 2 - 1
        with th.no_grad():
            q = model.critic.q1_forward(obs.repeat(21, 1, 1, 1), actions).squeeze(1)
        second_difference = q[2:] - 2 * q[1:-1] + q[:-2]
        assert second_difference.abs().max() > 1e-6


def test_bad_checkpoints_are_refused_with_one_line(tmp_path, random_ddqn):
    good = tmp_path / "good.zip"
    meta = {"algorithm": "ddqn", "strategy": "spec", "observation_shape": [6, 20, 20]}
    save_checkpoint(random_ddqn, good, meta)
    load_checkpoint(good, AREA)  # fine
    with pytest.raises(InputError, match="no such checkpoint"):
        load_checkpoint(tmp_path / "missing.zip", AREA)
    with pytest.raises(InputError, match="algorithm: expected ddpg"):
        load_checkpoint(good, AREA, algorithm="ddpg")
    with pytest.raises(InputError, match="observation_shape"):
        load_checkpoint(good, AreaConfig(size_x_m=250, size_y_m=250))
    corrupt = tmp_path / "corrupt.zip"
    corrupt.write_bytes(good.read_bytes()[:200])
    corrupt.with_suffix(".json").write_text(good.with_suffix(".json").read_text())
    with pytest.raises(InputError, match="corrupt"):
        load_checkpoint(corrupt, AREA)
    no_meta = tmp_path / "nometa.zip"
    no_meta.write_bytes(good.read_bytes())
    with pytest.raises(InputError, match="metadata"):
        load_checkpoint(no_meta, AREA)
    for message in ("corrupt", "metadata", "observation_shape"):
        assert "\n" not in message


def test_train_cli_refuses_bad_arguments(tmp_path, test_file, capsys):
    assert main(["train", "--algo", "ddqn", "--episodes", "5"]) == 2
    assert "required" in capsys.readouterr().err
    args = ["train", "--algo", "ddqn", "--strategy", "spec", "--test-scenarios", str(test_file)]
    assert main([*args, "--episodes", "0", "--out", str(tmp_path / "x")]) == 2
    assert "--episodes" in capsys.readouterr().err
    assert not (tmp_path / "x" / "model.zip").exists()
    assert main(["train", "--resume", str(tmp_path / "nothing")]) == 2


def test_export_keeps_the_weights_and_drops_the_optimizer_state(tmp_path, random_ddqn):
    from policies.learned.checkpoints import export_checkpoint

    source = tmp_path / "trained.zip"
    meta = {"algorithm": "ddqn", "strategy": "spec", "observation_shape": [6, 20, 20]}
    save_checkpoint(random_ddqn, source, meta)
    model, _ = load_checkpoint(source, AREA)  # one optimizer step gives RMSprop a state
    obs = th.rand(4, *model.observation_space.shape)
    model.policy.q_net(obs).sum().backward()
    model.policy.optimizer.step()
    assert model.policy.optimizer.state_dict()["state"]
    save_checkpoint(model, source, meta)
    dest = tmp_path / "shipped" / "ddqn-x.zip"
    exported = export_checkpoint(source, dest, training_command="tupa train ...")
    assert exported["training_command"] == "tupa train ..."
    assert json.loads(dest.with_suffix(".json").read_text())["exported_from"]["path"] == str(source)
    original, _ = load_checkpoint(source, AREA)
    copy, _ = load_checkpoint(dest, AREA)
    assert not copy.policy.optimizer.state_dict()["state"]
    for (k1, v1), (k2, v2) in zip(
        original.policy.state_dict().items(), copy.policy.state_dict().items(), strict=True
    ):
        assert k1 == k2 and th.equal(v1, v2)


def test_a_checkpoint_saved_before_the_folders_loads_and_acts_as_saved(
    tmp_path, random_ddqn, monkeypatch
):
    """A checkpoint and a replay buffer pickled when the CNN was ``policies.networks.ZoneMapsCNN``
    and the DDQN's buffer ``policies.ddqn.MaskedReplayBuffer`` (before ``policies/`` went into
    folders; the shipped checkpoints were): loading finds both at their current paths, and the
    network is the one saved."""
    from gymnasium import spaces

    from policies.learned import ddqn, networks
    from policies.learned.checkpoints import load_replay_buffer, moved_objects

    source, replay = tmp_path / "old.zip", tmp_path / "old_replay.pkl"
    moved = {"policies.networks": networks.ZoneMapsCNN, "policies.ddqn": ddqn.MaskedReplayBuffer}
    with monkeypatch.context() as before:
        for name, cls in moved.items():
            module = types.ModuleType(name)
            setattr(module, cls.__name__, cls)
            before.setitem(sys.modules, name, module)
            before.setattr(cls, "__module__", name)
        meta = {"algorithm": "ddqn", "strategy": "spec", "observation_shape": [6, 20, 20]}
        save_checkpoint(random_ddqn, source, meta)
        buffer = ddqn.MaskedReplayBuffer(16, random_ddqn.observation_space, spaces.Discrete(13))
        replay.write_bytes(pickle.dumps(buffer))  # as SB3's save_replay_buffer writes it
    assert not set(moved) & set(sys.modules)
    assert sorted(moved_objects(source)) == ["policy_kwargs", "replay_buffer_class"]
    model, _ = load_checkpoint(source, AREA)
    assert model.policy_kwargs["features_extractor_class"] is networks.ZoneMapsCNN
    assert type(model.replay_buffer) is ddqn.MaskedReplayBuffer
    obs = th.rand(4, *model.observation_space.shape)
    with th.no_grad():
        assert th.equal(model.policy.q_net(obs), random_ddqn.policy.q_net(obs))
    load_replay_buffer(model, replay)
    assert type(model.replay_buffer) is ddqn.MaskedReplayBuffer
    assert model.replay_buffer.buffer_size == 16
    save_checkpoint(model, tmp_path / "new.zip", meta)
    assert moved_objects(tmp_path / "new.zip") == {}  # saved since: nothing to look up


@pytest.mark.parametrize("algorithm", ["ddpg", "ddqn"])
def test_a_serving_only_export_acts_as_the_source_and_is_smaller(tmp_path, test_file, algorithm):
    """The networks only learning uses are zeroed (deflate keeps them in kilobytes); the acting
    network is the source's bit for bit, and plain SB3 still loads the file."""
    from policies.learned.checkpoints import algorithm_class, export_checkpoint
    from sim.files import load_scenarios

    _, scenarios = load_scenarios(test_file)
    env = make_env(algorithm, scenarios, replace(PAPER, area=AREA))
    model = build_model(algorithm, env, tiny_preset(algorithm), seed=0, tensorboard_log=None)
    source = tmp_path / "trained.zip"
    save_checkpoint(model, source, {"algorithm": algorithm, "observation_shape": [6, 20, 20]})
    full, served = tmp_path / "full.zip", tmp_path / "served.zip"
    export_checkpoint(source, full)
    meta = export_checkpoint(source, served, serving_only=True)
    assert meta["serving_only"] is True
    assert served.stat().st_size < 0.7 * full.stat().st_size
    original, _ = load_checkpoint(source, AREA)
    copy = algorithm_class(algorithm).load(served, device="cpu")  # plain SB3
    obs = np.random.default_rng(1).random((32, *model.observation_space.shape), dtype=np.float32)
    np.testing.assert_array_equal(
        original.predict(obs, deterministic=True)[0], copy.predict(obs, deterministic=True)[0]
    )
    zeroed = (
        ("actor_target", "critic", "critic_target") if algorithm == "ddpg" else ("q_net_target",)
    )
    for name in zeroed:
        assert all(not t.any() for t in getattr(copy.policy, name).state_dict().values())
    acting = "actor" if algorithm == "ddpg" else "q_net"
    assert any(t.any() for t in getattr(copy.policy, acting).state_dict().values())


@pytest.mark.training
def test_training_across_environments_draws_one_per_episode(tmp_path, test_file):
    out = tmp_path / "towns"
    config = replace(
        small_config(test_file, out, "ddpg", 8), environments=("urban", "highrise-urban")
    )
    assert [w.area.environment for w in config.train_worlds(AREA)] == ["urban", "highrise-urban"]
    meta = train(config)
    assert meta["train_environments"] == ["highrise-urban", "urban"]
    assert meta["world"]["area"]["environment"] == "urban"  # evaluations: the first
    env = make_env("ddpg", generate_scenarios(2, 3, seed=5), config.train_worlds(AREA))
    seen = set()
    for seed in range(12):
        env.reset(seed=seed)
        seen.add(env.unwrapped.area.environment)
        assert env.unwrapped.model.area.environment == env.unwrapped.area.environment
    assert seen == {"urban", "highrise-urban"}
    with pytest.raises(InputError, match="--environment: must be among"):
        replace(config, environments=("urban", "downtown"))


def test_training_over_two_sites_draws_each_episodes_users_on_its_own_sites_ground(tmp_path):
    """Generated training scenarios over munich and etoile: one set per site, each episode's
    users from its own site's set (on its walkable ground); it used to be the first site's set
    for both, refused by the second site's ground at the first such episode."""
    from policies.training.training import _Run
    from sim.channel import area_site
    from sim.envs import ScenariosByEnvironment
    from sim.sites.ground import walkable_at

    munich = AreaConfig(environment="site:munich")
    etoile = AreaConfig(environment="site:etoile")
    candidates = generate_scenarios(40, 2, seed=11, area=munich)
    both = [s for s in candidates if walkable_at(area_site(etoile), s.users_xy_m).all()][:2]
    assert both, "no generated scenario stands on both sites' ground"
    test_file = tmp_path / "test.json"
    save_scenarios(test_file, munich, both)
    config = replace(
        small_config(test_file, tmp_path / "sites", "ddpg", 4),
        strategy="gen10k",
        environments=("site:munich", "site:etoile"),
    )
    run = _Run(config)
    assert isinstance(run.train_source, ScenariosByEnvironment)
    env = make_env("ddpg", run.train_source, config.train_worlds(run.area))
    seen = set()
    for seed in range(16):
        env.reset(seed=seed)
        base = env.unwrapped
        seen.add(base.area.environment)
        assert walkable_at(base.model.site, base.users.xy_m).all()
    assert seen == {"site:munich", "site:etoile"}
    assert train(config)["episodes"] == 4


def test_checkpoint_files_get_the_usual_permissions(tmp_path, random_ddqn):
    """Saved and exported zips are readable like any file the user writes (umask), not 0o600
    as the temporary files they are written through."""
    from policies.learned.checkpoints import export_checkpoint

    old_mask = os.umask(0o022)
    try:
        source = tmp_path / "trained.zip"
        meta = {"algorithm": "ddqn", "strategy": "spec", "observation_shape": [6, 20, 20]}
        save_checkpoint(random_ddqn, source, meta)
        dest = tmp_path / "ddqn-x.zip"
        export_checkpoint(source, dest)
    finally:
        os.umask(old_mask)
    for path in (source, dest, dest.with_suffix(".json")):
        assert path.stat().st_mode & 0o777 == 0o644, path


@pytest.mark.training
def test_ctrl_c_saves_latest_with_its_replay_buffer_and_resume_continues_the_cycle(
    tmp_path, test_file, monkeypatch
):
    """Ctrl-C (KeyboardInterrupt inside SB3's learn) after 4 episodes of a run asked to save its
    replay buffer: latest.zip and the buffer are saved, and --resume goes on with the 5th
    scenario of the cycle, its buffer full."""
    from policies.training import training
    from sim.envs import ScenarioCycle

    out = tmp_path / "run"
    original_on_step = training.TrainingCallback._on_step

    def interrupt_after_four(self):
        keep_going = original_on_step(self)
        if self.run.episodes_done >= 4:
            raise KeyboardInterrupt
        return keep_going

    monkeypatch.setattr(training.TrainingCallback, "_on_step", interrupt_after_four)
    config = replace(small_config(test_file, out, "ddqn", 12), save_replay_buffer=True)
    with pytest.raises(training.TrainingInterrupted) as stopped:
        train(config)
    assert stopped.value.exit_code == 130
    assert str(stopped.value).startswith("interrupted (Ctrl-C) after 4 of 12 episodes; saved ")
    assert "and its replay buffer (latest_replay.pkl)" in str(stopped.value)
    assert (out / "checkpoints" / "latest.zip").is_file()
    assert (out / "checkpoints" / "latest_replay.pkl").is_file()
    assert json.loads((out / training.RUN_FILE).read_text())["episodes_done"] == 4

    monkeypatch.setattr(training.TrainingCallback, "_on_step", original_on_step)
    visited: list[int] = []
    original_next = ScenarioCycle.next

    def recording_next(self, rng):
        visited.append(self._next)
        return original_next(self, rng)

    monkeypatch.setattr(ScenarioCycle, "next", recording_next)
    loaded_buffer_sizes: list[int] = []
    original_load = training.algorithm_class("ddqn").load_replay_buffer

    def recording_load(self, path, *args, **kwargs):
        original_load(self, path, *args, **kwargs)
        loaded_buffer_sizes.append(self.replay_buffer.size())

    monkeypatch.setattr(training.algorithm_class("ddqn"), "load_replay_buffer", recording_load)
    resumed = train(small_config(test_file, out, "ddqn", 8), resume=True)
    assert resumed["episodes"] == 8
    # Four episodes of 30 steps, less the last transition: SB3 stores it after the callback.
    assert loaded_buffer_sizes and loaded_buffer_sizes[0] >= 4 * 30 - 1
    # SB3 resets the env once when learn() starts: that first episode is the 5th scenario.
    assert visited[:4] == [4, 5, 0, 1]


@pytest.mark.slow
@pytest.mark.training
def test_vectorised_training_runs_and_counts_episodes(tmp_path, test_file):
    config = replace(small_config(test_file, tmp_path / "vec", "ddqn", 8), envs=4)
    meta = train(config)
    assert meta["episodes"] >= 8 and (tmp_path / "vec" / "model.zip").is_file()


def test_an_untrained_residual_ddpg_is_the_load_weighted_baseline(test_file):
    """The residual actor starts at 0: its targets are the load-weighted placements."""
    from policies.learned.residual import residual_target
    from policies.training.training import zero_actor_output
    from sim.files import load_scenarios

    _, scenarios = load_scenarios(test_file)
    env = make_env("ddpg", scenarios, replace(PAPER, area=AREA), action="residual")
    model = build_model("ddpg", env, tiny_preset("ddpg"), seed=0, tensorboard_log=None)
    zero_actor_output(model)
    weighted = make_placement("load-weighted")
    for seed in range(3):
        observation, info = env.reset(seed=seed)
        delta, _ = model.predict(observation, deterministic=True)
        np.testing.assert_array_equal(delta, np.zeros(3, dtype=np.float32))
        target = residual_target(delta, info["reports"], AREA)
        users = env.unwrapped.users
        expected = weighted.place(ReportedUsers(users.xy_m, users.load_bps))
        np.testing.assert_allclose(target, expected, atol=1e-9)


def test_bad_training_options_are_named(test_file, tmp_path):
    for changes, message in (
        ({"envs": 0}, "--envs"),
        ({"action": "residual"}, "--action"),  # a DDQN cannot take residual actions
        ({"world": "paper,mars"}, "world"),
        ({"families": ("volcano",)}, "famil"),
    ):
        with pytest.raises(InputError, match=message):
            replace(small_config(test_file, tmp_path / "x", "ddqn", 2), **changes)
