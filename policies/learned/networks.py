"""The paper's network over the six zone maps, as a stable-baselines3 feature extractor.

Paper §III-D: 1–2 convolutional layers with 3×3 kernels, then 2 dense layers interleaved with
dropout, ReLU everywhere. The algorithm's own head (13 Q-values for DDQN; the actor's 3
coordinates and the critic's value for DDPG) sits on top of these features.
"""

from __future__ import annotations

import gymnasium as gym
import torch as th
from stable_baselines3.common.torch_layers import BaseFeaturesExtractor
from torch import nn


class ZoneMapsCNN(BaseFeaturesExtractor):
    """Conv(3×3) → ReLU → Conv(3×3, stride 2) → ReLU → Dense → ReLU → Dropout → Dense → ReLU
    → Dropout. Input (6, n_x, n_y) float maps in [0, 1]; output ``features_dim`` features."""

    def __init__(
        self,
        observation_space: gym.spaces.Box,
        channels: tuple[int, ...] = (32, 32),
        hidden: int = 256,
        features_dim: int = 256,
        dropout: float = 0.1,
    ) -> None:
        super().__init__(observation_space, features_dim)
        if not 1 <= len(channels) <= 2:
            raise ValueError(f"channels: the paper uses 1 or 2 conv layers, got {channels}")
        in_channels = observation_space.shape[0]
        layers: list[nn.Module] = []
        for i, out_channels in enumerate(channels):
            stride = 2 if i == len(channels) - 1 and len(channels) > 1 else 1
            layers += [nn.Conv2d(in_channels, out_channels, 3, stride=stride, padding=1), nn.ReLU()]
            in_channels = out_channels
        self.conv = nn.Sequential(*layers, nn.Flatten())
        with th.no_grad():
            n_flat = self.conv(th.zeros(1, *observation_space.shape)).shape[1]
        self.dense = nn.Sequential(
            nn.Linear(n_flat, hidden),
            nn.ReLU(),
            nn.Dropout(dropout),
            nn.Linear(hidden, features_dim),
            nn.ReLU(),
            nn.Dropout(dropout),
        )

    def forward(self, observations: th.Tensor) -> th.Tensor:
        return self.dense(self.conv(observations))
