"""DDPG over absolute coordinates, as a small extension of stable-baselines3's ``DDPG``.

What changes from SB3's DDPG (TD3 with one critic, no target smoothing, no policy delay):

- **Critic loss** is the Huber loss (the paper) or MSE, chosen by ``loss``.
- **Target networks** are soft-updated with τ every ``target_update_interval`` gradient steps
  (the paper: 80 % every 2000 steps) instead of a small τ at every step.
- **Action penalty** (``action_l2``, 0 by default): the actor's loss adds
  ``action_l2 · mean(a²)``, so an action moves away from 0 only where the critic's gain pays
  for it. With residual actions (:mod:`policies.learned.residual`) 0 is the load-weighted placement,
  and the penalty keeps the actor out of tanh's saturated corners, where its gradient vanishes
  and a run collapses onto one corner for every observation.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import torch as th
from stable_baselines3 import DDPG
from stable_baselines3.common.utils import polyak_update
from torch.nn import functional as F


class IntervalTargetDDPG(DDPG):
    """SB3 ``DDPG`` with a Huber critic loss and interval target updates (module doc)."""

    def __init__(
        self,
        *args: Any,
        target_update_interval: int = 1,
        loss: str = "huber",
        action_l2: float = 0.0,
        **kwargs: Any,
    ) -> None:
        if loss not in ("mse", "huber"):
            raise ValueError(f"loss: must be 'mse' or 'huber', got {loss!r}")
        if target_update_interval < 1:
            raise ValueError(f"target_update_interval: must be >= 1, got {target_update_interval}")
        if not action_l2 >= 0:
            raise ValueError(f"action_l2: must be >= 0, got {action_l2}")
        self.target_update_interval = target_update_interval
        self.loss = loss
        self.action_l2 = action_l2
        super().__init__(*args, **kwargs)

    def train(self, gradient_steps: int, batch_size: int = 100) -> None:
        self.policy.set_training_mode(True)
        self._update_learning_rate([self.actor.optimizer, self.critic.optimizer])
        actor_losses, critic_losses = [], []
        critic_loss_fn = F.smooth_l1_loss if self.loss == "huber" else F.mse_loss
        for _ in range(gradient_steps):
            self._n_updates += 1
            batch = self.replay_buffer.sample(batch_size, env=self._vec_normalize_env)
            with th.no_grad():
                next_actions = self.actor_target(batch.next_observations)
                next_q = self.critic_target(batch.next_observations, next_actions)[0]
                targets = batch.rewards + (1 - batch.dones) * self.gamma * next_q
            current_q = self.critic(batch.observations, batch.actions)[0]
            critic_loss = critic_loss_fn(current_q, targets)
            critic_losses.append(critic_loss.item())
            self.critic.optimizer.zero_grad()
            critic_loss.backward()
            self.critic.optimizer.step()

            actions = self.actor(batch.observations)
            actor_loss = -self.critic.q1_forward(batch.observations, actions).mean()
            if self.action_l2 > 0:
                actor_loss = actor_loss + self.action_l2 * (actions**2).mean()
            actor_losses.append(actor_loss.item())
            self.actor.optimizer.zero_grad()
            actor_loss.backward()
            self.actor.optimizer.step()

            if self._n_updates % self.target_update_interval == 0:
                polyak_update(self.critic.parameters(), self.critic_target.parameters(), self.tau)
                polyak_update(self.actor.parameters(), self.actor_target.parameters(), self.tau)
                polyak_update(
                    self.critic_batch_norm_stats, self.critic_batch_norm_stats_target, 1.0
                )
                polyak_update(self.actor_batch_norm_stats, self.actor_batch_norm_stats_target, 1.0)
        self.logger.record("train/n_updates", self._n_updates, exclude="tensorboard")
        self.logger.record("train/actor_loss", float(np.mean(actor_losses)))
        self.logger.record("train/critic_loss", float(np.mean(critic_losses)))
