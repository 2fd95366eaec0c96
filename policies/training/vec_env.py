"""stable-baselines3 on the vectorised environment: :class:`FapVecEnv` and :func:`make_vec_env`.

:class:`FapVecEnv` is an SB3 ``VecEnv`` over one :class:`sim.vector_env.FapVectorEnv`, so that
SB3's agents (and ours: ``MaskedDoubleDQN``, ``IntervalTargetDDPG``) train on E episodes stepping
as one numpy batch instead of a ``DummyVecEnv`` of single environments. What SB3 expects of a
``VecEnv`` and gets here:

- ``step_wait`` returns observations (E, ...), rewards (E,) float32, dones (E,) and one info
  dict per environment holding the keys of ``info_keys`` (``action_mask`` for the discrete
  kind: ``MaskedReplayBuffer`` reads it). When an episode ends the observation is already the
  next episode's first (autoreset) and that environment's info is the *final* step's, with
  ``terminal_observation``, ``TimeLimit.truncated`` and ``episode = {"r", "l", "t"}`` (return,
  length, seconds since this wrapper started), as ``DummyVecEnv`` over SB3's ``Monitor`` gives;
  the new episode's first info goes to ``reset_infos``.
- ``seed(s)`` (SB3 calls it with the algorithm's seed) makes the next ``reset`` use
  ``FapVectorEnv.reset(seed=s)``: environment e is seeded with ``s + e``, as ``DummyVecEnv``
  seeds its e-th environment.
- ``env_method("action_masks")`` (what ``MaskedDoubleDQN`` calls) and :meth:`action_masks` give
  the masks, one row per environment; ``get_attr`` gives each environment's ``scenario``
  (``episode_scenarios``), ``users``, ``uav_xyz_m`` and ``target_xyz_m``, and any other attribute
  of the vector environment, the same for all; ``set_attr`` and other ``env_method`` calls act
  on the vector environment, once. ``env_is_wrapped(Monitor)`` is true: the episode statistics
  are Monitor's.
"""

from __future__ import annotations

import time
from collections.abc import Sequence
from typing import Any

import gymnasium as gym
import numpy as np
from stable_baselines3.common.monitor import Monitor
from stable_baselines3.common.vec_env import VecEnv
from stable_baselines3.common.vec_env.base_vec_env import VecEnvIndices, VecEnvStepReturn

from sim.envs import ScenarioSource
from sim.network import NetworkModel
from sim.scenarios import Scenario
from sim.vector_env import FapVectorEnv
from sim.world import World

__all__ = ["ALGORITHM_KINDS", "FapVecEnv", "make_vec_env"]

ALGORITHM_KINDS: dict[str, str] = {"ddqn": "discrete", "ddpg": "continuous"}
# Attributes of FapVectorEnv with one entry per environment: get_attr gives each its own.
PER_ENV_ATTRIBUTES: dict[str, str] = {
    "scenario": "episode_scenarios",
    "episode_scenarios": "episode_scenarios",
    "users": "users",
    "uav_xyz_m": "uav_xyz_m",
    "target_xyz_m": "target_xyz_m",
}


def make_vec_env(
    algorithm: str,
    scenarios: Sequence[Scenario] | ScenarioSource,
    world: World | Sequence[World],
    n_envs: int,
    seed: int | None = None,
    model: NetworkModel | None = None,
) -> FapVecEnv:
    """The training environment of ``algorithm`` (``ddqn``: moves, ``ddpg``: coordinates) as
    ``n_envs`` episodes in one batch: the vectorised counterpart of
    ``policies.training.training.make_env`` (a list of scenarios is cycled, a sampler drawn from).

    ``world``: one :class:`World` (or a list holding one). ``seed`` seeds the first reset (SB3
    reseeds with the algorithm's own seed when it is given one)."""
    if algorithm not in ALGORITHM_KINDS:
        raise ValueError(f"algorithm: expected 'ddqn' or 'ddpg', got {algorithm!r}")
    env = FapVecEnv(FapVectorEnv(n_envs, ALGORITHM_KINDS[algorithm], scenarios, world, model))
    if seed is not None:
        env.seed(seed)
    return env


class FapVecEnv(VecEnv):
    """SB3's ``VecEnv`` interface over a :class:`FapVectorEnv` (see the module doc)."""

    def __init__(self, venv: FapVectorEnv, info_keys: Sequence[str] | None = None) -> None:
        self.venv = venv
        self.info_keys = tuple(
            info_keys
            if info_keys is not None
            else ("action_mask",)
            if venv.kind == "discrete"
            else ()
        )
        super().__init__(venv.num_envs, venv.single_observation_space, venv.single_action_space)
        self._actions: Any = None
        self._returns = np.zeros(self.num_envs)
        self._lengths = np.zeros(self.num_envs, dtype=np.int64)
        self._t_start = time.time()
        self.episode_returns: list[float] = []
        self.episode_lengths: list[int] = []

    @property
    def scenarios(self) -> ScenarioSource:
        """Where episodes get their scenarios (the vector environment's source)."""
        return self.venv.scenarios

    # -- SB3's VecEnv ----------------------------------------------------------------------
    def reset(self) -> np.ndarray:
        if any(self._options):
            raise ValueError(
                "options: FapVecEnv takes no per-environment reset options; pass options to "
                "FapVectorEnv.reset"
            )
        seed = self._seeds[0]
        obs, info = self.venv.reset(seed=seed)
        self.reset_infos = self._split(info, self.info_keys)
        self._reset_seeds()
        self._reset_options()
        self._returns[:] = 0.0
        self._lengths[:] = 0
        return obs

    def step_async(self, actions: np.ndarray) -> None:
        self._actions = actions

    def step_wait(self) -> VecEnvStepReturn:
        obs, rewards, terminated, truncated, info = self.venv.step(self._actions)
        self._actions = None
        self._returns += rewards
        self._lengths += 1
        dones = terminated | truncated
        if not dones.any():
            return obs, rewards.astype(np.float32), dones, self._split(info, self.info_keys)
        # The info of a finished episode is its final step's; the next one's first goes to
        # reset_infos (DummyVecEnv's convention).
        infos = self._split(info, self.info_keys)
        finals = self._split(info["final_info"], self.info_keys)
        elapsed = round(time.time() - self._t_start, 6)
        for e in np.flatnonzero(dones):
            episode_return, length = round(float(self._returns[e]), 6), int(self._lengths[e])
            finals[e].update(
                terminal_observation=info["final_obs"][e],
                episode={"r": episode_return, "l": length, "t": elapsed},
            )
            finals[e]["TimeLimit.truncated"] = bool(truncated[e] and not terminated[e])
            self.reset_infos[e], infos[e] = infos[e], finals[e]
            self.episode_returns.append(episode_return)
            self.episode_lengths.append(length)
            self._returns[e] = 0.0
            self._lengths[e] = 0
        return obs, rewards.astype(np.float32), dones, infos

    def close(self) -> None:
        self.venv.close()

    def get_attr(self, attr_name: str, indices: VecEnvIndices = None) -> list[Any]:
        rows = list(self._get_indices(indices))
        if attr_name == "render_mode":
            return [None] * len(rows)
        if attr_name == "action_masks" and self.venv.kind != "discrete":
            raise AttributeError("action_masks: the continuous kind has no moves to mask")
        if attr_name in PER_ENV_ATTRIBUTES:
            values = getattr(self.venv, PER_ENV_ATTRIBUTES[attr_name])
            return [values[e] for e in rows]
        value = getattr(self.venv, attr_name)
        return [value] * len(rows)

    def set_attr(self, attr_name: str, value: Any, indices: VecEnvIndices = None) -> None:
        rows = list(self._get_indices(indices))
        if attr_name in PER_ENV_ATTRIBUTES or sorted(rows) != list(range(self.num_envs)):
            raise ValueError(
                f"set_attr: {attr_name} can only be set for all environments of the batch at once"
            )
        setattr(self.venv, attr_name, value)

    def env_method(
        self,
        method_name: str,
        *method_args: Any,
        indices: VecEnvIndices = None,
        **method_kwargs: Any,
    ) -> list[Any]:
        rows = list(self._get_indices(indices))
        if method_name == "action_masks":
            masks = self.venv.action_masks()
            return [masks[e] for e in rows]
        result = getattr(self.venv, method_name)(*method_args, **method_kwargs)
        return [result] * len(rows)

    def env_is_wrapped(
        self, wrapper_class: type[gym.Wrapper], indices: VecEnvIndices = None
    ) -> list[bool]:
        return [wrapper_class is Monitor] * len(list(self._get_indices(indices)))

    # -- helpers ---------------------------------------------------------------------------
    def action_masks(self) -> np.ndarray:
        """Bool (E, 13): each environment's valid moves (discrete)."""
        return self.venv.action_masks()

    def _split(self, info: dict[str, Any], keys: Sequence[str]) -> list[dict[str, Any]]:
        """Gymnasium's batched info as SB3's list of per-environment dicts (``keys`` only)."""
        if not keys:
            return [{} for _ in range(self.num_envs)]
        if len(keys) == 1:
            (key,) = keys
            return [{key: value} for value in info[key]]
        columns = [info[key] for key in keys]
        return [dict(zip(keys, row, strict=True)) for row in zip(*columns, strict=True)]
