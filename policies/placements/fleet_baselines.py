"""Static placements of a fleet: k-means on the users, then the single-UAV baseline per cluster.

The field's usual extension of a single-UAV placement to K UAVs (and the paper's baseline
carried over): cluster the users' ground positions into K groups with k-means, then place one
UAV per cluster with :class:`policies.placements.baselines.MinDistancePlacement` over that cluster's
users (minimum mean 3-D distance at the lowest altitude). Two variants:

* ``kmeans-min-distance``: plain k-means, plain min-distance per cluster (traffic-blind);
* ``kmeans-load-weighted``: every user weighted by its offered load, in k-means (centroids are
  load-weighted means, the objective the load-weighted squared distance) and in the placement
  per cluster (``load-weighted``): heavy users pull clusters and UAVs toward them.

``per_cluster`` swaps the placement per cluster for any single-UAV placement (the single-UAV
search oracle, say) while the partition stays k-means': what a fleet gains from *where* each UAV
hovers over its group, apart from *which* users form the groups
(``benchmarks/fleet_decomposition.py``).

k-means is Lloyd's iteration from k-means++ seeds (Arthur & Vassilvitskii 2007), ``n_init``
seedings drawn from ``default_rng(seed)``, the lowest-inertia result kept; ties in the nearest
centre go to the lowest index, an emptied cluster takes the point farthest from its centre.
Deterministic given the seed. With fewer distinct user positions than UAVs the extra UAVs start
at the overall placement. Either way the UAVs are ordered by their clusters' positions (x, then
y) and separated (:func:`sim.geometry.enforce_separation`) before they are returned.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from policies.interface import Placement, UsersLike
from policies.placements.baselines import MinDistancePlacement
from sim.config import AreaConfig
from sim.errors import InputError
from sim.fleet import MAX_UAVS
from sim.geometry import enforce_separation

__all__ = ["FLEET_BASELINES", "KMeansPlacement", "kmeans", "place_groups"]

FLEET_BASELINES: tuple[str, ...] = ("kmeans-min-distance", "kmeans-load-weighted")


def kmeans(
    points: np.ndarray,
    k: int,
    weights: np.ndarray | None = None,
    seed: int = 0,
    n_init: int = 4,
    max_iterations: int = 100,
) -> tuple[np.ndarray, np.ndarray]:
    """Weighted k-means of ``points`` (U, d): ``(centres (k', d), labels (U,))``, with
    k' = min(k, number of distinct points). See the module doc; deterministic given ``seed``."""
    x = np.asarray(points, dtype=float)
    n = len(x)
    w = np.ones(n) if weights is None else np.asarray(weights, dtype=float)
    if w.shape != (n,) or not np.all(np.isfinite(w)) or np.any(w < 0):
        raise ValueError("weights: need one finite weight >= 0 per point")
    if w.sum() <= 0:
        w = np.ones(n)
    k = min(int(k), len(np.unique(x, axis=0)))
    rng = np.random.default_rng(seed)
    best: tuple[float, np.ndarray, np.ndarray] | None = None
    for _ in range(max(1, n_init)):
        centres = _plus_plus(x, w, k, rng)
        labels = np.full(n, -1)
        for _ in range(max_iterations):
            distance = np.sum((x[:, None, :] - centres[None, :, :]) ** 2, axis=-1)
            new = np.argmin(distance, axis=1)
            for c in range(k):
                if not np.any(new == c):  # emptied: the point farthest from its centre
                    far = int(np.argmax(w * distance[np.arange(n), new]))
                    new[far] = c
            if np.array_equal(new, labels):
                break
            labels = new
            for c in range(k):
                mine = labels == c
                weight = w[mine]
                centres[c] = (
                    weight @ x[mine] / weight.sum() if weight.sum() > 0 else x[mine].mean(axis=0)
                )
        inertia = float(np.sum(w * np.sum((x - centres[labels]) ** 2, axis=1)))
        if best is None or inertia < best[0]:
            best = (inertia, centres.copy(), labels.copy())
    assert best is not None
    return best[1], best[2]


def _plus_plus(x: np.ndarray, w: np.ndarray, k: int, rng: np.random.Generator) -> np.ndarray:
    """k-means++ seeds, each point drawn with probability ∝ weight × squared distance."""
    p = w / w.sum()
    centres = [x[rng.choice(len(x), p=p)]]
    for _ in range(1, k):
        d2 = np.min(np.sum((x[:, None, :] - np.array(centres)[None]) ** 2, axis=-1), axis=1)
        score = w * d2
        if score.sum() <= 0:  # every weighted point sits on a centre: any distinct one
            score = (d2 > 0).astype(float)
        centres.append(x[rng.choice(len(x), p=score / score.sum())])
    return np.array(centres, dtype=float)


@dataclass(frozen=True)
class KMeansPlacement:
    """K UAVs from k-means clusters, one min-distance (or load-weighted) placement each.

    ``per_cluster``: the single-UAV placement flown over each cluster's users instead (its
    ``place(users)`` gets the cluster's positions and loads); ``None``, the default, is
    :class:`~policies.placements.baselines.MinDistancePlacement`, load-weighted when
    ``load_weighted``."""

    n_uavs: int = 3
    area: AreaConfig = field(default_factory=AreaConfig)
    load_weighted: bool = False
    separation_m: float = 10.0
    seed: int = 0
    n_init: int = 4
    per_cluster: Placement | None = None

    def __post_init__(self) -> None:
        k = self.n_uavs
        if isinstance(k, bool) or not isinstance(k, int | np.integer) or not 1 <= k <= MAX_UAVS:
            raise InputError(f"n_uavs: must be an integer in 1..{MAX_UAVS}, got {k!r}")
        if not (np.isfinite(self.separation_m) and self.separation_m > 0):
            raise InputError(f"separation_m: must be > 0, got {self.separation_m!r}")

    @property
    def name(self) -> str:
        """``kmeans-load-weighted`` or ``kmeans-min-distance``; with ``per_cluster``, its name
        after a ``+`` (``kmeans-load-weighted+oracle``)."""
        name = FLEET_BASELINES[1] if self.load_weighted else FLEET_BASELINES[0]
        return name if self.per_cluster is None else f"{name}+{self.per_cluster.name}"

    def place(self, users: UsersLike) -> np.ndarray:
        """Positions (K, 3) in metres, area frame, separated, inside the volume."""
        xy = np.asarray(users.users_xy_m, dtype=float)
        load = np.asarray(users.load_bps, dtype=float)
        single = self.per_cluster or MinDistancePlacement(
            self.area, load_weighted=self.load_weighted
        )
        _, labels = kmeans(
            xy, self.n_uavs, load if self.load_weighted else None, self.seed, self.n_init
        )
        return place_groups(xy, load, labels, single, self.n_uavs, self.separation_m, self.area)


def place_groups(
    users_xy_m: np.ndarray,
    load_bps: np.ndarray,
    labels: np.ndarray,
    single: Placement,
    n_uavs: int,
    separation_m: float,
    area: AreaConfig,
) -> np.ndarray:
    """One UAV per group of users (``labels`` 0, 1, ...: a user's group; a label < 0 leaves the
    user out), placed by ``single`` over that group's positions and loads; ordered by position
    (x, then y), topped up with ``single``'s placement of every user when there are fewer groups
    than ``n_uavs``, and separated: (K, 3) metres."""
    xy = np.asarray(users_xy_m, dtype=float)
    load = np.asarray(load_bps, dtype=float)
    positions = [
        single.place(_Users(xy[labels == c], load[labels == c]))
        for c in range(labels.max() + 1)
        if np.any(labels == c)
    ]
    placed = sorted(positions, key=lambda p: tuple(p[:2]))
    if len(placed) < n_uavs:  # fewer groups than UAVs
        placed += [single.place(_Users(xy, load))] * (n_uavs - len(placed))
    return enforce_separation(np.array(placed[:n_uavs]), separation_m, area)


@dataclass(frozen=True)
class _Users:
    users_xy_m: np.ndarray
    load_bps: np.ndarray
