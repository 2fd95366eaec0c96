"""Double DQN with action masking, as a small extension of stable-baselines3's ``DQN``.

What changes from SB3's DQN, and only that:

- **Double-DQN target**: the next action is the online network's argmax, its value the target
  network's: ``y = r + γ (1 − done) Q_target(s', argmax_a Q_online(s', a))``.
- **Masking**: only valid moves are chosen when acting (greedy and ε-greedy alike) and in the
  target's argmax. The replay buffer stores the next state's mask from ``info["action_mask"]``.
- **Per-episode ε**: ``ε = max(ε_min, ε_0 · exp(−rate · episode))`` (the paper: from 1, rate
  0.02 per episode), instead of SB3's linear schedule over timesteps.
- **Loss**: mean squared error (the paper) or Huber, chosen by ``loss``.

Target-network soft updates (τ every ``target_update_interval`` steps) are SB3's own.
"""

from __future__ import annotations

import math
from typing import Any, NamedTuple

import numpy as np
import torch as th
from gymnasium import spaces
from stable_baselines3 import DQN
from stable_baselines3.common.buffers import ReplayBuffer
from stable_baselines3.common.vec_env import VecNormalize
from torch.nn import functional as F


class MaskedReplayBufferSamples(NamedTuple):
    observations: th.Tensor
    actions: th.Tensor
    next_observations: th.Tensor
    dones: th.Tensor
    rewards: th.Tensor
    next_action_masks: th.Tensor
    discounts: th.Tensor | None = None


class MaskedReplayBuffer(ReplayBuffer):
    """SB3's replay buffer plus the valid-move mask of each transition's next state."""

    def __init__(
        self,
        buffer_size: int,
        observation_space: spaces.Space,
        action_space: spaces.Space,
        *args: Any,
        **kwargs: Any,
    ) -> None:
        super().__init__(buffer_size, observation_space, action_space, *args, **kwargs)
        assert isinstance(action_space, spaces.Discrete)
        self.next_action_masks = np.ones(
            (self.buffer_size, self.n_envs, int(action_space.n)), dtype=bool
        )

    def add(
        self,
        obs: np.ndarray,
        next_obs: np.ndarray,
        action: np.ndarray,
        reward: np.ndarray,
        done: np.ndarray,
        infos: list[dict[str, Any]],
    ) -> None:
        n_actions = self.next_action_masks.shape[2]
        self.next_action_masks[self.pos] = np.stack(
            [np.asarray(info.get("action_mask", np.ones(n_actions, dtype=bool))) for info in infos]
        )
        super().add(obs, next_obs, action, reward, done, infos)

    def _get_samples(
        self, batch_inds: np.ndarray, env: VecNormalize | None = None
    ) -> MaskedReplayBufferSamples:
        env_indices = np.random.randint(0, high=self.n_envs, size=(len(batch_inds),))
        if self.optimize_memory_usage:
            next_obs = self.observations[(batch_inds + 1) % self.buffer_size, env_indices, :]
        else:
            next_obs = self.next_observations[batch_inds, env_indices, :]
        dones = self.dones[batch_inds, env_indices] * (1 - self.timeouts[batch_inds, env_indices])
        return MaskedReplayBufferSamples(
            observations=self.to_torch(
                self._normalize_obs(self.observations[batch_inds, env_indices, :], env)
            ),
            actions=self.to_torch(self.actions[batch_inds, env_indices, :]),
            next_observations=self.to_torch(self._normalize_obs(next_obs, env)),
            dones=self.to_torch(dones.reshape(-1, 1)),
            rewards=self.to_torch(
                self._normalize_reward(self.rewards[batch_inds, env_indices].reshape(-1, 1), env)
            ),
            next_action_masks=th.as_tensor(
                self.next_action_masks[batch_inds, env_indices], device=self.device
            ),
        )


def double_dqn_targets(
    rewards: th.Tensor,
    dones: th.Tensor,
    gamma: float,
    next_q_online: th.Tensor,
    next_q_target: th.Tensor,
    next_action_masks: th.Tensor,
) -> th.Tensor:
    """``r + γ (1 − done) Q_target(s', argmax_{valid a} Q_online(s', a))``, shape (batch, 1)."""
    masked = next_q_online.masked_fill(~next_action_masks, -th.inf)
    next_actions = masked.argmax(dim=1, keepdim=True)
    next_values = next_q_target.gather(1, next_actions)
    return rewards + (1.0 - dones) * gamma * next_values


class MaskedDoubleDQN(DQN):
    """SB3 ``DQN`` with the Double-DQN target, action masks and a per-episode ε (module doc)."""

    def __init__(
        self,
        *args: Any,
        epsilon_start: float = 1.0,
        epsilon_decay_per_episode: float = 0.02,
        epsilon_min: float = 0.01,
        loss: str = "mse",
        **kwargs: Any,
    ) -> None:
        if loss not in ("mse", "huber"):
            raise ValueError(f"loss: must be 'mse' or 'huber', got {loss!r}")
        kwargs.setdefault("replay_buffer_class", MaskedReplayBuffer)
        self.epsilon_start = epsilon_start
        self.epsilon_decay_per_episode = epsilon_decay_per_episode
        self.epsilon_min = epsilon_min
        self.loss = loss
        super().__init__(*args, **kwargs)
        self.exploration_rate = epsilon_start

    # -- exploration ---------------------------------------------------------------------------
    def episode_epsilon(self, episode: int) -> float:
        return max(
            self.epsilon_min,
            self.epsilon_start * math.exp(-self.epsilon_decay_per_episode * episode),
        )

    def _on_step(self) -> None:
        super()._on_step()
        self.exploration_rate = self.episode_epsilon(self._episode_num)
        self.logger.record("rollout/exploration_rate", self.exploration_rate)

    def _current_masks(self) -> np.ndarray:
        return np.stack(self.env.env_method("action_masks"))

    def _sample_action(
        self, learning_starts: int, action_noise: Any = None, n_envs: int = 1
    ) -> tuple[np.ndarray, np.ndarray]:
        masks = self._current_masks()
        explore = self.num_timesteps < learning_starts
        actions = self.masked_predict(
            self._last_obs, masks, epsilon=1.0 if explore else self.exploration_rate
        )
        return actions, actions

    # -- acting --------------------------------------------------------------------------------
    def masked_predict(
        self, observation: np.ndarray, action_masks: np.ndarray, epsilon: float = 0.0
    ) -> np.ndarray:
        """ε-greedy over valid moves only: a batch of observations and (batch, n_actions) masks."""
        masks = np.asarray(action_masks, dtype=bool).reshape(-1, int(self.action_space.n))
        if not masks.any(axis=1).all():
            raise ValueError("action_masks: every state needs at least one valid move")
        self.policy.set_training_mode(False)
        obs_tensor, _ = self.policy.obs_to_tensor(observation)
        with th.no_grad():
            q = self.q_net(obs_tensor)
        q = q.masked_fill(~th.as_tensor(masks, device=q.device), -th.inf)
        actions = q.argmax(dim=1).cpu().numpy()
        for i in np.flatnonzero(np.random.rand(len(actions)) < epsilon):
            actions[i] = np.random.choice(np.flatnonzero(masks[i]))
        return actions

    def predict(
        self,
        observation: np.ndarray | dict[str, np.ndarray],
        state: tuple[np.ndarray, ...] | None = None,
        episode_start: np.ndarray | None = None,
        deterministic: bool = False,
        action_masks: np.ndarray | None = None,
    ) -> tuple[np.ndarray, tuple[np.ndarray, ...] | None]:
        """Like ``DQN.predict``, restricted to valid moves when ``action_masks`` is given."""
        if action_masks is None:
            return super().predict(observation, state, episode_start, deterministic)
        epsilon = 0.0 if deterministic else self.exploration_rate
        actions = self.masked_predict(observation, action_masks, epsilon)
        single = np.asarray(observation).ndim == len(self.observation_space.shape)
        return (actions[0] if single else actions), state

    # -- learning ------------------------------------------------------------------------------
    def train(self, gradient_steps: int, batch_size: int = 100) -> None:
        self._update_learning_rate(self.policy.optimizer)
        losses = []
        for _ in range(gradient_steps):
            batch = self.replay_buffer.sample(batch_size, env=self._vec_normalize_env)
            self.policy.set_training_mode(False)
            with th.no_grad():
                targets = double_dqn_targets(
                    batch.rewards,
                    batch.dones,
                    self.gamma,
                    self.q_net(batch.next_observations),
                    self.q_net_target(batch.next_observations),
                    batch.next_action_masks,
                )
            self.policy.set_training_mode(True)
            current = self.q_net(batch.observations).gather(1, batch.actions.long())
            loss = (
                F.mse_loss(current, targets)
                if self.loss == "mse"
                else F.smooth_l1_loss(current, targets)
            )
            losses.append(loss.item())
            self.policy.optimizer.zero_grad()
            loss.backward()
            th.nn.utils.clip_grad_norm_(self.policy.parameters(), self.max_grad_norm)
            self.policy.optimizer.step()
        self._n_updates += gradient_steps
        self.logger.record("train/n_updates", self._n_updates, exclude="tensorboard")
        self.logger.record("train/loss", float(np.mean(losses)))
