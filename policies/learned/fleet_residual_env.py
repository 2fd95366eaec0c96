"""The fleet's residual action space (:mod:`policies.learned.fleet_residual`) as a PettingZoo
wrapper, for training; serving needs only
:func:`policies.learned.fleet_residual.fleet_residual_targets` (and so never imports PettingZoo or
Gymnasium)."""

from __future__ import annotations

from typing import Any

import numpy as np
from gymnasium import spaces
from pettingzoo.utils.wrappers import BaseParallelWrapper

from policies.learned.fleet_residual import DEFAULT_PRIOR, fleet_residual_targets, make_prior
from policies.learned.residual import RESIDUAL_RADIUS_M
from sim.fleet import FleetConfig
from sim.fleet_env import FleetParallelEnv

__all__ = ["FleetResidualActions"]


class FleetResidualActions(BaseParallelWrapper):
    """A :class:`sim.fleet_env.FleetParallelEnv` whose agents act with residual actions in
    [-1, 1]³ (module doc): each step, the K deltas become K targets through
    :func:`fleet_residual_targets` around ``prior`` (:data:`PRIORS`; ``kmeans-scored`` scores
    over ``score_steps`` decisions of the env's world) from the report the decision sees and
    the APs in it, and go to :meth:`~sim.fleet_env.FleetParallelEnv.step_to`."""

    def __init__(
        self,
        env: FleetParallelEnv,
        radius_m: float = RESIDUAL_RADIUS_M,
        prior: str = DEFAULT_PRIOR,
        score_steps: int = 100,
    ) -> None:
        super().__init__(env)
        self.radius_m = float(radius_m)
        fleet: FleetConfig = env.fleet
        self._prior = make_prior(prior, env.area, fleet.separation_m, env.world, score_steps, fleet)
        self._space = spaces.Box(-1.0, 1.0, (3,), dtype=np.float32)

    def action_space(self, agent: str) -> spaces.Space:
        return self._space

    def step(self, actions: dict[str, Any]) -> tuple[dict, dict, dict, dict, dict]:
        env: FleetParallelEnv = self.env  # type: ignore[assignment]
        try:
            deltas = np.stack([np.asarray(actions[a], dtype=float) for a in env.possible_agents])
        except KeyError as missing:
            raise ValueError(f"actions: no action for agent {missing}") from None
        if deltas.shape != (env.n_uavs, 3) or not np.all(np.isfinite(deltas)):
            raise ValueError("actions: each agent's must be 3 finite numbers in [-1, 1]")
        targets = fleet_residual_targets(
            deltas,
            env.reports,
            env.uav_xyz_m,
            env.area,
            env.fleet.separation_m,
            self.radius_m,
            self._prior,
            env.reported_association,
            env.world.flight,
        )
        return env.step_to(targets)
