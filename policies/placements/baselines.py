"""Static placements: the paper's baseline and a load-weighted variant.

A *static* placement (:class:`policies.interface.Placement`) looks at one scenario — the users'
ground positions and their offered loads, which is what the service knows from the users'
reports — and returns one UAV position (area frame, metres) to hold for the whole episode. It
never sees network metrics.

* ``min-distance`` (the paper's baseline, §IV): the point at the minimum altitude that minimises
  the mean **3-D** distance from the UAV to the users (users at ``area.user_height_m``). At a fixed
  altitude that is the geometric median of the users' ground positions under the distance
  ``sqrt(d_ground² + h²)``, h = z_min − user height; minimising distance is what maximises the
  mean SNR under Friis path loss, which is why the paper calls it SNR-optimal and traffic-blind.
  The minimum altitude is where every distance is shortest. ``metric="ground"`` gives the plain
  2-D geometric median instead (the two differ by metres at most in the paper's area).
* ``load-weighted``: the same, each user's distance weighted by its offered load, so the UAV
  leans toward the heavy users. Traffic-aware, but still blind to the MAC (airtime, queues).
* ``min-distance-env``: min-distance's ground point, at the altitude that maximises the users'
  mean SNR under the area's channel environment (:func:`sim.channel.mean_path_loss_db`): still
  traffic-blind, but it knows that over a town climbing buys line of sight. In the ``open``
  environment it is min-distance. **On a site** (``site:PATH``), where the loss depends on
  where the UAV is and not only on how far, the same rule — the least mean path loss in dB the
  model sees, i.e. the highest mean SNR — is applied to the whole position
  (:func:`best_site_position_m`): the site's loss (:func:`sim.sites.lookup.path_loss_db`) at
  every point of a lattice over the flight volume (the site's UAV grid and the midpoints
  between its points, where coverage can change), then a local pattern search down to 1 m.
  A link with no path counts at :data:`sim.channel.NO_LINK_LOSS_DB`, as the network model
  takes it, so reaching every user comes first and the mean SNR second. Positions inside a
  building (at or below the roof of the ground cell the UAV hovers over) are never chosen.

The ``oracle`` (:mod:`policies.placements.oracle`: exhaustive search with the network model itself)
is the third placement; :mod:`policies.registry` builds any of them by name.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Literal

import numpy as np

from policies.interface import UsersLike
from sim.channel import NO_LINK_LOSS_DB, area_site, mean_path_loss_db
from sim.config import AreaConfig, RadioConfig
from sim.geometry import clip_to_volume

if TYPE_CHECKING:
    from sim.sites.format import Site

DistanceMetric = Literal["3d", "ground"]
AltitudeRule = Literal["lowest", "best-snr"]
ALTITUDE_STEP_M = 1.0
"""The altitude grid ``best-snr`` searches (metres)."""
SITE_REFINE_MIN_STEP_M = 1.0
"""The finest step of :func:`best_site_position_m`'s local search (metres)."""
SITE_REFINE_MAX_ROUNDS = 200
"""At most this many moves or step halvings in :func:`best_site_position_m`'s local search."""


# --------------------------------------------------------------------------------------------
# Geometric median


@dataclass(frozen=True)
class MedianConfig:
    """Stopping rule of the Weiszfeld iteration in :func:`geometric_median`."""

    max_iterations: int = 200
    tolerance_m: float = 1e-4  # stop when an iteration moves the point less than this
    coincident_m: float = 1e-9  # a user closer than this to the iterate counts as "at" it


# Up to this many users every user is tested as the median first (U² work); beyond, only the
# one the iteration ends next to.
_VERTEX_CHECK_MAX_USERS = 256
# Multiples of the Weiszfeld step tried at each iteration (1 keeps the classic step).
_STRETCH = 2.0 ** np.arange(0, 7)


def geometric_median(
    points_xy_m: np.ndarray,
    weights: np.ndarray | None = None,
    height_m: float = 0.0,
    config: MedianConfig = MedianConfig(),
) -> np.ndarray:
    """The point p (2,) minimising ``Σ w_i · sqrt(|p − x_i|² + height_m²)``.

    With ``height_m = 0`` this is the weighted geometric median of ``points_xy_m`` (U, 2); with
    ``height_m > 0`` it is the ground position of a point at that height above the points that
    minimises the weighted 3-D distance to them (the objective is then smooth and strictly
    convex, so the minimiser is unique even for collinear users). With ``height_m = 0`` a user
    that is itself the median (e.g. one holding half the weight or more) is found exactly by
    its optimality condition first, where Weiszfeld would only crawl toward it.

    Weiszfeld's iteration ``p ← Σ (w_i / D_i) x_i / Σ (w_i / D_i)`` (D_i the current distances),
    started from the weighted centroid, vectorised over users, at most
    ``config.max_iterations`` iterations. Each iteration tries 1, 2, 4, ... 64 times the
    Weiszfeld step along its direction and keeps the best (the plain step is slow where the
    objective is flat), so the objective never increases. When the
    iterate lands on a user (only possible with ``height_m = 0``) the Vardi-Zhang modification
    decides whether that user is the median or steps off it, so there is no division by zero.

    ``weights`` default to equal; negative weights are an error, zero weights drop the user.
    If every weight is zero, the users count equally.
    """
    points = np.asarray(points_xy_m, dtype=float).reshape(-1, 2)
    if points.shape[0] == 0:
        raise ValueError("points_xy_m: need at least one user")
    if weights is None:
        w = np.ones(points.shape[0])
    else:
        w = np.asarray(weights, dtype=float).reshape(-1)
        if w.shape[0] != points.shape[0]:
            raise ValueError(f"weights: {w.shape[0]} weights for {points.shape[0]} users")
        if not np.all(np.isfinite(w)) or np.any(w < 0):
            raise ValueError("weights: must be finite and >= 0")
    if not np.all(np.isfinite(points)):
        raise ValueError("points_xy_m: must be finite")
    keep = w > 0
    if not np.any(keep):
        keep = np.ones_like(keep)
        w = np.ones_like(w)
    points, w = points[keep], w[keep] / np.sum(w[keep])
    if points.shape[0] == 1:
        return points[0].copy()

    h2 = float(height_m) ** 2
    if h2 == 0.0 and len(points) <= _VERTEX_CHECK_MAX_USERS:
        # Weiszfeld crawls (sublinearly) toward a median that sits on a user: test the users.
        optimal = _optimal_users(points, w, np.arange(len(points)), config.coincident_m)
        if len(optimal):
            return points[optimal[0]].copy()
    p = w @ points  # weighted centroid: a good start, and exact for two equal users
    for _ in range(config.max_iterations):
        diff = points - p
        distance = np.sqrt(np.einsum("ij,ij->i", diff, diff) + h2)
        at = distance < config.coincident_m
        inv = np.where(at, 0.0, w / np.where(at, 1.0, distance))
        new = inv @ points / np.sum(inv) if np.any(inv > 0) else p
        if np.any(at):
            # Vardi & Zhang (2000): the users at p pull with total weight eta; p is optimal if
            # the others' resultant pull is weaker, otherwise step part of the way to T(p).
            eta = float(np.sum(w[at]))
            pull = inv @ diff
            strength = float(np.hypot(pull[0], pull[1]))
            if strength <= eta:
                return p.copy()
            new = (1.0 - eta / strength) * new + (eta / strength) * p
        else:
            # Over-relaxation: Weiszfeld's step is a descent direction but can be very short
            # (a flat objective, a median next to a heavy user); take the best multiple.
            trial = p + _STRETCH[:, None] * (new - p)  # (L, 2); the first is Weiszfeld's
            gap = trial[:, None, :] - points[None, :, :]
            cost = np.sqrt(np.sum(gap**2, axis=-1) + h2) @ w
            new = trial[int(np.argmin(cost))]
        step = float(np.hypot(*(new - p)))
        p = new
        if step < config.tolerance_m:
            break
    if h2 == 0.0:  # many users: test the one the iteration ended next to
        nearest = np.array([np.argmin(np.sum((points - p) ** 2, axis=1))])
        if len(_optimal_users(points, w, nearest, config.coincident_m)):
            return points[nearest[0]].copy()
    return p


def _optimal_users(
    points: np.ndarray, w: np.ndarray, candidates: np.ndarray, coincident_m: float
) -> np.ndarray:
    """The ``candidates`` (user indices) that are weighted geometric medians (ground metric).

    User j (with total weight eta_j at its spot) is a median iff the others' resultant pull,
    ``|Σ w_i (x_i − x_j) / |x_i − x_j||``, is at most eta_j (the subgradient condition).
    """
    diff = points[None, :, :] - points[candidates, None, :]  # [c, i] = x_i - x_c
    distance = np.sqrt(np.sum(diff**2, axis=-1))
    same = distance < coincident_m
    eta = np.sum(np.where(same, w[None, :], 0.0), axis=1)
    unit = diff / np.where(same, 1.0, distance)[..., None]
    pull = np.sum(np.where(same[..., None], 0.0, w[None, :, None] * unit), axis=1)
    strength = np.sqrt(np.sum(pull**2, axis=-1))
    return candidates[strength <= eta * (1.0 + 1e-12)]


# --------------------------------------------------------------------------------------------
# Baselines


@dataclass(frozen=True)
class MinDistancePlacement:
    """The paper's baseline: minimum mean distance to the users, at the minimum altitude.

    ``load_weighted=True`` weights each user's distance by its offered load (``load-weighted``).
    ``metric="3d"`` (default) minimises the 3-D distance from the UAV at ``z_min_m`` to users at
    ``user_height_m``; ``"ground"`` the ground distance (plain geometric median).
    ``altitude="best-snr"`` then flies at the altitude (on a 1 m grid) with the highest mean SNR
    over the users under the area's environment, ``frequency_hz`` its carrier
    (``min-distance-env``); ``"lowest"`` (default) at ``z_min_m``. On a site ``best-snr``
    chooses the whole position with the highest mean SNR the site gives
    (:func:`best_site_position_m`; the mean weighted by load with ``load_weighted``), ties
    going to the place nearest the min-distance point; ``frequency_hz`` is then unused (the
    site's losses are at the carrier it was built for).
    """

    area: AreaConfig = field(default_factory=AreaConfig)
    load_weighted: bool = False
    metric: DistanceMetric = "3d"
    median: MedianConfig = field(default_factory=MedianConfig)
    altitude: AltitudeRule = "lowest"
    frequency_hz: float = RadioConfig().frequency_hz

    def __post_init__(self) -> None:
        if self.metric not in ("3d", "ground"):
            raise ValueError(f"metric: must be '3d' or 'ground', got {self.metric!r}")
        if self.altitude not in ("lowest", "best-snr"):
            raise ValueError(f"altitude: must be 'lowest' or 'best-snr', got {self.altitude!r}")

    @property
    def name(self) -> str:
        if self.altitude == "best-snr":
            return "load-weighted-env" if self.load_weighted else "min-distance-env"
        return "load-weighted" if self.load_weighted else "min-distance"

    def place(self, scenario: UsersLike) -> np.ndarray:
        area = self.area
        height_m = area.z_min_m - area.user_height_m if self.metric == "3d" else 0.0
        weights = np.asarray(scenario.load_bps, dtype=float) if self.load_weighted else None
        xy_m = geometric_median(scenario.users_xy_m, weights, max(height_m, 0.0), self.median)
        z_m = area.z_min_m
        if self.altitude == "best-snr" and area.environment != "open":
            site = area_site(area)
            if site is not None:
                start_m = clip_to_volume(np.array([xy_m[0], xy_m[1], z_m]), area)
                return best_site_position_m(scenario.users_xy_m, area, site, weights, start_m)
            z_m = best_snr_altitude_m(scenario.users_xy_m, xy_m, area, self.frequency_hz)
        return clip_to_volume(np.array([xy_m[0], xy_m[1], z_m]), area)


def best_snr_altitude_m(
    users_xy_m: np.ndarray, xy_m: np.ndarray, area: AreaConfig, frequency_hz: float
) -> float:
    """The altitude above ``xy_m`` (on the :data:`ALTITUDE_STEP_M` grid of the altitude band)
    with the highest mean SNR over the users, i.e. the lowest mean path loss in dB."""
    steps = round((area.z_max_m - area.z_min_m) / ALTITUDE_STEP_M)
    heights_m = np.linspace(area.z_min_m, area.z_max_m, steps + 1)
    ground_m = np.hypot(users_xy_m[:, 0] - xy_m[0], users_xy_m[:, 1] - xy_m[1])
    loss_db = mean_path_loss_db(
        area.environment,
        ground_m[None, :],
        (heights_m - area.user_height_m)[:, None],
        frequency_hz,
    )
    return float(heights_m[int(np.argmin(loss_db.mean(axis=1)))])


# --------------------------------------------------------------------------------------------
# Sites


def site_mean_loss_db(
    site: Site, positions_xyz_m: np.ndarray, users_xy_m: np.ndarray, weights: np.ndarray | None
) -> np.ndarray:
    """The users' mean path loss in dB (N,) at each UAV position (N, 3) on ``site``, as the
    network model sees it: the site's loss, a link with no path at
    :data:`~sim.channel.NO_LINK_LOSS_DB`; weighted by ``weights`` (U,) when given (normalised;
    all zero: equal)."""
    from sim.sites.lookup import path_loss_db

    loss = np.minimum(path_loss_db(site, positions_xyz_m, users_xy_m), NO_LINK_LOSS_DB)
    if weights is None or not np.sum(weights) > 0:
        return loss.mean(axis=1)
    w = np.asarray(weights, dtype=float)
    return loss @ (w / w.sum())


def _lattice_axis(grid_m: np.ndarray, lo_m: float, hi_m: float) -> np.ndarray:
    """A search axis in [lo_m, hi_m]: the grid's points, the midpoints between neighbours (where
    the lookup's coverage can change) and both ends."""
    grid = np.asarray(grid_m, dtype=float)
    values = np.concatenate([grid, (grid[1:] + grid[:-1]) / 2.0, [lo_m, hi_m]])
    return np.unique(values[(values >= lo_m) & (values <= hi_m)])


def _above_roofs(site: Site, positions_xyz_m: np.ndarray) -> np.ndarray:
    """Whether each position (N, 3) is above the roof of the ground cell it hovers over (N,)."""
    from sim.sites.lookup import ground_cells

    row, column = ground_cells(site, positions_xyz_m[:, :2])
    return positions_xyz_m[:, 2] > site.building_height_m[row, column]


def best_site_position_m(
    users_xy_m: np.ndarray,
    area: AreaConfig,
    site: Site,
    weights: np.ndarray | None = None,
    start_xyz_m: np.ndarray | None = None,
) -> np.ndarray:
    """The position (3,) in ``area``'s flight volume, above the roofs, with the least mean path
    loss over the users on ``site`` (:func:`site_mean_loss_db`; the highest mean SNR): the best
    point of a lattice (the site's UAV grid, its midpoints and the volume's faces — between
    grid points the lookup is trilinear, so a covered link's mean loss is least at such a
    point), then a pattern search over the 26 neighbours from half the lattice's finest
    spacing down to :data:`SITE_REFINE_MIN_STEP_M`, each move taken only if it lowers the mean
    (it also finds where coverage changes off the lattice). Ties (within 1e-9 dB) go to the
    lattice point nearest ``start_xyz_m`` (default: the volume's centre at ``z_min_m``).
    Deterministic; never inside a building unless no lattice point is above the roofs."""
    users = np.asarray(users_xy_m, dtype=float).reshape(-1, 2)
    w = None if weights is None else np.asarray(weights, dtype=float)
    lower = np.array([0.0, 0.0, area.z_min_m])
    upper = np.array([area.size_x_m, area.size_y_m, area.z_max_m])
    start = (
        np.array([area.size_x_m / 2, area.size_y_m / 2, area.z_min_m])
        if start_xyz_m is None
        else np.clip(np.asarray(start_xyz_m, dtype=float), lower, upper)
    )
    axes = [
        _lattice_axis(grid, lo, hi)
        for grid, lo, hi in zip(
            (site.uav_x_m, site.uav_y_m, site.uav_z_m), lower, upper, strict=True
        )
    ]
    z, y, x = np.meshgrid(axes[2], axes[1], axes[0], indexing="ij")
    candidates = np.column_stack([x.ravel(), y.ravel(), z.ravel()])
    allowed = _above_roofs(site, candidates)
    if allowed.any():
        candidates = candidates[allowed]
    cost = site_mean_loss_db(site, candidates, users, w)
    ties = np.flatnonzero(cost <= cost.min() + 1e-9)
    gap = candidates[ties] - start
    best = candidates[ties[int(np.argmin(np.einsum("ij,ij->i", gap, gap)))]]
    best_cost = float(cost.min())
    spacing = [np.diff(a).min() for a in axes[:2] if a.size > 1]
    step = (min(spacing) if spacing else 2.0 * SITE_REFINE_MIN_STEP_M) / 2.0
    moves = np.array([(i, j, k) for i in (-1, 0, 1) for j in (-1, 0, 1) for k in (-1, 0, 1)])
    moves = moves[np.any(moves != 0, axis=1)].astype(float)
    for _ in range(SITE_REFINE_MAX_ROUNDS):
        if step < SITE_REFINE_MIN_STEP_M:
            break
        trial = np.clip(best + step * moves, lower, upper)
        trial = trial[_above_roofs(site, trial)]
        if trial.size:
            trial_cost = site_mean_loss_db(site, trial, users, w)
            i = int(np.argmin(trial_cost))
            if trial_cost[i] < best_cost - 1e-9:
                best, best_cost = trial[i], float(trial_cost[i])
                continue
        step /= 2.0
    return best.copy()
