"""The residual action space (:mod:`policies.learned.residual`) as a Gymnasium wrapper, for training
and evaluating residual checkpoints; serving needs only
:func:`policies.learned.residual.residual_target` (and so never imports Gymnasium)."""

from __future__ import annotations

from typing import Any

import gymnasium as gym
import numpy as np
from gymnasium import spaces

from policies.learned.residual import RESIDUAL_RADIUS_M, residual_target
from sim.geometry import m_to_unit
from sim.observation import UserReports


class ResidualActions(gym.Wrapper):
    """``FapContinuous`` with residual actions in [-1, 1]³ (see the module doc): each action
    becomes a target through :func:`residual_target`, from the report the decision sees."""

    def __init__(self, env: gym.Env, radius_m: float = RESIDUAL_RADIUS_M) -> None:
        super().__init__(env)
        self.radius_m = radius_m
        self.action_space = spaces.Box(-1.0, 1.0, (3,), dtype=np.float32)
        self._reports: UserReports | None = None

    def reset(self, **kwargs: Any) -> tuple[Any, dict[str, Any]]:
        observation, info = self.env.reset(**kwargs)
        self._reports = info["reports"]
        return observation, info

    def step(self, action: Any) -> tuple[Any, float, bool, bool, dict[str, Any]]:
        if self._reports is None:
            raise RuntimeError("step() called before reset()")
        a = np.asarray(action, dtype=float)
        if a.shape != (3,) or not np.all(np.isfinite(a)):
            raise ValueError(f"action: must be 3 finite numbers in [-1, 1], got {action!r}")
        area = self.env.unwrapped.area
        target = residual_target(a, self._reports, area, self.radius_m)
        result = self.env.step(m_to_unit(target, area))
        self._reports = result[4]["reports"]
        return result
