"""Scenarios (users' positions and offered loads) and the seeded generator of scenario sets.

A *scenario* (paper §II) is a fixed combination of ground users' positions and their uplink
offered loads; a *case* is a scenario plus one fixed UAV position (what ``tupa sim evaluate``
simulates). Positions are in the area frame (origin at the south-west corner, x east, y north,
metres); loads in bit/s.

The generator follows the paper (§IV): users' x, y and loads are drawn from exponential
distributions, and the loads are rescaled to sum to Λ (40 Mbit/s). A single exponential from
one corner gives mostly clustered users with similar H, so each scenario also draws how spread
its users and loads are (see :class:`GeneratorConfig`): the set then spans the heterogeneity
index range the paper bins in steps of 0.05, including the upper bins where traffic-aware
placement pays off. With U users the load half of H is at most (1 − 1/U)/2, so with the paper's
3 users H tops out near 0.7, never 1.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from sim.config import AreaConfig, TrafficConfig
from sim.errors import InputError
from sim.utility import heterogeneity_index

_DEFAULT_AREA = AreaConfig()


def _frozen_array(value: object, shape_tail: tuple[int, ...], name: str) -> np.ndarray:
    """A read-only float64 copy of ``value`` with shape ``(U, *shape_tail)``, U >= 1."""
    array = np.array(value, dtype=np.float64)
    if array.ndim != 1 + len(shape_tail) or array.shape[1:] != shape_tail or array.shape[0] < 1:
        expected = "(U" + "".join(f", {n}" for n in shape_tail) + "), U >= 1"
        raise ValueError(f"{name}: expected shape {expected}, got {array.shape}")
    array.setflags(write=False)
    return array


@dataclass(frozen=True, eq=False)
class Scenario:
    """Ground users' positions and offered loads. Arrays are read-only float64 copies.

    ``users_xy_m``: shape (U, 2), area frame, metres. ``load_bps``: shape (U,), uplink offered
    load of each user in bit/s. Equality compares ids and arrays exactly.
    """

    id: str
    users_xy_m: np.ndarray  # (U, 2) float64
    load_bps: np.ndarray  # (U,) float64

    def __post_init__(self) -> None:
        xy = _frozen_array(self.users_xy_m, (2,), "users_xy_m")
        load = _frozen_array(self.load_bps, (), "load_bps")
        if load.shape[0] != xy.shape[0]:
            raise ValueError(
                f"load_bps: {load.shape[0]} loads for {xy.shape[0]} users (need one per user)"
            )
        bad_xy = ~np.isfinite(xy).all(axis=1)
        if bad_xy.any():
            user = int(np.argmax(bad_xy))
            raise ValueError(f"users_xy_m: user {user} has a non-finite position {xy[user]}")
        bad_load = ~(np.isfinite(load) & (load >= 0))
        if bad_load.any():
            user = int(np.argmax(bad_load))
            raise ValueError(f"load_bps: user {user} has {load[user]}, need a finite load >= 0")
        object.__setattr__(self, "users_xy_m", xy)
        object.__setattr__(self, "load_bps", load)

    @property
    def n_users(self) -> int:
        return int(self.load_bps.shape[0])

    def __eq__(self, other: object) -> bool:
        if not isinstance(other, Scenario):
            return NotImplemented
        return (
            self.id == other.id
            and np.array_equal(self.users_xy_m, other.users_xy_m)
            and np.array_equal(self.load_bps, other.load_bps)
        )


@dataclass(frozen=True, eq=False)
class Case:
    """A scenario plus a fixed UAV position ``uav_xyz_m`` (shape (3,), area frame, metres)."""

    id: str
    uav_xyz_m: np.ndarray  # (3,) float64
    users_xy_m: np.ndarray  # (U, 2) float64
    load_bps: np.ndarray  # (U,) float64

    def __post_init__(self) -> None:
        uav = np.array(self.uav_xyz_m, dtype=np.float64)
        if uav.shape != (3,):
            raise ValueError(f"uav_xyz_m: expected shape (3,), got {uav.shape}")
        uav.setflags(write=False)
        scenario = Scenario(self.id, self.users_xy_m, self.load_bps)  # validates the users
        object.__setattr__(self, "uav_xyz_m", uav)
        object.__setattr__(self, "users_xy_m", scenario.users_xy_m)
        object.__setattr__(self, "load_bps", scenario.load_bps)

    @property
    def n_users(self) -> int:
        return int(self.load_bps.shape[0])

    @property
    def scenario(self) -> Scenario:
        """The users of this case as a :class:`Scenario` with the same id."""
        return Scenario(self.id, self.users_xy_m, self.load_bps)

    def __eq__(self, other: object) -> bool:
        if not isinstance(other, Case):
            return NotImplemented
        return np.array_equal(self.uav_xyz_m, other.uav_xyz_m) and self.scenario == other.scenario


@dataclass(frozen=True)
class GeneratorConfig:
    """Constants of :func:`generate_scenarios`. Defaults give 3-user sets spanning H ≈ 0.0-0.7.

    Per scenario the generator draws:

    * a position scale, log-uniform in [``position_scale_min_m``, ``position_scale_max_m``]
      (``None``: the area's longer side). Small scales cluster the users, large ones spread them
      over the whole area.
    * a layout: with probability ``scatter_probability`` every user is measured from its own
      randomly chosen corner of the area, otherwise all users share one corner (the paper's
      clustered layout). The scattered layout fills the upper H bins, which one corner rarely
      reaches.
    * a load skew k, uniform in [0, ``load_skew_max``]: weights are Exp(1)**k, so k = 0 gives
      equal loads, k = 1 the paper's exponential loads, larger k one dominant user.

    Each coordinate is its distance from the corner, Exp(scale), *reflected* back into the area
    at the far edge (a value of size + d becomes size − d; clipping instead would pile users on
    the edges), then kept ``edge_margin_m`` away from the boundary so users lie strictly inside.

    Each user's load is at least ``min_load_share`` of the mean load Λ/U (1 % of Λ with 3
    users, 400 kbit/s for Λ = 40 Mbit/s): a user offering almost nothing would be a user in name
    only. Loads are then scaled to sum to Λ.
    """

    position_scale_min_m: float = 10.0
    position_scale_max_m: float | None = None
    scatter_probability: float = 0.3
    load_skew_max: float = 4.0
    min_load_share: float = 0.03
    edge_margin_m: float = 0.5

    def __post_init__(self) -> None:
        scale_max = self.position_scale_max_m
        if not (math.isfinite(self.position_scale_min_m) and self.position_scale_min_m > 0):
            raise ValueError(
                f"position_scale_min_m: must be a positive number, got {self.position_scale_min_m}"
            )
        if scale_max is not None and not (
            math.isfinite(scale_max) and scale_max >= self.position_scale_min_m
        ):
            raise ValueError(
                f"position_scale_max_m: must be >= position_scale_min_m, got {scale_max}"
            )
        if not 0.0 <= self.scatter_probability <= 1.0:
            raise ValueError(
                f"scatter_probability: must be in [0, 1], got {self.scatter_probability}"
            )
        if not (math.isfinite(self.load_skew_max) and self.load_skew_max >= 0):
            raise ValueError(f"load_skew_max: must be >= 0, got {self.load_skew_max}")
        if not 0.0 <= self.min_load_share <= 1.0:
            raise ValueError(f"min_load_share: must be in [0, 1], got {self.min_load_share}")
        if not (math.isfinite(self.edge_margin_m) and self.edge_margin_m >= 0):
            raise ValueError(f"edge_margin_m: must be >= 0, got {self.edge_margin_m}")


def _reflect_into(distance_m: np.ndarray, size_m: np.ndarray) -> np.ndarray:
    """Fold non-negative distances into [0, size] by reflecting at both edges."""
    folded = np.mod(distance_m, 2.0 * size_m)
    return np.where(folded > size_m, 2.0 * size_m - folded, folded)


def _draw_scenario(
    rng: np.random.Generator,
    scenario_id: str,
    n_users: int,
    area: AreaConfig,
    total_load_bps: float,
    config: GeneratorConfig,
) -> Scenario:
    size_m = np.array([area.size_x_m, area.size_y_m])
    scale_max_m = config.position_scale_max_m or float(size_m.max())
    scale_m = math.exp(rng.uniform(math.log(config.position_scale_min_m), math.log(scale_max_m)))
    if rng.random() < config.scatter_probability:
        corner = rng.integers(0, 2, size=(n_users, 2))
    else:
        corner = np.broadcast_to(rng.integers(0, 2, size=(1, 2)), (n_users, 2))
    skew = rng.uniform(0.0, config.load_skew_max)

    distance_m = _reflect_into(rng.exponential(scale_m, size=(n_users, 2)), size_m)
    xy_m = np.where(corner == 1, size_m - distance_m, distance_m)
    margin_m = np.minimum(config.edge_margin_m, size_m / 4.0)
    xy_m = np.clip(xy_m, margin_m, size_m - margin_m)

    weights = rng.exponential(1.0, size=n_users) ** skew
    weight_sum = float(weights.sum())
    shares = weights / weight_sum if weight_sum > 0 else np.full(n_users, 1.0 / n_users)
    floor_share = config.min_load_share / n_users
    shares = floor_share + (1.0 - n_users * floor_share) * shares
    load_bps = total_load_bps * shares
    load_bps *= total_load_bps / load_bps.sum()  # remove rounding drift in the sum
    return Scenario(scenario_id, xy_m, load_bps)


def generate_scenarios(
    n: int,
    n_users: int,
    seed: int,
    area: AreaConfig = _DEFAULT_AREA,
    total_load_bps: float = TrafficConfig.total_load_bps,
    config: GeneratorConfig = GeneratorConfig(),
) -> list[Scenario]:
    """Draw ``n`` scenarios of ``n_users`` users each, ids ``s0000``, ``s0001``, ...

    Deterministic given the arguments. Scenario i is drawn from its own stream
    ``default_rng(SeedSequence(seed, spawn_key=(i,)))``, so a set is a prefix of any larger set
    drawn with the same seed, users, area and config. Every user lies strictly inside the area,
    every load is positive and the loads sum to ``total_load_bps`` (to rounding).
    """
    if n < 0:
        raise InputError(f"n: must be >= 0, got {n}")
    if n_users < 1:
        raise InputError(f"n_users: must be >= 1, got {n_users}")
    if not (math.isfinite(total_load_bps) and total_load_bps > 0):
        raise InputError(f"total_load_bps: must be a positive number, got {total_load_bps}")
    width = max(4, len(str(n - 1)))
    return [
        _draw_scenario(
            np.random.default_rng(np.random.SeedSequence(seed, spawn_key=(i,))),
            f"s{i:0{width}d}",
            n_users,
            area,
            float(total_load_bps),
            config,
        )
        for i in range(n)
    ]


def heterogeneity_indices(scenarios: Sequence[Scenario], area: AreaConfig) -> np.ndarray:
    """Heterogeneity index H (paper eq. 3) of each scenario, shape (len(scenarios),)."""
    return np.array(
        [heterogeneity_index(s.users_xy_m, s.load_bps, area) for s in scenarios], dtype=float
    )


def heterogeneity_histogram(
    scenarios: Sequence[Scenario], area: AreaConfig, bin_width: float = 0.05
) -> list[tuple[float, float, int]]:
    """Count scenarios per H bin: ``(lo, hi, count)`` for bins [lo, hi) covering [0, 1].

    The last bin is closed (H = 1 falls in it). ``bin_width`` must divide 1 (0.05: 20 bins,
    as in the paper's per-heterogeneity figure).
    """
    n_bins_float = 1.0 / bin_width if bin_width > 0 else math.inf
    n_bins = round(n_bins_float) if math.isfinite(n_bins_float) else 0
    if n_bins < 1 or abs(n_bins_float - n_bins) > 1e-9:
        raise ValueError(f"bin_width: must divide 1 (e.g. 0.05), got {bin_width}")
    h = heterogeneity_indices(scenarios, area)
    # Round before flooring so that H = 0.1 lands in [0.10, 0.15) despite 0.1 / 0.05 rounding.
    index = np.clip(np.floor(np.round(h * n_bins, 9)).astype(int), 0, n_bins - 1)
    counts = np.bincount(index, minlength=n_bins)
    return [
        (round(i / n_bins, 12), round((i + 1) / n_bins, 12), int(counts[i])) for i in range(n_bins)
    ]


def format_heterogeneity_histogram(
    scenarios: Sequence[Scenario], area: AreaConfig, bar_width: int = 40
) -> str:
    """A text histogram of H in 0.05 bins for the terminal, empty bins at the top end left out.

    The longest bar is ``bar_width`` '#' characters; a non-empty bin always shows at least one.
    """
    if not scenarios:
        return "heterogeneity index H: no scenarios"
    bins = heterogeneity_histogram(scenarios, area)
    h = heterogeneity_indices(scenarios, area)
    last = max(i for i, (_, _, count) in enumerate(bins) if count > 0)
    peak = max(count for _, _, count in bins)
    lines = [
        f"heterogeneity index H of {len(scenarios)} scenarios: "
        f"min {h.min():.3f}, median {np.median(h):.3f}, max {h.max():.3f}"
    ]
    for lo, hi, count in bins[: last + 1]:
        bar = "#" * (max(1, round(bar_width * count / peak)) if count else 0)
        lines.append(f"  [{lo:.2f}, {hi:.2f})  {count:5d}  {bar}")
    return "\n".join(lines)
