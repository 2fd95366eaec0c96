"""Learned cooperative fleet policies: one DDPG network shared by every UAV of a fleet.

Parameter sharing (Gupta et al. 2017): every agent of :class:`sim.fleet_env.FleetParallelEnv`
sees its own observation (9 maps, the same channels for any K) and gets the same reward (the
network utility over all users); one stable-baselines3 agent learns from the transitions of all
of them. The PettingZoo → SB3 bridge is SuperSuit: ``pettingzoo_env_to_vec_env_v1`` turns one
fleet of K agents into a vector env of K environments, ``concat_vec_envs_v1`` stacks
``n_fleets`` fleets into one SB3 ``VecEnv`` of ``n_fleets × K`` environments. Because the
parameters are shared, the checkpoint flies any K (1..8), not only the K it trained with.

* :func:`train_fleet` (``tupa train --uavs K``): builds that vector env over the world's
  preset (the training episode of the :mod:`policies.presets` preset: length and start), the
  DDPG agent with the paper's CNN (:func:`policies.training.build_model`, 9 input channels),
  learns ``episodes × episode_steps × K`` agent-steps and writes ``model.zip`` + ``model.json``
  (:func:`policies.checkpoints.save_checkpoint`).
* :class:`FleetCheckpointPolicy`: such a checkpoint deciding K targets from K observations.
* :func:`evaluate_fleet`: the utility, served-user fraction, Jain fairness and minimum user
  throughput of a fleet policy, or of a placement (k-means baselines, the search oracle)
  re-placed every ``replan_every`` decisions, over a list of scenarios.

Update ratio: a vector step gives ``n_fleets × K`` transitions, so the preset's
``train_freq`` (environment steps per gradient step) is re-expressed per vector step
(``train_freq // n_envs`` vector steps, ``n_envs // train_freq`` gradient steps each, at least
one of both), keeping about one gradient step per ``train_freq`` transitions.
"""

from __future__ import annotations

import shlex
import sys
import time
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import Any, Protocol

import numpy as np
import supersuit as ss
from stable_baselines3.common.vec_env import VecMonitor
from supersuit.vector.sb3_vector_wrapper import SB3VecEnvWrapper

from policies.checkpoints import git_commit, load_checkpoint, save_checkpoint
from policies.presets import PRESET_NAMES, Preset, get_preset
from policies.training import TRAIN_SEED_OFFSET, build_model
from sim.config import AreaConfig
from sim.errors import InputError
from sim.fleet import MAX_UAVS, FleetConfig
from sim.fleet_env import FLEET_MAPS, FleetParallelEnv
from sim.geometry import enforce_separation, unit_to_m_many
from sim.scenarios import Scenario, ScenarioSampler
from sim.world import World, get_world

__all__ = [
    "FLEET_ALGORITHMS",
    "FleetCheckpointPolicy",
    "FleetTrainConfig",
    "evaluate_fleet",
    "fleet_observation_shape",
    "train_fleet",
]

FLEET_ALGORITHMS: tuple[str, ...] = ("ddpg",)
"""Algorithms a fleet trains with (DDQN's masked moves need per-agent masks through the
bridge: not yet)."""


def fleet_observation_shape(area: AreaConfig) -> tuple[int, int, int]:
    """One fleet agent's observation shape: (9, n_zones_x, n_zones_y)."""
    return (FLEET_MAPS, area.n_zones_x, area.n_zones_y)


@dataclass(frozen=True)
class FleetTrainConfig:
    """One fleet training run.

    ``episodes`` counts fleet episodes (each ``preset.train_episode_steps`` decisions of all K
    UAVs); ``n_fleets`` fleets step as one batch. Training scenarios are drawn by a
    :class:`sim.scenarios.ScenarioSampler` over ``families`` and ``users`` (an inclusive
    range) with a total offered load of ``load_per_uav_bps × K``. ``preset`` is a preset name
    (``paper``, ``fast``) or a :class:`policies.presets.Preset`."""

    n_uavs: int
    episodes: int
    out_dir: Path
    algorithm: str = "ddpg"
    preset: str | Preset = "fast"
    seed: int = 1
    world: str = "closed-loop"
    families: tuple[str, ...] = ("uniform", "hotspots", "mixture")
    users: tuple[int, int] = (20, 20)
    load_per_uav_bps: float = 40e6
    n_fleets: int = 1
    command: str | None = None

    def __post_init__(self) -> None:
        k = self.n_uavs
        if isinstance(k, bool) or not isinstance(k, int | np.integer) or not 1 <= k <= MAX_UAVS:
            raise InputError(f"--uavs: must be an integer in 1..{MAX_UAVS}, got {k!r}")
        if self.algorithm not in FLEET_ALGORITHMS:
            raise InputError("--uavs: fleets train with --algo ddpg for now")
        if isinstance(self.preset, str) and self.preset not in PRESET_NAMES:
            raise InputError(
                f"--preset: must be one of {', '.join(PRESET_NAMES)}, got {self.preset!r}"
            )
        if self.episodes < 1:
            raise InputError(f"--episodes: must be at least 1, got {self.episodes}")
        if self.seed < 0:
            raise InputError(f"--seed: must be >= 0, got {self.seed}")
        if self.n_fleets < 1:
            raise InputError(f"--envs: must be at least 1, got {self.n_fleets}")
        if not (np.isfinite(self.load_per_uav_bps) and self.load_per_uav_bps > 0):
            raise InputError(f"load_per_uav_bps: must be > 0, got {self.load_per_uav_bps!r}")
        get_world(self.world)  # an unknown world fails here, named
        self.sampler(AreaConfig())  # and so do unknown families or user counts

    @property
    def chosen_preset(self) -> Preset:
        if isinstance(self.preset, Preset):
            return self.preset
        return get_preset(self.preset, self.algorithm)

    def train_world(self) -> World:
        """The world with the preset's training episode (length, start)."""
        p = self.chosen_preset
        return replace(
            get_world(self.world), episode_steps=p.train_episode_steps, home=p.train_start
        )

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
    fleet = FleetParallelEnv(
        n_uavs=config.n_uavs,
        action_kind="continuous",
        scenarios=config.sampler(world.area),
        world=world,
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
        return observations


def _vector_preset(preset: Preset, n_envs: int) -> Preset:
    """``preset`` with its update ratio kept per transition over ``n_envs`` environments."""
    train_freq = max(1, preset.train_freq // n_envs)
    gradient_steps = max(1, round(n_envs * preset.gradient_steps / preset.train_freq))
    return replace(preset, train_freq=train_freq, gradient_steps=gradient_steps)


def train_fleet(config: FleetTrainConfig) -> dict[str, Any]:
    """Train one shared DDPG network for a fleet of ``config.n_uavs``; write ``model.zip`` and
    ``model.json`` into ``config.out_dir``; return the metadata."""
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
    total = config.episodes * preset.train_episode_steps * config.n_uavs
    model.learn(total_timesteps=total)
    world = config.train_world()
    shape = fleet_observation_shape(world.area)
    metadata = {
        "algorithm": config.algorithm,
        "strategy": "fleet-shared",
        "fleet": True,
        "n_uavs_trained": config.n_uavs,
        "observation_shape": list(shape),
        "action": "coordinates",
        "preset": preset.to_dict(),
        "episodes": config.episodes,
        "timesteps": int(model.num_timesteps),
        "n_fleets": config.n_fleets,
        "seed": config.seed,
        "world": get_world(config.world).to_dict(),
        "families": list(config.families),
        "users": list(config.users),
        "load_per_uav_bps": config.load_per_uav_bps,
        "area": world.area.to_dict(),
        "git_commit": git_commit(),
        "device": str(model.device),
        "wall_time_s": round(time.monotonic() - started, 1),
        "command": config.command or shlex.join(sys.argv),
    }
    save_checkpoint(model, config.out_dir / "model.zip", metadata)
    env.close()
    return metadata


class FleetCheckpointPolicy:
    """A shared-parameter fleet checkpoint as a fleet policy: K observations → K targets.

    ``targets(observations)`` takes the K agents' observations (K, 9, n_x, n_y), acts with the
    one network on each (deterministic), maps each action in [0, 1]³ to metres and separates
    the set (:func:`sim.geometry.enforce_separation`, lower index first). Any K works: the
    network never sees K."""

    name = "fleet-checkpoint"

    def __init__(
        self,
        model: Any,
        metadata: dict[str, Any],
        area: AreaConfig | None = None,
        separation_m: float = FleetConfig().separation_m,
    ) -> None:
        if metadata.get("action", "coordinates") != "coordinates":
            raise InputError(
                f"action: fleet checkpoints act with coordinates, got {metadata.get('action')!r}"
            )
        if not (np.isfinite(separation_m) and separation_m > 0):
            raise InputError(f"separation_m: must be > 0, got {separation_m!r}")
        self.model = model
        self.metadata = metadata
        self.area = area or AreaConfig()
        self.separation_m = float(separation_m)
        self.shape = fleet_observation_shape(self.area)

    @classmethod
    def load(
        cls,
        path: Path | str,
        area: AreaConfig | None = None,
        separation_m: float = FleetConfig().separation_m,
        device: str = "cpu",
    ) -> FleetCheckpointPolicy:
        """Load a checkpoint written by :func:`train_fleet` (shape and algorithm checked)."""
        area = area or AreaConfig()
        model, meta = load_checkpoint(
            path,
            area,
            algorithm="ddpg",
            device=device,
            observation_shape=fleet_observation_shape(area),
        )
        return cls(model, meta, area, separation_m)

    def targets(self, observations: np.ndarray) -> np.ndarray:
        """Targets (K, 3) in metres for observations (K, 9, n_x, n_y)."""
        obs = np.asarray(observations, dtype=np.float32)
        if obs.ndim != 4 or obs.shape[1:] != self.shape or not 1 <= len(obs) <= MAX_UAVS:
            raise InputError(
                f"observations: must be (K, {', '.join(map(str, self.shape))}) with K in "
                f"1..{MAX_UAVS}, got {obs.shape}"
            )
        actions, _ = self.model.predict(obs, deterministic=True)
        targets = unit_to_m_many(np.asarray(actions).reshape(len(obs), 3), self.area)
        return enforce_separation(targets, self.separation_m, self.area)


class FleetPlacement(Protocol):
    """A placement of the whole fleet from the users' report (k-means baselines, oracle)."""

    def place(self, users: Any) -> np.ndarray: ...


@dataclass(frozen=True)
class _Report:
    users_xy_m: np.ndarray
    load_bps: np.ndarray


@dataclass
class _Decider:
    """Targets for one step: the policy's, or the placement's (re-placed every N steps)."""

    policy: FleetCheckpointPolicy | FleetPlacement
    replan_every: int
    _held: np.ndarray | None = field(default=None, init=False)

    def __call__(self, env: FleetParallelEnv, observations: np.ndarray, step: int) -> np.ndarray:
        if isinstance(self.policy, FleetCheckpointPolicy):
            return self.policy.targets(observations)
        if self._held is None or step % self.replan_every == 0:
            report = env.reports
            users = _Report(
                np.column_stack([report.x_m, report.y_m]), np.asarray(report.offered_bps)
            )
            self._held = np.asarray(self.policy.place(users), dtype=float)
        return self._held


def evaluate_fleet(
    policy: FleetCheckpointPolicy | FleetPlacement,
    scenarios: Sequence[Scenario],
    n_uavs: int,
    world: World,
    fleet: FleetConfig | None = None,
    replan_every: int = 1,
    seed: int = 0,
) -> dict[str, Any]:
    """Run one episode of the fleet env (``world``'s length, from the fleet's homes) per
    scenario with ``policy`` deciding every step, and average.

    ``policy``: a :class:`FleetCheckpointPolicy`, or a placement with ``place(users) -> (K, 3)``
    re-placed on the report the decision sees every ``replan_every`` steps. Returns the means
    over scenarios of each episode's mean utility, served-user fraction, Jain fairness and
    minimum user throughput, the per-scenario utilities, and the scenario count."""
    if not scenarios:
        raise InputError("scenarios: empty")
    if replan_every < 1:
        raise InputError(f"replan_every: must be >= 1, got {replan_every}")
    fleet = fleet or FleetConfig(n_uavs=n_uavs)
    if fleet.n_uavs != n_uavs:
        raise InputError(f"n_uavs: {n_uavs} disagrees with the fleet's {fleet.n_uavs}")
    env = FleetParallelEnv(action_kind="continuous", scenarios=list(scenarios), world=world,
                           fleet=fleet)  # fmt: skip
    keys = ("utility", "served_fraction", "jain_fairness", "min_throughput_bps")
    per_scenario: dict[str, list[float]] = {k: [] for k in keys}
    for i, scenario in enumerate(scenarios):
        decide: Callable[..., np.ndarray] = _Decider(policy, replan_every)
        observations, _ = env.reset(seed=seed + i, options={"scenario": scenario})
        sums = dict.fromkeys(keys, 0.0)
        steps = 0
        while env.agents:
            joint = np.stack([observations[a] for a in env.possible_agents])
            observations, _, _, _, infos = env.step_to(decide(env, joint, steps))
            info = infos[env.possible_agents[0]]
            for k in keys:
                sums[k] += info[k]
            steps += 1
        for k in keys:
            per_scenario[k].append(sums[k] / steps)
    summary: dict[str, Any] = {f"mean_{k}": float(np.mean(v)) for k, v in per_scenario.items()}
    summary["utilities"] = per_scenario["utility"]
    summary["n_scenarios"] = len(scenarios)
    return summary
