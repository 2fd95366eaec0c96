"""A fleet's residual action: each UAV's correction to its place in a k-means placement, the
*prior*.

The fleet counterpart of :mod:`policies.learned.residual`. Learned from scratch with absolute
coordinates, the shared fleet actor put every UAV in a corner whatever it observed (0.67 × the
search oracle, K = 2), while the k-means placements are already close to the oracle. With
residual actions each agent outputs ``delta`` in [-1, 1]³ and flies to

* x, y: *its* place in the prior plus ``delta_xy · radius_m``;
* z: the minimum altitude plus ``max(delta_z, 0)`` of the altitude band;

then the set is clipped into the volume and separated (:func:`sim.geometry.enforce_separation`).
Two priors (:data:`PRIORS`, named in a checkpoint's metadata):

* ``kmeans-load-weighted`` (:class:`KMeansPrior`, the default and every checkpoint's without a
  ``prior`` in its metadata): k-means on the users weighted by load, the load-weighted
  single-UAV placement per cluster, each UAV taking the place that keeps the fleet's total
  flight least (:func:`sim.geometry.assign_targets`);
* ``kmeans-scored`` (:class:`ScoredPrior`):
  :class:`policies.placements.fleet_scored.ScoredKMeansPlacement` flown from where the fleet is (its
  ``place_from``: the candidates scored on the fleet model, the users on the APs they are on), row i
  for UAV i; it needs the world's network, decision period and flight, and takes tens of
  milliseconds a decision where k-means takes one.

The actor starts at ``delta = 0`` (its last layer zeroed), so an untrained fleet policy *is*
its prior, and training learns what the prior misses (contention within a cell, the interplay
of cells, heavy users that need a cell of their own).
:func:`fleet_residual_targets` is the one function both the training wrapper
(:class:`policies.learned.fleet_residual_env.FleetResidualActions`) and serving
(:class:`policies.learned.fleet_checkpoint.FleetCheckpointPolicy`) use, so they agree to the bit.
"""

from __future__ import annotations

from collections import OrderedDict
from dataclasses import replace
from typing import Protocol

import numpy as np

from policies.interface import ReportedUsers
from policies.learned.residual import RESIDUAL_RADIUS_M
from policies.placements.fleet_baselines import KMeansPlacement
from policies.placements.fleet_scored import KMEANS_SCORED, ScoredKMeansPlacement
from sim.config import AreaConfig
from sim.errors import InputError
from sim.fleet import FleetConfig
from sim.flight import Flight
from sim.geometry import assign_targets, clip_to_volume, enforce_separation
from sim.observation import UserReports
from sim.world import World

__all__ = [
    "DEFAULT_PRIOR",
    "PRIORS",
    "FleetPrior",
    "KMeansPrior",
    "ScoredPrior",
    "fleet_residual_targets",
    "make_prior",
]

_CACHE_SIZE = 64
DEFAULT_PRIOR = "kmeans-load-weighted"
PRIORS: tuple[str, ...] = (DEFAULT_PRIOR, KMEANS_SCORED)
"""The placements a residual fleet action corrects (module doc)."""


class FleetPrior(Protocol):
    """Where each UAV of a fleet flies when its residual action is zero."""

    name: str

    def place_for(
        self,
        reports: UserReports,
        uav_xyz_m: np.ndarray,
        association: np.ndarray | None = None,
        flight: Flight | None = None,
    ) -> np.ndarray:
        """Places (K, 3), metres, row i for the UAV at ``uav_xyz_m[i]``; ``association``: the
        users' APs in the report (U,; ``None``: unknown); ``flight``: how the UAVs fly."""
        ...


class KMeansPrior:
    """The ``kmeans-load-weighted`` placement of K UAVs for a report, cached by the report's
    positions and loads (k-means takes milliseconds; a static crowd's report repeats every
    step). Deterministic: the same users give the same placement."""

    name = DEFAULT_PRIOR

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

    def place_for(
        self,
        reports: UserReports,
        uav_xyz_m: np.ndarray,
        association: np.ndarray | None = None,
        flight: Flight | None = None,
    ) -> np.ndarray:
        """The placement, each UAV on the place that keeps the fleet's total flight least
        (``association`` and ``flight`` play no part)."""
        here = np.asarray(uav_xyz_m, dtype=float)
        return assign_targets(here, self.place(reports, len(here)))


class ScoredPrior:
    """``kmeans-scored`` flown from where the fleet is (module doc), over ``world``'s area,
    network, utility and decision period, each candidate scored over ``score_steps`` decisions
    of a fleet like ``fleet`` (its channels and hysteresis; K and the separation are set per
    call). One :class:`ScoredKMeansPlacement` per K, built when first needed."""

    name = KMEANS_SCORED

    def __init__(
        self,
        world: World,
        separation_m: float,
        score_steps: int = 100,
        fleet: FleetConfig | None = None,
    ) -> None:
        self.world = world
        self.separation_m = float(separation_m)
        self.score_steps = score_steps
        self.fleet = fleet or FleetConfig()
        self._placements: dict[int, ScoredKMeansPlacement] = {}

    def place_for(
        self,
        reports: UserReports,
        uav_xyz_m: np.ndarray,
        association: np.ndarray | None = None,
        flight: Flight | None = None,
    ) -> np.ndarray:
        here = np.asarray(uav_xyz_m, dtype=float)
        k, w = len(here), self.world
        if k not in self._placements:
            fleet = replace(self.fleet, n_uavs=k, separation_m=self.separation_m)
            self._placements[k] = ScoredKMeansPlacement(
                fleet, w.area, w.network, w.utility, self.score_steps, w.step_s
            )
        users = ReportedUsers.of(reports)
        return self._placements[k].place_from(users, here, association, flight)


def make_prior(
    name: str,
    area: AreaConfig,
    separation_m: float,
    world: World | None = None,
    score_steps: int = 100,
    fleet: FleetConfig | None = None,
) -> FleetPrior:
    """The prior called ``name`` (:data:`PRIORS`); ``kmeans-scored`` needs ``world``.
    InputError naming ``prior`` otherwise."""
    if name == DEFAULT_PRIOR:
        return KMeansPrior(area, separation_m)
    if name == KMEANS_SCORED:
        if world is None:
            raise InputError("prior: kmeans-scored scores on a world's network; none was given")
        return ScoredPrior(replace(world, area=area), separation_m, score_steps, fleet)
    raise InputError(f"prior: must be one of {', '.join(PRIORS)}, got {name!r}")


def fleet_residual_targets(
    deltas: np.ndarray,
    reports: UserReports,
    uav_xyz_m: np.ndarray,
    area: AreaConfig,
    separation_m: float,
    radius_m: float = RESIDUAL_RADIUS_M,
    prior: FleetPrior | None = None,
    association: np.ndarray | None = None,
    flight: Flight | None = None,
) -> np.ndarray:
    """Targets (K, 3), metres, for the K agents' residual actions ``deltas`` (K, 3) given the
    report, where the UAVs are (K, 3) and, for a prior that scores from there, the users' APs
    (U,) and the UAVs' flight; ``prior``: ``kmeans-load-weighted`` unless given (module doc)."""
    here = np.asarray(uav_xyz_m, dtype=float)
    d = np.clip(np.asarray(deltas, dtype=float).reshape(len(here), 3), -1.0, 1.0)
    prior = prior or KMeansPrior(area, separation_m)
    mine = prior.place_for(reports, here, association, flight)
    z = area.z_min_m + np.maximum(d[:, 2], 0.0) * (area.z_max_m - area.z_min_m)
    targets = np.column_stack([mine[:, :2] + d[:, :2] * radius_m, z])
    return enforce_separation(clip_to_volume(targets, area), separation_m, area)
