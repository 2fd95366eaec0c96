"""A fleet's residual action: each UAV's correction to its place in the load-weighted k-means
placement.

The fleet counterpart of :mod:`policies.residual`. Learned from scratch with absolute
coordinates, the shared fleet actor put every UAV in a corner whatever it observed (0.67 × the
search oracle, K = 2), while the ``kmeans-load-weighted`` placement (k-means on the users
weighted by load, then the load-weighted single-UAV placement per cluster) is already close to
the oracle. With residual actions each agent outputs ``delta`` in [-1, 1]³ and flies to

* x, y: *its* prior plus ``delta_xy · radius_m``, where the priors are the
  ``kmeans-load-weighted`` placement of the reported users, one per UAV, each UAV taking the
  one that keeps the fleet's total flight least (:func:`sim.geometry.assign_targets`);
* z: the minimum altitude plus ``max(delta_z, 0)`` of the altitude band;

then the set is clipped into the volume and separated (:func:`sim.geometry.enforce_separation`).
The actor starts at ``delta = 0`` (its last layer zeroed), so an untrained fleet policy *is*
the k-means baseline, and training learns what it misses (contention within a cell, the
interplay of cells, heavy users that need a cell of their own).
:func:`fleet_residual_targets` is the one function both the training wrapper
(:class:`FleetResidualActions`) and serving (:class:`policies.fleet_training.FleetCheckpointPolicy`)
use, so they agree to the bit.
"""

from __future__ import annotations

from collections import OrderedDict
from typing import Any

import numpy as np
from gymnasium import spaces
from pettingzoo.utils.wrappers import BaseParallelWrapper

from policies.fleet_baselines import KMeansPlacement
from policies.interface import ReportedUsers
from policies.residual import RESIDUAL_RADIUS_M
from sim.config import AreaConfig
from sim.fleet import FleetConfig
from sim.fleet_env import FleetParallelEnv
from sim.geometry import assign_targets, clip_to_volume, enforce_separation
from sim.observation import UserReports

__all__ = ["FleetResidualActions", "KMeansPrior", "fleet_residual_targets"]

_CACHE_SIZE = 64


class KMeansPrior:
    """The ``kmeans-load-weighted`` placement of K UAVs for a report, cached by the report's
    positions and loads (k-means takes milliseconds; a static crowd's report repeats every
    step). Deterministic: the same users give the same placement."""

    def __init__(self, area: AreaConfig, separation_m: float) -> None:
        self.area = area
        self.separation_m = float(separation_m)
        self._cache: OrderedDict[tuple[int, bytes, bytes], np.ndarray] = OrderedDict()

    def place(self, reports: UserReports, n_uavs: int) -> np.ndarray:
        users = ReportedUsers.of(reports)
        key = (n_uavs, users.users_xy_m.tobytes(), users.load_bps.tobytes())
        if key not in self._cache:
            placement = KMeansPlacement(n_uavs, self.area, True, self.separation_m)
            self._cache[key] = placement.place(users)
            if len(self._cache) > _CACHE_SIZE:
                self._cache.popitem(last=False)
        self._cache.move_to_end(key)
        return self._cache[key].copy()


def fleet_residual_targets(
    deltas: np.ndarray,
    reports: UserReports,
    uav_xyz_m: np.ndarray,
    area: AreaConfig,
    separation_m: float,
    radius_m: float = RESIDUAL_RADIUS_M,
    prior: KMeansPrior | None = None,
) -> np.ndarray:
    """Targets (K, 3), metres, for the K agents' residual actions ``deltas`` (K, 3) given the
    report and where the UAVs are (K, 3); see the module doc."""
    here = np.asarray(uav_xyz_m, dtype=float)
    d = np.clip(np.asarray(deltas, dtype=float).reshape(len(here), 3), -1.0, 1.0)
    placed = (prior or KMeansPrior(area, separation_m)).place(reports, len(here))
    mine = assign_targets(here, placed)
    z = area.z_min_m + np.maximum(d[:, 2], 0.0) * (area.z_max_m - area.z_min_m)
    targets = np.column_stack([mine[:, :2] + d[:, :2] * radius_m, z])
    return enforce_separation(clip_to_volume(targets, area), separation_m, area)


class FleetResidualActions(BaseParallelWrapper):
    """A :class:`sim.fleet_env.FleetParallelEnv` whose agents act with residual actions in
    [-1, 1]³ (module doc): each step, the K deltas become K targets through
    :func:`fleet_residual_targets` from the report the decision sees, and go to
    :meth:`~sim.fleet_env.FleetParallelEnv.step_to`."""

    def __init__(self, env: FleetParallelEnv, radius_m: float = RESIDUAL_RADIUS_M) -> None:
        super().__init__(env)
        self.radius_m = float(radius_m)
        fleet: FleetConfig = env.fleet
        self._prior = KMeansPrior(env.area, fleet.separation_m)
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
        )
        return env.step_to(targets)
