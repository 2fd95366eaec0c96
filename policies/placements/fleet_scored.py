"""``kmeans-scored``: a few k-means partitions of the users, each scored on the fleet model.

The k-means baselines (:mod:`policies.placements.fleet_baselines`) commit to one partition of the
users and place one UAV per group. Most of the fleet search oracle's margin over them is in the
partition, *which* users each UAV serves, not where a UAV hovers over its group
(``benchmarks/fleet_decomposition.py``). This placement keeps k-means' speed but not its single
partition. It builds these candidate placements:

* ``kmeans-min-distance``: plain k-means, the min-distance placement per group;
* load-weighted k-means with every load raised to ``alpha`` (:data:`ALPHAS`), in the
  clustering and in the load-weighted placement per group. ``alpha = 1`` is
  ``kmeans-load-weighted``; a larger one pulls groups and UAVs toward the heaviest users, a
  smaller one toward the crowd;
* for ``alpha`` in :data:`REGROUP_ALPHAS`, two regroupings: K + 1 groups with the lightest
  dropped (its users left to whichever UAV they hear best), and K − 1 groups with the heaviest
  split in two (two UAVs share a loaded hot spot).

It scores them all in one batch on the fleet network model
(:func:`policies.placements.fleet_oracle.fleet_episode_utility`, expected mode, over ``score_steps``
steps of ``step_s``: an evaluation episode by default) and returns the best: held from a fresh
association (:meth:`ScoredKMeansPlacement.place`) or, as a closed loop and the service ask,
flown from where the fleet is (:meth:`ScoredKMeansPlacement.place_from`, as the fleet oracle's
``place_from``). The score is the model's, so the pick
knows contention, cells and interference, which no distance rule does; the candidates are few
and fixed, so a decision takes tens of milliseconds where the oracle's search takes seconds
(``benchmarks/fleet_policy.py`` flies it beside the k-means baselines and the oracle).
Deterministic: k-means is seeded, ties go to the first candidate in the order above.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from policies.interface import UsersLike
from policies.placements.baselines import MinDistancePlacement
from policies.placements.fleet_baselines import KMeansPlacement, kmeans, place_groups
from policies.placements.fleet_oracle import FleetStart, fleet_episode_utility
from sim.config import AreaConfig, NetworkConfig, UtilityConfig
from sim.errors import InputError
from sim.fleet import FleetConfig, FleetModel
from sim.flight import Flight
from sim.geometry import assign_targets

__all__ = ["ALPHAS", "KMEANS_SCORED", "REGROUP_ALPHAS", "ScoredKMeansPlacement"]

KMEANS_SCORED = "kmeans-scored"
ALPHAS: tuple[float, ...] = (0.5, 1.0, 2.0, 3.0)
"""The load exponents of the load-weighted candidates."""
REGROUP_ALPHAS: tuple[float, ...] = (1.0, 2.0)
"""The load exponents of the K + 1 (lightest dropped) and K − 1 (heaviest split) candidates."""


@dataclass(frozen=True)
class ScoredKMeansPlacement:
    """The best of the candidate placements of the module doc, scored on the fleet model of
    ``fleet`` (its K, separation, channels) over ``network``, ``area`` and ``utility``."""

    fleet: FleetConfig = field(default_factory=FleetConfig)
    area: AreaConfig = field(default_factory=AreaConfig)
    network: NetworkConfig = field(default_factory=NetworkConfig)
    utility: UtilityConfig = field(default_factory=UtilityConfig)
    score_steps: int = 100
    step_s: float = 1.0
    seed: int = 0
    name: str = KMEANS_SCORED
    _model: FleetModel = field(init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        if isinstance(self.score_steps, bool) or not (
            isinstance(self.score_steps, int) and self.score_steps >= 1
        ):
            raise InputError(f"score_steps: must be an integer >= 1, got {self.score_steps!r}")
        if not (np.isfinite(self.step_s) and self.step_s > 0):
            raise InputError(f"step_s: must be > 0 seconds, got {self.step_s!r}")
        object.__setattr__(
            self, "_model", FleetModel(self.fleet, self.network, self.area, self.utility)
        )

    @property
    def n_uavs(self) -> int:
        return self.fleet.n_uavs

    def candidates(self, users: UsersLike) -> tuple[np.ndarray, tuple[str, ...]]:
        """The candidate placements (M, K, 3) and their names, in the module doc's order."""
        xy = np.asarray(users.users_xy_m, dtype=float)
        load = np.asarray(users.load_bps, dtype=float)
        k, sep, area = self.n_uavs, self.fleet.separation_m, self.area
        placed = [KMeansPlacement(k, area, False, sep, self.seed).place(users)]
        names = ["kmeans-min-distance"]
        single = MinDistancePlacement(area, load_weighted=True)
        for alpha in ALPHAS:
            weights = load**alpha
            _, labels = kmeans(xy, k, weights, self.seed)
            placed.append(place_groups(xy, weights, labels, single, k, sep, area))
            names.append(f"load^{alpha:g}")
            if alpha in REGROUP_ALPHAS and k >= 2:
                for name, regrouped in _regroupings(xy, weights, k, self.seed):
                    keep = regrouped >= 0
                    placed.append(
                        place_groups(xy[keep], weights[keep], regrouped[keep], single, k, sep, area)
                    )
                    names.append(f"load^{alpha:g} {name}")
        return np.stack(placed), tuple(names)

    def scores(
        self, users: UsersLike, start: FleetStart | None = None
    ) -> tuple[np.ndarray, np.ndarray, tuple[str, ...]]:
        """``(candidates (M, K, 3), their scores (M,), their names)``. With ``start`` (where a
        closed loop's fleet is) each candidate is given to the vehicles by least total flight
        and scored flown from there, the users on the APs they are on."""
        fleets_m, names = self.candidates(users)
        if start is not None:
            fleets_m = np.stack([assign_targets(start.positions_m, f) for f in fleets_m])
        utility = fleet_episode_utility(
            self._model, fleets_m, users, self.score_steps, 1, self.step_s, start
        )
        return fleets_m, np.asarray(utility, dtype=float), names

    def place(self, users: UsersLike) -> np.ndarray:
        """Positions (K, 3) in metres, area frame, separated, inside the volume: the candidate
        with the best score held from a fresh association (the first among equals)."""
        fleets_m, utility, _ = self.scores(users)
        return fleets_m[int(np.argmax(utility))]

    def place_from(
        self,
        users: UsersLike,
        positions_m: np.ndarray,
        association: np.ndarray | None = None,
        flight: Flight | None = None,
    ) -> np.ndarray:
        """:meth:`place` for a fleet at ``positions_m`` (K, 3), the users on ``association``
        (U,; ``None``: none yet), flying as ``flight``: the candidate that scores best flown
        from there, row i for vehicle i. A split of a hot spot that a fresh association would
        give can be out of reach once stations have joined one UAV on its way (the roaming
        hysteresis); scored flown, it is not picked."""
        fleets_m, utility, _ = self.scores(users, FleetStart.at(positions_m, association, flight))
        return fleets_m[int(np.argmax(utility))]


def _regroupings(
    xy: np.ndarray, weights: np.ndarray, k: int, seed: int
) -> list[tuple[str, np.ndarray]]:
    """The K + 1 groups with the lightest dropped (its users labelled −1) and the K − 1 groups
    with the heaviest split in two (when its users stand at two distinct places or more)."""
    out = []
    _, labels = kmeans(xy, k + 1, weights, seed)
    groups = labels.max() + 1
    if groups == k + 1:
        lightest = int(np.argmin(np.bincount(labels, weights=weights, minlength=groups)))
        dropped = np.where(labels == lightest, -1, labels - (labels > lightest))
        out.append(("drop lightest", dropped))
    _, labels = kmeans(xy, k - 1, weights, seed)
    heaviest = int(np.argmax(np.bincount(labels, weights=weights, minlength=labels.max() + 1)))
    mine = np.flatnonzero(labels == heaviest)
    if len(np.unique(xy[mine], axis=0)) >= 2:
        _, halves = kmeans(xy[mine], 2, weights[mine], seed)
        split = labels.copy()
        split[mine[halves == 1]] = labels.max() + 1
        out.append(("split heaviest", split))
    return out
