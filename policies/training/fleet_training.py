"""Learned cooperative fleet policies: one DDPG or DDQN network shared by every UAV of a fleet.

Parameter sharing (Gupta et al. 2017): every agent of :class:`sim.fleet_env.FleetParallelEnv`
sees its own observation (9 maps, the same channels for any K) and gets the same reward (the
network utility over all users); one stable-baselines3 agent learns from the transitions of all
of them. The PettingZoo → SB3 bridge is SuperSuit: ``pettingzoo_env_to_vec_env_v1`` turns one
fleet of K agents into a vector env of K environments, ``concat_vec_envs_v1`` stacks
``n_fleets`` fleets into one SB3 ``VecEnv`` of ``n_fleets × K`` environments. Because the
parameters are shared, the checkpoint flies any K (1..8), not only the K it trained with.

* :func:`train_fleet` (``tupa train --uavs K``): builds that vector env over the world's
  preset (the training episode of the :mod:`policies.training.presets` preset: length and start),
  the agent with the paper's CNN (:func:`policies.training.training.build_model`, 9 input channels):
  DDPG with absolute coordinates or residual actions around a k-means placement
  (:mod:`policies.learned.fleet_residual`: ``kmeans-load-weighted``, or ``kmeans-scored`` with
  ``--prior``), or the masked Double DQN over the 13 moves; learns
  ``episodes × episode_steps × K`` agent-steps with a progress bar and writes ``model.zip`` +
  ``model.json`` (:func:`policies.learned.checkpoints.save_checkpoint`). DDQN's ε decays per episode
  of each agent (SB3 counts the K agent-environments' episodes), so K times faster per fleet
  episode than the preset's rate says.
* :class:`~policies.learned.fleet_checkpoint.FleetCheckpointPolicy` (its own module): such a
  checkpoint deciding K targets from K observations.

Evaluation (the checkpoint against the k-means baselines and the search oracle) lives in
:mod:`policies.evaluation.fleet_evaluation`.

Update ratio: a vector step gives ``n_fleets × K`` transitions, so the preset's
``train_freq`` (environment steps per gradient step) is re-expressed per vector step
(``train_freq // n_envs`` vector steps, ``n_envs // train_freq`` gradient steps each, at least
one of both), keeping about one gradient step per ``train_freq`` transitions.
"""

from __future__ import annotations

import shlex
import sys
import tempfile
import time
from collections import deque
from dataclasses import asdict, dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np
import supersuit as ss
from stable_baselines3.common.callbacks import BaseCallback
from stable_baselines3.common.vec_env import VecMonitor
from supersuit.vector.sb3_vector_wrapper import SB3VecEnvWrapper

from policies.learned.checkpoints import git_commit, save_checkpoint
from policies.learned.fleet_checkpoint import FLEET_ALGORITHMS, fleet_observation_shape
from policies.learned.fleet_residual import DEFAULT_PRIOR, PRIORS
from policies.learned.fleet_residual_env import FleetResidualActions
from policies.learned.residual import RESIDUAL_RADIUS_M, residual_metadata
from policies.training.fleet_imitation import (
    TEACHERS,
    ImitationConfig,
    TeacherData,
    collect_teacher_data,
    fit_actor,
)
from policies.training.presets import PRESET_NAMES, Preset, get_preset
from policies.training.training import (
    TRAIN_SEED_OFFSET,
    build_model,
    check_train_environment,
    episode_bar,
    zero_actor_output,
)
from sim.config import AreaConfig
from sim.errors import InputError
from sim.fleet import MAX_UAVS
from sim.fleet_env import FleetParallelEnv
from sim.scenarios import ScenarioSampler
from sim.world import World, get_world, world_with

__all__ = ["FleetTrainConfig", "train_fleet"]


@dataclass(frozen=True)
class FleetTrainConfig:
    """One fleet training run.

    ``episodes`` counts fleet episodes (each ``preset.train_episode_steps`` decisions of all K
    UAVs); ``n_fleets`` fleets step as one batch. Training scenarios are drawn by a
    :class:`sim.scenarios.ScenarioSampler` over ``families`` and ``users`` (an inclusive
    range) with a total offered load of ``load_per_uav_bps × K``. ``preset`` is a preset name
    (``paper``, ``fast``) or a :class:`policies.training.presets.Preset`."""

    n_uavs: int
    episodes: int
    out_dir: Path
    algorithm: str = "ddpg"
    preset: str | Preset = "fast"
    seed: int = 1
    world: str = "closed-loop"
    environment: str | None = None
    """The channel environment the fleet trains in (``--environment``: a town class or
    ``site:PATH``); None: the world's own (the open field)."""
    families: tuple[str, ...] = ("uniform", "hotspots", "mixture")
    users: tuple[int, int] = (20, 20)
    load_per_uav_bps: float = 40e6
    n_fleets: int = 1
    action: str = "coordinates"
    """``coordinates`` (each agent's absolute target) or ``residual`` (a correction to its
    place in the ``kmeans-load-weighted`` placement: :mod:`policies.learned.fleet_residual`)."""
    residual_radius_m: float = RESIDUAL_RADIUS_M
    """How far (m, per axis) a residual action may move a UAV from its k-means place."""
    prior: str = DEFAULT_PRIOR
    """The placement residual actions correct (:data:`policies.learned.fleet_residual.PRIORS`):
    ``kmeans-load-weighted``, or ``kmeans-scored`` scored over the world's evaluation episode
    (``--prior``)."""
    imitate: int = 0
    """Teacher episodes flown by the search oracle whose decisions the residual actor or the
    DDQN's moves are fitted to before any reinforcement learning
    (:mod:`policies.training.fleet_imitation`); 0: none."""
    imitate_teacher: str = "search"
    """Which oracle search teaches (:data:`policies.training.fleet_imitation.TEACHERS`)."""
    imitate_symmetries: bool = False
    """Fit under the area's eight symmetries (:attr:`ImitationConfig.symmetries`)."""
    imitate_rounds: int = 0
    """DAgger rounds after the first fit (Ross, Gordon & Bagnell 2011): each flies ``imitate``
    more episodes with the fitted policy, the teacher labelling every state the learner
    visits, and refits on all the data so far (``--dagger R``)."""
    imitate_replan_every: int = 30
    """Decisions a teacher placement is held (the training episode's length: one search each)."""
    workers: int = 1
    """Processes the teacher episodes are spread over (the same data for any count)."""
    command: str | None = None
    progress: bool = True
    """A progress bar on stderr (fleet episodes, recent utility, ETA)."""

    def __post_init__(self) -> None:
        k = self.n_uavs
        if isinstance(k, bool) or not isinstance(k, int | np.integer) or not 1 <= k <= MAX_UAVS:
            raise InputError(f"--uavs: must be an integer in 1..{MAX_UAVS}, got {k!r}")
        if self.algorithm not in FLEET_ALGORITHMS:
            raise InputError(
                f"--algo: fleets train with {' or '.join(FLEET_ALGORITHMS)}, got {self.algorithm!r}"
            )
        if isinstance(self.preset, str) and self.preset not in PRESET_NAMES:
            raise InputError(
                f"--preset: must be one of {', '.join(PRESET_NAMES)}, got {self.preset!r}"
            )
        if self.episodes < (0 if self.imitate else 1):
            raise InputError(
                f"--episodes: must be at least {0 if self.imitate else 1}, got {self.episodes}"
            )
        if self.imitate < 0:
            raise InputError(f"--imitate: must be >= 0 teacher episodes, got {self.imitate}")
        if self.imitate and (self.algorithm, self.action) == ("ddpg", "coordinates"):
            raise InputError(
                "--imitate: fits a residual actor (--algo ddpg --action residual) or the "
                "DDQN's moves (--algo ddqn)"
            )
        if self.imitate_teacher not in TEACHERS:
            raise InputError(
                f"--teacher: one of {', '.join(TEACHERS)}, got {self.imitate_teacher!r}"
            )
        if isinstance(self.imitate_rounds, bool) or self.imitate_rounds < 0:
            raise InputError(f"--dagger: must be >= 0 rounds, got {self.imitate_rounds!r}")
        if self.imitate_rounds and not self.imitate:
            raise InputError("--dagger: refits --imitate N's policy, so only with it")
        if self.imitate_symmetries and not self.imitate:
            raise InputError("--symmetries: fits --imitate N's teacher data, so only with it")
        if self.imitate_teacher != "search" and not self.imitate:
            raise InputError("--teacher: chooses the teacher of --imitate N, so only with it")
        if self.imitate == 1:
            raise InputError("--imitate: needs at least 2 teacher episodes (one is held out)")
        if self.workers < 1:
            raise InputError(f"--workers: must be at least 1, got {self.workers}")
        if self.workers > 1 and not self.imitate:
            raise InputError("--workers: spreads teacher episodes, so only with --imitate N")
        if self.seed < 0:
            raise InputError(f"--seed: must be >= 0, got {self.seed}")
        if self.action not in ("coordinates", "residual"):
            raise InputError(f"--action: 'coordinates' or 'residual', got {self.action!r}")
        if not (np.isfinite(self.residual_radius_m) and self.residual_radius_m > 0):
            raise InputError(f"--residual-radius-m: must be > 0, got {self.residual_radius_m!r}")
        if self.algorithm == "ddqn" and self.action != "coordinates":
            raise InputError("--action: residual actions are DDPG's (DDQN moves by zones)")
        if self.prior not in PRIORS:
            raise InputError(f"--prior: must be one of {', '.join(PRIORS)}, got {self.prior!r}")
        if self.prior != DEFAULT_PRIOR and self.action != "residual":
            raise InputError("--prior: the placement residual actions correct, so only with "
                             "--algo ddpg --action residual")  # fmt: skip
        if self.prior != DEFAULT_PRIOR and self.imitate:
            raise InputError(f"--imitate: teaches residuals around {DEFAULT_PRIOR} only "
                             f"(drop --prior {self.prior})")  # fmt: skip
        if self.n_fleets < 1:
            raise InputError(f"--envs: must be at least 1, got {self.n_fleets}")
        if not (np.isfinite(self.load_per_uav_bps) and self.load_per_uav_bps > 0):
            raise InputError(f"load_per_uav_bps: must be > 0, got {self.load_per_uav_bps!r}")
        get_world(self.world)  # an unknown world fails here, named
        if self.environment is not None:
            check_train_environment(self.environment)
        self.sampler(AreaConfig())  # and so do unknown families or user counts

    @property
    def chosen_preset(self) -> Preset:
        if isinstance(self.preset, Preset):
            return self.preset
        return get_preset(self.preset, self.algorithm, self.action)

    @property
    def prior_score_steps(self) -> int:
        """Decisions a ``kmeans-scored`` prior scores each candidate over: an evaluation
        episode of the world (not the preset's shorter training episode)."""
        return self.base_world().episode_steps

    def base_world(self) -> World:
        """The run's world in its channel environment (``environment``), as evaluated."""
        world = get_world(self.world)
        if self.environment is None:
            return world
        return world_with(world, {"environment": self.environment})

    def train_world(self) -> World:
        """The world with the preset's training episode (length, start)."""
        p = self.chosen_preset
        return replace(self.base_world(), episode_steps=p.train_episode_steps, home=p.train_start)

    def sampler(self, area: AreaConfig) -> ScenarioSampler:
        return ScenarioSampler(
            families=self.families,
            users=self.users,
            area=area,
            total_load_bps=self.load_per_uav_bps * self.n_uavs,
        )

    def to_dict(self) -> dict[str, Any]:
        d = asdict(self)
        d["out_dir"] = str(self.out_dir)
        d["preset"] = self.chosen_preset.to_dict()
        d["families"] = list(self.families)
        d["users"] = list(self.users)
        return d


def make_fleet_vec_env(config: FleetTrainConfig) -> Any:
    """The SB3 vector env of ``n_fleets`` fleets of K agents (SuperSuit), monitored."""
    world = config.train_world()
    fleet: Any = FleetParallelEnv(
        n_uavs=config.n_uavs,
        action_kind="discrete" if config.algorithm == "ddqn" else "continuous",
        scenarios=config.sampler(world.area),
        world=world,
    )
    if config.action == "residual":
        fleet = FleetResidualActions(
            fleet, config.residual_radius_m, config.prior, config.prior_score_steps
        )
    # concat_vec_envs_v1 copies the fleet n_fleets times (each copy its own generator).
    vec = ss.pettingzoo_env_to_vec_env_v1(fleet)
    vec = ss.concat_vec_envs_v1(vec, config.n_fleets, num_cpus=0, base_class="stable_baselines3")
    return VecMonitor(_SeededVecEnv(vec.venv))


class _SeededVecEnv(SB3VecEnvWrapper):
    """SuperSuit's SB3 wrapper with SB3's ``seed()``: the seed is passed to the next reset
    (fleet i of the batch gets seed + i). SuperSuit's own wrapper forwards ``seed()`` to its
    concatenated env, which has none, so SB3's ``set_random_seed`` fails on it."""

    def __init__(self, venv: Any) -> None:
        super().__init__(venv)
        self._pending_seed: int | None = None
        self._infos: list[dict[str, Any]] = []

    def step_wait(self) -> Any:
        observations, rewards, dones, infos = super().step_wait()
        self._infos = infos  # after an episode's end, the next one's first infos (SuperSuit)
        return observations, rewards, dones, infos

    def env_method(
        self, method_name: str, *args: Any, indices: Any = None, **kwargs: Any
    ) -> list[Any]:
        """``action_masks`` (what the masked DDQN asks each environment before acting): each
        agent's mask of its current state, from the infos the bridge returned last."""
        if method_name != "action_masks":
            return super().env_method(method_name, *args, indices=indices, **kwargs)
        if len(self._infos) != self.num_envs or any("action_mask" not in i for i in self._infos):
            raise RuntimeError("action_masks: the fleet's infos carry none (continuous actions?)")
        return [np.asarray(info["action_mask"], dtype=bool) for info in self._infos]

    def seed(self, seed: int | None = None) -> list[int | None]:
        self._pending_seed = seed
        return [None if seed is None else seed + i for i in range(self.num_envs)]

    def get_attr(self, attr_name: str, indices: Any = None) -> list[Any]:
        if attr_name == "render_mode":  # the fleet renders nothing
            return [None] * self.num_envs
        return super().get_attr(attr_name, indices)

    def reset(self, seed: int | None = None, options: dict | None = None) -> Any:
        seed = self._pending_seed if seed is None else seed
        self._pending_seed = None
        observations, self.reset_infos = self.venv.reset(seed=seed, options=options)
        self._infos = list(self.reset_infos)
        return observations


class _FleetProgress(BaseCallback):
    """A progress bar in fleet episodes: each of a fleet's K agent-environments reports the
    end of the same episode, so K reports make one."""

    def __init__(self, config: FleetTrainConfig) -> None:
        super().__init__()
        self.config = config
        self.agent_episodes = 0
        self.recent_utility: deque[float] = deque(maxlen=50)
        self.bar: Any = None

    def _on_training_start(self) -> None:
        if self.config.progress:
            c = self.config
            residual = "-residual" if c.action == "residual" else ""
            self.bar = episode_bar(c.episodes, f"fleet-{c.algorithm}{residual} K={c.n_uavs}")

    def _on_step(self) -> bool:
        for info in self.locals.get("infos", []):
            episode = info.get("episode")
            if episode is None:
                continue
            self.agent_episodes += 1
            if self.agent_episodes % self.config.n_uavs == 0:
                self.recent_utility.append(episode["r"] / max(episode["l"], 1))
                if self.bar is not None:
                    self.bar.update(1)
                    self.bar.set_postfix(utility=f"{np.mean(self.recent_utility):.3f}")
        return True

    def _on_training_end(self) -> None:
        if self.bar is not None:
            self.bar.close()


def _vector_preset(preset: Preset, n_envs: int) -> Preset:
    """``preset`` with its update ratio kept per transition over ``n_envs`` environments."""
    train_freq = max(1, preset.train_freq // n_envs)
    gradient_steps = max(1, round(n_envs * preset.gradient_steps / preset.train_freq))
    return replace(preset, train_freq=train_freq, gradient_steps=gradient_steps)


def train_fleet(config: FleetTrainConfig) -> dict[str, Any]:
    """Train one network (DDPG or DDQN, ``config.algorithm``) shared by a fleet of
    ``config.n_uavs``: imitation first when ``config.imitate``, then ``config.episodes`` of
    reinforcement learning; write ``model.zip`` and ``model.json`` into ``config.out_dir``;
    return the metadata."""
    started = time.monotonic()
    preset = config.chosen_preset
    env = make_fleet_vec_env(config)
    n_envs = env.num_envs
    config.out_dir.mkdir(parents=True, exist_ok=True)
    # build_model seeds torch, numpy and (through _SeededVecEnv) the fleets' first reset.
    model = build_model(
        config.algorithm,
        env,
        _vector_preset(preset, n_envs),
        TRAIN_SEED_OFFSET + config.seed,
        tensorboard_log=None,
    )
    if config.action == "residual":  # an untrained policy is its prior
        zero_actor_output(model)
    world = config.train_world()
    imitation = None
    if config.imitate:
        imitation = _imitate(model, config, world, started)
    if config.episodes:
        total = config.episodes * preset.train_episode_steps * config.n_uavs
        model.learn(total_timesteps=total, callback=_FleetProgress(config))
    metadata = _metadata(model, config, imitation, started)
    save_checkpoint(model, config.out_dir / "model.zip", metadata)
    env.close()
    return metadata


def _metadata(
    model: Any, config: FleetTrainConfig, imitation: dict[str, Any] | None, started: float
) -> dict[str, Any]:
    """The checkpoint's metadata (``started``: the run's ``time.monotonic()`` start)."""
    world = config.train_world()
    return {
        "algorithm": config.algorithm,
        "strategy": "fleet-shared",
        "fleet": True,
        "n_uavs_trained": config.n_uavs,
        "observation_shape": list(fleet_observation_shape(world.area)),
        **(
            {"action": "moves", "residual_radius_m": None}
            if config.algorithm == "ddqn"
            else {
                **residual_metadata(config.action),
                "residual_radius_m": config.residual_radius_m
                if config.action == "residual"
                else None,
                **(
                    {
                        "prior": config.prior,
                        "prior_score_steps": config.prior_score_steps,
                    }
                    if config.action == "residual"
                    else {}
                ),
            }
        ),
        "preset": config.chosen_preset.to_dict(),
        "episodes": config.episodes,
        "timesteps": int(model.num_timesteps),
        "n_fleets": config.n_fleets,
        "imitation": imitation,
        "seed": config.seed,
        "world": config.base_world().to_dict(),
        "train_environments": [world.area.environment],
        "families": list(config.families),
        "users": list(config.users),
        "load_per_uav_bps": config.load_per_uav_bps,
        "area": world.area.to_dict(),
        "git_commit": git_commit(),
        "device": str(model.device),
        "wall_time_s": round(time.monotonic() - started, 1),
        "command": config.command or shlex.join(sys.argv),
    }


def _imitate(model: Any, config: FleetTrainConfig, world: World, started: float) -> dict[str, Any]:
    """Fit ``model``'s network to the search oracle's decisions
    (:mod:`policies.training.fleet_imitation`), then ``config.imitate_rounds`` DAgger rounds; return
    the record kept in the checkpoint's metadata (the last fit's, with every round's)."""
    imitation = ImitationConfig(
        episodes=config.imitate,
        replan_every=config.imitate_replan_every,
        workers=config.workers,
        horizon_steps=config.base_world().episode_steps,
        teacher=config.imitate_teacher,
        symmetries=config.imitate_symmetries,
    )
    radius_m = config.residual_radius_m if config.algorithm == "ddpg" else None
    rounds: list[dict[str, Any]] = []
    data: TeacherData | None = None
    with tempfile.TemporaryDirectory(prefix="tupa-dagger-") as scratch:
        learner = Path(scratch) / "learner.zip"
        for number in range(config.imitate_rounds + 1):
            round_started = time.monotonic()
            if number:  # the policy fitted so far flies the next round
                save_checkpoint(model, learner, _metadata(model, config, None, started))
            more = collect_teacher_data(
                config.n_uavs,
                world,
                config.sampler(world.area),
                imitation,
                radius_m,
                config.seed,
                config.progress,
                learner=learner if number else None,
                first_episode=number * config.imitate,
            )
            data = more if data is None else data + more
            collected_s = time.monotonic() - round_started
            record = fit_actor(model, data, imitation, config.seed, config.progress)
            rounds.append(
                {
                    "round": number,
                    "flown_by": "learner" if number else "teacher",
                    **record,
                    "collect_s": round(collected_s, 1),
                    "fit_s": round(time.monotonic() - round_started - collected_s, 1),
                }
            )
    return {
        **rounds[-1],
        "teacher": {
            "oracle": "fleet-oracle",
            "name": imitation.teacher,
            **TEACHERS[imitation.teacher],
        },
        "replan_every": imitation.replan_every,
        "horizon_steps": imitation.horizon_steps,
        "dagger_rounds": config.imitate_rounds,
        "rounds": rounds,
        "collect_s": round(sum(r["collect_s"] for r in rounds), 1),
        "fit_s": round(sum(r["fit_s"] for r in rounds), 1),
    }
