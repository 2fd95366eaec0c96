"""Offline training of a TUPA policy, top to bottom: data, environment, agent, callbacks, save.

``train(config)`` is what ``tupa train`` runs:

1. **Scenarios** by strategy (paper §IV-A): ``spec`` trains on the test set cycled in order;
   ``gen10k`` on as many unique generated scenarios as episodes, each once; ``gen500`` on 500
   unique scenarios cycled. Generated training scenarios use seed ``TRAIN_SEED_OFFSET + seed``,
   far from the seeds test sets are drawn with. ``families`` and ``users`` (a range) make each
   generated scenario draw its family and user count (:class:`sim.scenarios.ScenarioSampler`):
   one checkpoint for many kinds of scenario.
2. **Environment**: ``tupa/FapDiscrete`` for DDQN, ``tupa/FapContinuous`` for DDPG, in the
   run's world (``--world``, ``--world-set``: :mod:`sim.world`) with the preset's training
   episode (length and start). Learning-curve and final evaluations run in the same world with
   its own episode (100 steps from home).
3. **Agent** from the preset (``policies.training.presets``) with the paper's CNN
   (``policies.learned.networks.ZoneMapsCNN``); GPU when torch sees one, CPU otherwise.
4. **Callbacks**: progress on standard error (episodes, recent utility, time left:
   :class:`policies.training.progress.Progress`) and, once a few episodes have been timed with
   learning under way, one line with the estimated time of the whole run; TensorBoard logs; a
   checkpoint every ``checkpoint_every`` episodes (``checkpoints/latest.zip``); evaluations on part
   of the test set at 100, 200, 500, 1000, … episodes for the learning curve.
5. **Save**: ``checkpoints/latest.zip`` with the trained policy, then the final evaluation on
   the whole test set beside min-distance and the oracle (with its own progress), then
   ``model.zip`` and ``model.json`` (metadata with that evaluation), written atomically.

Ctrl-C, or SIGTERM (what ``timeout``, systemd and ``docker stop`` send), stops the run and
saves ``checkpoints/latest.zip`` and ``run.json`` (the replay buffer too, as
``latest_replay.pkl``, only with ``save_replay_buffer``: it is hundreds of megabytes); the
:class:`TrainingInterrupted` raised says what was saved where. ``train(config, resume=True)``
continues from it with the same step counter (and an empty replay buffer when none was saved).
"""

from __future__ import annotations

import json
import signal
import sys
import threading
import time
from collections import deque
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import asdict, dataclass, replace
from pathlib import Path
from typing import Any

import gymnasium as gym
import numpy as np
import torch as th
from stable_baselines3.common.callbacks import BaseCallback
from stable_baselines3.common.monitor import Monitor
from stable_baselines3.common.noise import NormalActionNoise

from policies.adapters import CheckpointPolicy
from policies.evaluation.evaluation import evaluate_policy
from policies.learned.checkpoints import (
    LATEST_CHECKPOINT,
    REPLAY_BUFFER,
    RUN_FILE,
    algorithm_class,
    git_commit,
    load_replay_buffer,
    moved_objects,
    save_checkpoint,
)
from policies.learned.networks import ZoneMapsCNN
from policies.learned.residual import residual_metadata
from policies.learned.residual_env import ResidualActions
from policies.registry import make_placement
from policies.training.presets import NetworkPreset, Preset, get_preset
from policies.training.progress import Progress, format_duration
from sim.atomic import atomic_write_json
from sim.config import (
    ENVIRONMENTS,
    AreaConfig,
    NetworkConfig,
    Queueing,
    check_environment,
    site_path,
)
from sim.envs import FapContinuousEnv, FapDiscreteEnv, ScenarioCycle, ScenariosByEnvironment
from sim.errors import InputError
from sim.files import load_scenarios, scenario_set_hash
from sim.observation import observation_shape
from sim.scenarios import Scenario, ScenarioSampler, check_scenario_area, generate_scenarios
from sim.world import World, get_world, world_with

STRATEGIES: tuple[str, ...] = ("spec", "gen10k", "gen500")
TRAIN_SEED_OFFSET = 1_000_000
GEN500_UNIQUE = 500
CURVE_POINTS: tuple[int, ...] = (100, 200, 500, 1_000, 2_000, 5_000, 10_000, 20_000, 50_000)
ESTIMATE_EPISODES = 3
"""Episodes timed, once learning has started, before the run's estimated time is said."""


def check_train_environment(environment: str) -> None:
    """InputError naming ``--environment`` unless ``environment`` is a channel environment
    (:data:`sim.config.ENVIRONMENTS`) or a sound ``site:PATH`` on disk."""
    if site_path(environment) is None and environment not in ENVIRONMENTS:
        raise InputError(
            f"--environment: must be among {', '.join(ENVIRONMENTS)} or site:PATH, "
            f"got {environment!r}"
        )
    check_environment(environment, "--environment", on_disk=True)


@dataclass(frozen=True)
class TrainConfig:
    """One training run. ``preset`` holds every hyper-parameter (see
    ``policies.training.presets``)."""

    algorithm: str
    strategy: str
    episodes: int
    preset: Preset
    seed: int
    test_scenarios: Path
    out_dir: Path
    queueing: Queueing = "fq-codel"
    world: str = "paper"  # one preset, or several separated by commas (one drawn per episode)
    world_set: tuple[str, ...] = ()
    # Channel environments (sim.config.ENVIRONMENTS) the episodes draw from, one per episode
    # with the world; empty: the world's own (the test set's, or --world-set environment=).
    environments: tuple[str, ...] = ()
    families: tuple[str, ...] = ("exponential",)
    users: tuple[int, int] | None = None  # None: the test set's user count
    action: str = "coordinates"  # DDPG: "coordinates" (the paper) or "residual"
    envs: int = 1  # episodes stepping as one batch (sim.vector_env); 1: one environment
    checkpoint_every: int = 500
    curve_scenarios: int = 100
    final_eval: bool = True
    progress: bool = True
    save_replay_buffer: bool = False  # on an interruption, beside latest.zip (large)

    def __post_init__(self) -> None:
        if self.strategy not in STRATEGIES:
            raise InputError(
                f"--strategy: must be one of {', '.join(STRATEGIES)}, got {self.strategy!r}"
            )
        if self.episodes < 1:
            raise InputError(f"--episodes: must be at least 1, got {self.episodes}")
        if self.checkpoint_every < 1:
            raise InputError(f"--checkpoint-every: must be at least 1, got {self.checkpoint_every}")
        if self.seed < 0:
            raise InputError(f"--seed: must be >= 0, got {self.seed}")
        if self.envs < 1:
            raise InputError(f"--envs: must be at least 1, got {self.envs}")
        for environment in self.environments:
            check_train_environment(environment)
        if self.envs > 1 and (
            self.action == "residual" or "," in self.world or len(self.environments) > 1
        ):
            raise InputError(
                "--envs: more than 1 needs one world, one environment and coordinates or moves "
                "(not residual)"
            )
        if self.action not in ("coordinates", "residual") or (
            self.action == "residual" and self.algorithm != "ddpg"
        ):
            raise InputError(
                f"--action: 'coordinates' or, for ddpg, 'residual'; got {self.action!r} "
                f"for {self.algorithm}"
            )
        self.train_worlds(AreaConfig())  # an unknown world or setting fails here, named
        self.sampler(AreaConfig(), 3)  # and so do unknown families or user counts

    def _worlds(self, area: AreaConfig) -> list[World]:
        network = NetworkConfig().with_queueing(self.queueing)
        names = [name.strip() for name in self.world.split(",")]
        worlds = [
            world_with(replace(get_world(name), area=area, network=network), self.world_set)
            for name in names
        ]
        if not self.environments:
            return worlds
        return [world_with(w, {"environment": e}) for w in worlds for e in self.environments]

    def eval_world(self, area: AreaConfig) -> World:
        """The run's (first) world over ``area``: where its evaluations run."""
        return self._worlds(area)[0]

    def train_worlds(self, area: AreaConfig) -> list[World]:
        """The run's worlds with the preset's training episode (length, start)."""
        return [
            replace(w, episode_steps=self.preset.train_episode_steps, home=self.preset.train_start)
            for w in self._worlds(area)
        ]

    def sampler(self, area: AreaConfig, test_users: int) -> ScenarioSampler:
        """What generated training scenarios are drawn from."""
        users = self.users or (test_users, test_users)
        return ScenarioSampler(families=self.families, users=users, area=area)

    def to_dict(self) -> dict[str, Any]:
        d = asdict(self)
        d["test_scenarios"] = str(self.test_scenarios)
        d["out_dir"] = str(self.out_dir)
        d["world_set"] = list(self.world_set)
        d["environments"] = list(self.environments)
        d["families"] = list(self.families)
        d["users"] = list(self.users) if self.users else None
        return d

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> TrainConfig:
        d = dict(d)
        p = dict(d.pop("preset"))
        p["network"] = NetworkPreset(
            **{**p["network"], "channels": tuple(p["network"]["channels"])}
        )
        if "critic_hidden" in p:
            p["critic_hidden"] = tuple(p["critic_hidden"])
        d["world_set"] = tuple(d.get("world_set", ()))
        d["environments"] = tuple(d.get("environments", ()))
        d["families"] = tuple(d.get("families", ("exponential",)))
        d["users"] = tuple(d["users"]) if d.get("users") else None
        return cls(
            **{
                **d,
                "preset": Preset(**p),
                "test_scenarios": Path(d["test_scenarios"]),
                "out_dir": Path(d["out_dir"]),
            }
        )


def training_scenarios(
    strategy: str,
    episodes: int,
    test: list[Scenario],
    area: AreaConfig,
    seed: int,
    sampler: ScenarioSampler | None = None,
) -> list[Scenario]:
    """The scenarios a strategy trains on, in the order the episodes visit them (cycled).

    Generated ones come from the paper's generator with the test set's user count, or, given a
    ``sampler`` that draws families or user counts, from it."""
    if strategy == "spec":
        return list(test)
    n_users = test[0].n_users
    count = episodes if strategy == "gen10k" else min(GEN500_UNIQUE, episodes)
    if sampler is None or (
        sampler.families == ("exponential",) and sampler.users == (n_users,) * 2
    ):
        return generate_scenarios(count, n_users, seed=TRAIN_SEED_OFFSET + seed, area=area)
    rng = np.random.default_rng(TRAIN_SEED_OFFSET + seed)
    return [sampler.sample(rng) for _ in range(count)]


def make_env(
    algorithm: str,
    scenarios: list[Scenario] | ScenariosByEnvironment,
    world: World | list[World],
    action: str = "coordinates",
) -> gym.Env:
    """The training environment: discrete moves for DDQN; absolute coordinates for DDPG, or a
    correction to the load-weighted placement with ``action="residual"``
    (:mod:`policies.learned.residual`). A list of scenarios is cycled; a per-environment source is
    drawn from by each episode's environment."""
    env: gym.Env
    source = (
        scenarios if isinstance(scenarios, ScenariosByEnvironment) else ScenarioCycle(scenarios)
    )
    if algorithm == "ddqn":
        env = FapDiscreteEnv(source, world=world)
    else:
        env = FapContinuousEnv(source, world=world)
        if action == "residual":
            env = ResidualActions(env)
    return Monitor(env)


def zero_actor_output(model: Any) -> None:
    """Start a DDPG actor (and its target) at action 0: the residual policy's prior."""
    for actor in (model.actor, model.actor_target):
        last = [m for m in actor.mu if isinstance(m, th.nn.Linear)][-1]
        with th.no_grad():
            last.weight.zero_()
            last.bias.zero_()


def build_model(
    algorithm: str, env: gym.Env, preset: Preset, seed: int, tensorboard_log: Path | None
) -> Any:
    """The SB3 agent for ``preset`` on ``env`` (CUDA when available)."""
    optimizer = th.optim.RMSprop if preset.optimizer == "rmsprop" else th.optim.Adam
    net = preset.network
    extractor_kwargs = {
        "channels": net.channels,
        "hidden": net.hidden,
        "features_dim": net.features_dim,
        "dropout": net.dropout,
    }
    common: dict[str, Any] = {
        "learning_rate": preset.learning_rate,
        "buffer_size": preset.buffer_size,
        "learning_starts": preset.learning_starts,
        "batch_size": preset.batch_size,
        "tau": preset.tau,
        "gamma": preset.gamma,
        "train_freq": preset.train_freq,
        "gradient_steps": preset.gradient_steps,
        "seed": seed,
        "device": "auto",
        "tensorboard_log": str(tensorboard_log) if tensorboard_log else None,
        "verbose": 0,
    }
    if algorithm == "ddqn":
        return algorithm_class("ddqn")(
            "CnnPolicy",
            env,
            target_update_interval=preset.target_update_interval,
            epsilon_start=preset.epsilon_start,
            epsilon_decay_per_episode=preset.epsilon_decay_per_episode,
            epsilon_min=preset.epsilon_min,
            loss=preset.loss,
            policy_kwargs={
                "features_extractor_class": ZoneMapsCNN,
                "features_extractor_kwargs": extractor_kwargs,
                "net_arch": [],
                "normalize_images": False,
                "optimizer_class": optimizer,
            },
            **common,
        )
    n_actions = env.action_space.shape[0]
    return algorithm_class("ddpg")(
        "CnnPolicy",
        env,
        target_update_interval=preset.target_update_interval,
        loss=preset.loss,
        action_l2=preset.action_l2,
        action_noise=NormalActionNoise(
            np.zeros(n_actions), preset.action_noise_sigma * np.ones(n_actions)
        ),
        policy_kwargs={
            "features_extractor_class": ZoneMapsCNN,
            "features_extractor_kwargs": extractor_kwargs,
            # The actor maps features straight to the 3 coordinates; the critic needs dense
            # layers after the action joins the features (see Preset.critic_hidden).
            "net_arch": {"pi": [], "qf": list(preset.critic_hidden)},
            "normalize_images": False,
            "optimizer_class": optimizer,
        },
        **common,
    )


def episode_bar(total: int, desc: str, initial: int = 0) -> Any:
    """A training run's progress bar on stderr, counted in episodes (tqdm: rate and ETA); the
    caller shows the recent utility beside it."""
    from tqdm import tqdm

    return tqdm(total=total, initial=initial, desc=desc, unit="ep", dynamic_ncols=True)


class TrainingCallback(BaseCallback):
    """Progress (with the time left) and the run's estimated time, periodic checkpoints and
    learning-curve evaluations, counted in episodes.

    The estimate is said once, after :data:`ESTIMATE_EPISODES` episodes have been timed with
    learning under way (the episodes before ``learning_starts`` train nothing, and are much
    faster): the time the run has taken so far plus the episodes left at the timed pace.
    """

    def __init__(self, run: _Run) -> None:
        super().__init__()
        self.run = run
        self.recent_utility: deque[float] = deque(maxlen=50)
        self.progress: Progress | None = None
        self._timed_from: tuple[float, int] | None = None  # (time, episodes) learning started
        self._estimated = False

    @property
    def label(self) -> str:
        return f"{self.run.config.algorithm}-{self.run.config.strategy}"

    def _on_training_start(self) -> None:
        config = self.run.config
        self.progress = Progress(
            config.episodes,
            self.label,
            "ep",
            initial=self.run.episodes_done,
            enabled=config.progress,
        )

    def _on_step(self) -> bool:
        for info in self.locals.get("infos", []):
            episode = info.get("episode")
            if episode is None:
                continue
            self.run.episodes_done += 1
            self.recent_utility.append(episode["r"] / max(episode["l"], 1))
            if self.progress is not None:
                self.progress.update(1, utility=f"{np.mean(self.recent_utility):.3f}")
                self._estimate()
            self.logger.record("rollout/episode_utility", float(np.mean(self.recent_utility)))
            done = self.run.episodes_done
            if done % self.run.config.checkpoint_every == 0 and done < self.run.config.episodes:
                self.run.save_latest(self.model)
            if done in CURVE_POINTS and done <= self.run.config.episodes:
                self.run.add_curve_point(self.model, done)
        return self.run.episodes_done < self.run.config.episodes

    def _estimate(self) -> None:
        """Time the first episodes that learn; say the run's estimated time once."""
        if self._estimated or self.progress is None or not self.progress.enabled:
            return
        if self.model.num_timesteps < self.model.learning_starts:
            return
        now, done = time.monotonic(), self.run.episodes_done
        if self._timed_from is None:
            self._timed_from = (now, done)
            return
        since, first = self._timed_from
        timed = done - first
        if timed < ESTIMATE_EPISODES:
            return
        self._estimated = True
        config = self.run.config
        per_episode = (now - since) / timed
        total = self.progress.elapsed_s() + per_episode * max(config.episodes - done, 0)
        todo = config.episodes - self.progress.initial
        which = f"{todo} episodes" if not self.progress.initial else f"the {todo} episodes left"
        then = (
            f", then the final evaluation on the {len(self.run.test)} test scenarios"
            if config.final_eval
            else ""
        )
        self.progress.write(
            f"{self.label}: about {format_duration(total)} for {which} ({per_episode:.2f} s an "
            f"episode, timed over episodes {first + 1}-{done} once learning started){then}"
        )

    def close(self) -> None:
        """End the progress (also when the run stopped early)."""
        if self.progress is not None:
            self.progress.close()


class _Run:
    """State of one run shared by the trainer and its callback: data, counters, files."""

    def __init__(
        self, config: TrainConfig, episodes_done: int = 0, wall_time_s: float = 0.0
    ) -> None:
        self.config = config
        self.area, self.test = load_scenarios(config.test_scenarios)
        # On a site (--environment site:PATH) the test users must stand on its walkable
        # ground, and generated training users are drawn there (the first site's area).
        site_areas = [
            w.area for w in config.train_worlds(self.area) if site_path(w.area.environment)
        ]
        for site_area in site_areas:
            for scenario in self.test:
                check_scenario_area(
                    scenario, site_area, f"{config.test_scenarios}: scenario {scenario.id}: "
                )
        drawn_in = site_areas[0] if site_areas else self.area
        self.train_set = training_scenarios(
            config.strategy,
            config.episodes,
            self.test,
            drawn_in,
            config.seed,
            config.sampler(drawn_in, self.test[0].n_users) if self.test else None,
        )
        # Several sites: each environment's own generated set, its users on its own ground
        # (the first site's set above is the one the run's metadata hashes).
        self.train_source: list[Scenario] | ScenariosByEnvironment = self.train_set
        if len({a.environment for a in site_areas}) > 1 and config.strategy != "spec":
            areas = {w.area.environment: w.area for w in config.train_worlds(self.area)}
            self.train_source = ScenariosByEnvironment(
                {
                    environment: ScenarioCycle(
                        training_scenarios(
                            config.strategy,
                            config.episodes,
                            self.test,
                            area,
                            config.seed,
                            config.sampler(area, self.test[0].n_users),
                        )
                    )
                    for environment, area in areas.items()
                }
            )
        self.episodes_done = episodes_done
        self.wall_time_before_s = wall_time_s
        self.started = time.monotonic()
        self.curve_path = config.out_dir / "learning_curve.json"
        self.curve_test = self.test[: config.curve_scenarios]
        self.world = config.eval_world(self.area)

    @property
    def wall_time_s(self) -> float:
        return self.wall_time_before_s + time.monotonic() - self.started

    def metadata(self, model: Any, evaluation: dict[str, Any] | None = None) -> dict[str, Any]:
        c = self.config
        return {
            "algorithm": c.algorithm,
            **residual_metadata(c.action),
            "strategy": c.strategy,
            "preset": c.preset.to_dict(),
            "episodes": self.episodes_done,
            "timesteps": int(model.num_timesteps),
            "seed": c.seed,
            "queueing": c.queueing,
            "world": self.world.to_dict(),
            "train_worlds": [w.name for w in c.train_worlds(self.area)],
            "train_environments": sorted({w.area.environment for w in c.train_worlds(self.area)}),
            "families": list(c.families),
            "users": list(c.users) if c.users else None,
            "n_users": self.test[0].n_users,
            "observation_shape": list(observation_shape(self.area)),
            "area": self.area.to_dict(),
            "scenario_set_hash": scenario_set_hash(self.area, self.train_set),
            "test_set_hash": scenario_set_hash(self.area, self.test),
            "git_commit": git_commit(),
            "device": str(model.device),
            "wall_time_s": round(self.wall_time_s, 1),
            "evaluation": evaluation,
        }

    def save_latest(self, model: Any, with_replay_buffer: bool = False) -> None:
        checkpoint = self.config.out_dir / LATEST_CHECKPOINT
        save_checkpoint(model, checkpoint, self.metadata(model))
        if with_replay_buffer:
            model.save_replay_buffer(checkpoint.with_name(REPLAY_BUFFER))
        atomic_write_json(
            self.config.out_dir / RUN_FILE,
            {
                "config": self.config.to_dict(),
                "episodes_done": self.episodes_done,
                "wall_time_s": self.wall_time_s,
            },
        )

    def evaluate(
        self, model: Any, scenarios: list[Scenario], on_scenario: Any = None
    ) -> dict[str, Any]:
        c = self.config
        metadata = {"algorithm": c.algorithm, "strategy": c.strategy, **residual_metadata(c.action)}
        agent = CheckpointPolicy(model, metadata, world=self.world)
        return evaluate_policy(
            agent, scenarios, self.world, seed=0, progress=False, on_scenario=on_scenario
        )

    def interrupted(
        self, model: Any, stop: KeyboardInterrupt, during: str | None = None
    ) -> TrainingInterrupted:
        """Save what resumes the run (further signals held off meanwhile) and say so: the
        :class:`TrainingInterrupted` to raise."""
        terminated = isinstance(stop, _Terminated)
        out, c = self.config.out_dir, self.config
        with _signals_held():
            self.save_latest(model, with_replay_buffer=c.save_replay_buffer)
        where = (
            f"during {during}, after all {self.episodes_done} episodes"
            if during
            else f"after {self.episodes_done} of {c.episodes} episodes"
        )
        replay = f" and its replay buffer ({REPLAY_BUFFER})" if c.save_replay_buffer else ""
        message = (
            f"interrupted ({'SIGTERM' if terminated else 'Ctrl-C'}) {where}; saved "
            f"{out / LATEST_CHECKPOINT}{replay}: tupa train --resume {out} continues it, "
            f"tupa eval --policy {out} evaluates it"
        )
        return TrainingInterrupted(message, signal.SIGTERM if terminated else signal.SIGINT)

    def add_curve_point(self, model: Any, episodes: int) -> None:
        from policies.report.curves import write_learning_curve

        result = self.evaluate(model, self.curve_test)
        curve = json.loads(self.curve_path.read_text()) if self.curve_path.exists() else None
        points = curve["curves"][0]["points"] if curve else []
        points = [p for p in points if p["episodes"] != episodes]
        points.append(
            {
                "episodes": episodes,
                "median_utility": result["median_utility"],
                "mean_utility": result["mean_utility"],
            }
        )
        reference = curve["reference"] if curve else self.reference_medians()
        label = f"{self.config.algorithm}-{self.config.strategy}"
        write_learning_curve(
            self.curve_path,
            [{"label": label, "points": sorted(points, key=lambda p: p["episodes"])}],
            reference,
        )

    def reference_medians(self) -> dict[str, float]:
        medians = {}
        for name in ("min-distance", "oracle"):
            policy = make_placement(name, self.world)
            medians[name] = evaluate_policy(
                policy, self.curve_test, self.world, seed=0, progress=False
            )["median_utility"]
        return medians


class TrainingInterrupted(KeyboardInterrupt):
    """A run stopped by Ctrl-C or SIGTERM, after saving what resumes it. The message is one
    line saying when it stopped and what was saved where; ``exit_code`` is the shell's for the
    signal (130 for Ctrl-C, 143 for SIGTERM)."""

    def __init__(self, message: str, signal_number: int = signal.SIGINT) -> None:
        super().__init__(message)
        self.exit_code = 128 + int(signal_number)


class _Terminated(KeyboardInterrupt):
    """SIGTERM, raised wherever the run is, as Ctrl-C raises ``KeyboardInterrupt``."""

    exit_code = 128 + signal.SIGTERM


@contextmanager
def _sigterm_stops_training() -> Iterator[None]:
    """While the block runs (in the main thread only: signals go there), SIGTERM stops it as
    Ctrl-C does; the previous handler is put back after."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return

    def terminate(signum: int, frame: object) -> None:
        raise _Terminated

    previous = signal.signal(signal.SIGTERM, terminate)
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, previous)


@contextmanager
def _signals_held() -> Iterator[None]:
    """Ctrl-C and SIGTERM ignored while the block runs (the save after an interruption: a
    second Ctrl-C must not cut it short), in the main thread; handlers put back after."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    previous = {s: signal.signal(s, signal.SIG_IGN) for s in (signal.SIGINT, signal.SIGTERM)}
    try:
        yield
    finally:
        for number, handler in previous.items():
            signal.signal(number, handler)


def train(config: TrainConfig, resume: bool = False) -> dict[str, Any]:
    """Run (or, with ``resume``, continue) a training run; returns the final metadata.

    Ctrl-C or SIGTERM (while this runs in the main thread) saves the latest checkpoint and
    raises :class:`TrainingInterrupted` saying where (see the module doc)."""
    with _sigterm_stops_training():
        return _train(config, resume)


def _train(config: TrainConfig, resume: bool) -> dict[str, Any]:
    run_state = _read_run(config.out_dir) if resume else None
    run = _Run(config, *(run_state or (0, 0.0)))
    if not run.test:
        raise InputError(f"{config.test_scenarios}: scenarios: empty")
    if config.envs > 1:
        from policies.training.vec_env import make_vec_env

        env: Any = make_vec_env(
            config.algorithm, run.train_source, config.train_worlds(run.area), config.envs
        )
    else:
        env = make_env(
            config.algorithm, run.train_source, config.train_worlds(run.area), config.action
        )
    latest = config.out_dir / LATEST_CHECKPOINT
    if resume:
        model = algorithm_class(config.algorithm).load(
            latest, env=env, device="auto", custom_objects=moved_objects(latest)
        )
        replay = latest.with_name(REPLAY_BUFFER)
        if replay.exists():
            load_replay_buffer(model, replay)
        elif config.progress:
            print(
                f"resuming {config.out_dir} with an empty replay buffer (none was saved: "
                "--save-replay-buffer keeps it on an interruption)",
                file=sys.stderr,
            )
        # Episodes visit the training set in order: continue where the run stopped.
        scenarios = env.unwrapped.scenarios
        by_environment = isinstance(scenarios, ScenariosByEnvironment)
        cycles = scenarios.sources.values() if by_environment else [scenarios]
        for cycle in cycles:  # every environment's cycle by as many episodes (an upper bound)
            cycle._next = run.episodes_done % len(cycle.scenarios)
    else:
        config.out_dir.mkdir(parents=True, exist_ok=True)
        model = build_model(
            config.algorithm, env, config.preset, config.seed, config.out_dir / "tb"
        )
        if config.action == "residual":
            zero_actor_output(model)
    total_timesteps = config.episodes * config.preset.train_episode_steps
    callback = TrainingCallback(run)
    try:
        model.learn(
            total_timesteps=max(total_timesteps - model.num_timesteps, 1),
            callback=callback,
            reset_num_timesteps=not resume,
            tb_log_name=f"{config.algorithm}-{config.strategy}",
        )
    except KeyboardInterrupt as stop:
        callback.close()
        raise run.interrupted(model, stop) from None
    finally:  # flushes TensorBoard's last events and ends its writer thread
        callback.close()
        if getattr(model, "_logger", None) is not None:  # None: learn failed before setting it
            model.logger.close()
    try:
        run.save_latest(model)  # the trained policy on disk before the (long) final evaluation
        evaluation = final_evaluation(run, model) if config.final_eval else None
    except KeyboardInterrupt as stop:
        raise run.interrupted(model, stop, during="the final evaluation") from None
    metadata = run.metadata(model, evaluation)
    save_checkpoint(model, config.out_dir / "model.zip", metadata)
    return metadata


def final_evaluation(run: _Run, model: Any) -> dict[str, Any]:
    """The trained policy on the whole test set, beside min-distance and the oracle, with one
    progress over the three (they can take minutes)."""
    progress = Progress(
        3 * len(run.test), "final evaluation", "scenarios", enabled=run.config.progress
    )
    progress.write(
        f"final evaluation on the {len(run.test)} test scenarios: the trained policy, "
        "min-distance and the oracle"
    )
    try:
        per_policy = {"policy": run.evaluate(model, run.test, on_scenario=progress.update)}
        for name in ("min-distance", "oracle"):
            per_policy[name] = evaluate_policy(
                make_placement(name, run.world),
                run.test,
                run.world,
                seed=0,
                progress=False,
                on_scenario=progress.update,
            )
    finally:
        progress.close()
    summary: dict[str, Any] = {}
    for name in ("min-distance", "oracle", "policy"):
        result = per_policy[name]
        summary[name] = {k: result[k] for k in ("mean_utility", "median_utility", "p25_utility")}
    oracle = per_policy["oracle"]["mean_utility"]
    summary["ratio_to_oracle"] = per_policy["policy"]["mean_utility"] / oracle
    summary["n_scenarios"] = len(run.test)
    return summary


def _read_run(out_dir: Path) -> tuple[int, float]:
    path = out_dir / RUN_FILE
    if not (out_dir / LATEST_CHECKPOINT).exists() or not path.exists():
        raise InputError(
            f"--resume: {out_dir} holds no interrupted run (no checkpoints/latest.zip)"
        )
    state = json.loads(path.read_text())
    return int(state["episodes_done"]), float(state["wall_time_s"])


def resume_config(
    out_dir: Path, episodes: int | None = None, save_replay_buffer: bool = False
) -> TrainConfig:
    """The configuration of the run in ``out_dir`` (optionally with a new episode target, and
    saving the replay buffer on an interruption from now on)."""
    path = out_dir / RUN_FILE
    if not path.exists():
        raise InputError(f"--resume: {out_dir} holds no training run ({RUN_FILE} missing)")
    config = TrainConfig.from_dict(json.loads(path.read_text())["config"])
    if save_replay_buffer:
        config = replace(config, save_replay_buffer=True)
    return replace(config, episodes=episodes) if episodes else config


def config_from_args(
    algorithm: str,
    strategy: str,
    episodes: int,
    preset: str,
    seed: int,
    test_scenarios: Path,
    out_dir: Path,
    **kwargs: Any,
) -> TrainConfig:
    try:
        chosen = get_preset(preset, algorithm, kwargs.get("action", "coordinates"))
    except ValueError as exc:
        raise InputError(f"--{exc}") from None
    return TrainConfig(
        algorithm, strategy, episodes, chosen, seed, test_scenarios, out_dir, **kwargs
    )
