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

Beyond the paper, the generator has named *families* of layouts (:data:`FAMILIES`, knobs in
:class:`FamilyConfig`), for any user count 1..300 (:data:`MAX_USERS`):

* ``exponential`` (the default): the paper's generator above, bit-for-bit what it always drew.
* ``uniform``: every user uniform over the area.
* ``hotspots``: 1-4 hot spots at uniform random centres; each user joins one at random and lies
  at a Gaussian offset from its centre, with a per-scenario spread (σ log-uniform in 10-60 m),
  clipped into the area.
* ``corners``: 1-4 of the four corners picked at random (any of them, not only the corner the
  paper's single exponential measures from); each user joins one and lies at Exp(scale)
  distances from it along x and y, with a per-scenario scale (log-uniform in 10-80 m),
  reflected back into the area like the exponential family.
* ``mixture``: each scenario first draws one of the families above (equally likely), then is
  drawn from it.

Three more families (:data:`SITE_FAMILIES`) put users where people are in a real district and so
need a site (``area.environment`` ``site:PATH``; refused in one line elsewhere,
:func:`check_family_area`). They read the site's walkable ground (cells of the area outside
buildings) through one analysis (:func:`site_ground`): each walkable cell's *clearance* (the
distance from its centre to the nearest non-walkable cell's centre; the area's edge is not a
wall), the *open* ground (what a disc of radius r = ``street_width_max_m / 2`` covers when
rolled over walkable ground without touching a wall, the morphological opening: the walkable
cells within r of a cell whose clearance is at least r plus half a cell), and the *street*
ground (walkable but not open: passages narrower than ``street_width_max_m``, in 8-connected
pieces at least ``street_length_min_m`` long, the bounding box's diagonal; shorter nooks are
dropped).

* ``streets``: 1-``street_segments_max`` stretches of street per scenario, each the street cells
  within ``L/2`` of a street cell drawn uniformly, counted in 8-connected steps along the street
  (L log-uniform in [``street_segment_min_m``, ``street_segment_max_m``]); each user joins a
  stretch at random and stands in one of its cells.
* ``squares``: the open ground's 8-connected pieces, largest first; each scenario draws how many
  of the ``squares_max`` largest it uses (uniform in 1..that many) and which, and its users stand
  uniformly over their cells (a larger square holds more users).
* ``crowd``: a strict majority of the users (a share uniform in [``crowd_share_min``,
  ``crowd_share_max``]) stand in the walkable cells whose centres lie within ``crowd_radius_m``
  of the centre of one walkable cell drawn uniformly (those reachable from it without leaving
  the disc: a crowd does not stand behind a wall), the others uniformly over the area's
  walkable ground.

In each, a user stands uniformly inside its cell, kept ``min(edge_margin_m, cell_m / 4)`` from
the cell's edges (so on walkable ground and strictly inside the area), and loads follow the
common load model below. Deterministic per seed, like every family.

Every family uses the same load model: per-scenario skew, loads Exp(1)**skew with a floor,
scaled to sum to Λ (see :class:`GeneratorConfig`), so each family spans a range of load
heterogeneity. Every user lies strictly inside the area.

**On a site** (``area.environment`` ``site:PATH``, :mod:`sim.sites`) users stand on walkable
ground only (:func:`sim.sites.ground.place_on_walkable`): after the scenario's layout and loads
are drawn as anywhere else, each user that landed inside a building is drawn again from the same
layout (the same scale and corner, hot spot set, ...: only its own position is new), from the
scenario's own stream, up to :data:`~sim.sites.ground.PLACEMENT_TRIES` times; one still inside
then moves to the centre of the nearest walkable cell. Deterministic per seed; outside a site
nothing changes (the same draws, bit for bit). :func:`check_scenario_area` refuses a scenario
with a user inside a building.

:class:`ScenarioSampler` draws one scenario at a time from a set of families and a range of user
counts: what training uses for domain randomisation (a fresh scenario per episode).
"""

from __future__ import annotations

import hashlib
import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import numpy as np
from numba import njit

from sim.channel import area_site
from sim.config import AreaConfig, TrafficConfig, site_path
from sim.errors import InputError
from sim.utility import heterogeneity_index

if TYPE_CHECKING:
    from sim.sites.format import Site

_DEFAULT_AREA = AreaConfig()

FAMILIES: tuple[str, ...] = ("exponential", "uniform", "hotspots", "corners", "mixture")
"""The scenario families :func:`generate_scenarios` and :class:`ScenarioSampler` know anywhere."""

SITE_FAMILIES: tuple[str, ...] = ("streets", "squares", "crowd")
"""The families that need a site (module doc): users in its streets, its squares, a crowd."""

MAX_USERS = 300
"""The most users a generated scenario may have."""


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


@dataclass(frozen=True)
class FamilyConfig:
    """Knobs of the families other than ``exponential`` (see the module docstring).

    Per scenario, ``hotspots`` draws a number of hot spots uniform in [``hotspots_min``,
    ``hotspots_max``] and a spread σ log-uniform in [``hotspot_spread_min_m``,
    ``hotspot_spread_max_m``]; ``corners`` draws a number of corners uniform in [1,
    ``corners_max``] and a distance scale log-uniform in [``corner_scale_min_m``,
    ``corner_scale_max_m``]; ``mixture`` draws one of ``mixture_families``, equally likely (list
    a family twice to weight it double; the site families are not mixed). The site families'
    knobs (``street_*``, ``squares_max``, ``crowd_*``) are described in the module doc. Loads
    and the edge margin follow :class:`GeneratorConfig`.
    """

    hotspots_min: int = 1
    hotspots_max: int = 4
    hotspot_spread_min_m: float = 10.0
    hotspot_spread_max_m: float = 60.0
    corners_max: int = 4
    corner_scale_min_m: float = 10.0
    corner_scale_max_m: float = 80.0
    mixture_families: tuple[str, ...] = ("exponential", "uniform", "hotspots", "corners")
    street_width_max_m: float = 30.0
    street_length_min_m: float = 40.0
    street_segments_max: int = 3
    street_segment_min_m: float = 40.0
    street_segment_max_m: float = 200.0
    squares_max: int = 3
    crowd_radius_m: float = 20.0
    crowd_share_min: float = 0.6
    crowd_share_max: float = 0.95

    def __post_init__(self) -> None:
        def positive_range(lo_name: str, hi_name: str) -> None:
            lo, hi = getattr(self, lo_name), getattr(self, hi_name)
            if not (math.isfinite(lo) and lo > 0):
                raise ValueError(f"{lo_name}: must be a positive number, got {lo}")
            if not (math.isfinite(hi) and hi >= lo):
                raise ValueError(f"{hi_name}: must be a number >= {lo_name} ({lo}), got {hi}")

        if not 1 <= self.hotspots_min <= self.hotspots_max:
            raise ValueError(
                f"hotspots_min/hotspots_max: need 1 <= hotspots_min <= hotspots_max, "
                f"got {self.hotspots_min} and {self.hotspots_max}"
            )
        positive_range("hotspot_spread_min_m", "hotspot_spread_max_m")
        if not 1 <= self.corners_max <= 4:
            raise ValueError(f"corners_max: must be in 1..4, got {self.corners_max}")
        positive_range("corner_scale_min_m", "corner_scale_max_m")
        positive_range("street_segment_min_m", "street_segment_max_m")
        for name in ("street_width_max_m", "street_length_min_m", "crowd_radius_m"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value > 0):
                raise ValueError(f"{name}: must be a positive number, got {value}")
        for name in ("street_segments_max", "squares_max"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int) or value < 1:
                raise ValueError(f"{name}: must be a whole number >= 1, got {value!r}")
        if not 0.5 < self.crowd_share_min <= self.crowd_share_max <= 1.0:
            raise ValueError(
                f"crowd_share_min/crowd_share_max: need 0.5 < crowd_share_min <= "
                f"crowd_share_max <= 1, got {self.crowd_share_min} and {self.crowd_share_max}"
            )
        mixture = self.mixture_families
        if isinstance(mixture, str):
            mixture = (mixture,)
        mixture = tuple(mixture)
        allowed = tuple(f for f in FAMILIES if f != "mixture")
        if not mixture or any(f not in allowed for f in mixture):
            raise ValueError(
                f"mixture_families: need one or more of {', '.join(allowed)}, got {mixture!r}"
            )
        object.__setattr__(self, "mixture_families", mixture)


def _reflect_into(distance_m: np.ndarray, size_m: np.ndarray) -> np.ndarray:
    """Fold non-negative distances into [0, size] by reflecting at both edges."""
    folded = np.mod(distance_m, 2.0 * size_m)
    return np.where(folded > size_m, 2.0 * size_m - folded, folded)


def _log_uniform(rng: np.random.Generator, lo: float, hi: float) -> float:
    return math.exp(rng.uniform(math.log(lo), math.log(hi)))


# A family's layout draws its users' positions: (rng, which users) -> (len(which), 2). The first
# call draws everybody; on a site, later calls draw again those inside buildings, the scenario's
# parameters (scale, corners, hot spots) unchanged.
_Layout = Callable[[np.random.Generator, np.ndarray], np.ndarray]


def _exponential_xy(
    rng: np.random.Generator,
    n_users: int,
    size_m: np.ndarray,
    margin_m: np.ndarray,
    config: GeneratorConfig,
) -> tuple[np.ndarray, float, _Layout]:
    """The paper's layout and the load skew, in the draw order the generator always used."""
    scale_max_m = config.position_scale_max_m or float(size_m.max())
    scale_m = _log_uniform(rng, config.position_scale_min_m, scale_max_m)
    if rng.random() < config.scatter_probability:
        corner = rng.integers(0, 2, size=(n_users, 2))
    else:
        corner = np.broadcast_to(rng.integers(0, 2, size=(1, 2)), (n_users, 2))
    skew = rng.uniform(0.0, config.load_skew_max)

    def layout(rng: np.random.Generator, which: np.ndarray) -> np.ndarray:
        distance_m = _reflect_into(rng.exponential(scale_m, size=(which.size, 2)), size_m)
        xy_m = np.where(corner[which] == 1, size_m - distance_m, distance_m)
        return np.clip(xy_m, margin_m, size_m - margin_m)

    return layout(rng, np.arange(n_users)), skew, layout


def _uniform_xy(
    rng: np.random.Generator, n_users: int, size_m: np.ndarray, margin_m: np.ndarray
) -> tuple[np.ndarray, _Layout]:
    def layout(rng: np.random.Generator, which: np.ndarray) -> np.ndarray:
        return rng.uniform(margin_m, size_m - margin_m, size=(which.size, 2))

    return layout(rng, np.arange(n_users)), layout


def _hotspots_xy(
    rng: np.random.Generator,
    n_users: int,
    size_m: np.ndarray,
    margin_m: np.ndarray,
    families: FamilyConfig,
) -> tuple[np.ndarray, _Layout]:
    n_spots = int(rng.integers(families.hotspots_min, families.hotspots_max + 1))
    centres_m = rng.uniform(margin_m, size_m - margin_m, size=(n_spots, 2))
    spread_m = _log_uniform(rng, families.hotspot_spread_min_m, families.hotspot_spread_max_m)
    spot = rng.integers(0, n_spots, size=n_users)

    def layout(rng: np.random.Generator, which: np.ndarray) -> np.ndarray:
        xy_m = centres_m[spot[which]] + rng.normal(0.0, spread_m, size=(which.size, 2))
        return np.clip(xy_m, margin_m, size_m - margin_m)

    return layout(rng, np.arange(n_users)), layout


def _corners_xy(
    rng: np.random.Generator,
    n_users: int,
    size_m: np.ndarray,
    margin_m: np.ndarray,
    families: FamilyConfig,
) -> tuple[np.ndarray, _Layout]:
    n_corners = int(rng.integers(1, families.corners_max + 1))
    corners = rng.permutation(4)[:n_corners]  # corner c: x at the far edge if c & 1, y if c & 2
    scale_m = _log_uniform(rng, families.corner_scale_min_m, families.corner_scale_max_m)
    corner = corners[rng.integers(0, n_corners, size=n_users)]
    far = np.stack([corner & 1, corner >> 1], axis=1)

    def layout(rng: np.random.Generator, which: np.ndarray) -> np.ndarray:
        distance_m = _reflect_into(rng.exponential(scale_m, size=(which.size, 2)), size_m)
        xy_m = np.where(far[which] == 1, size_m - distance_m, distance_m)
        return np.clip(xy_m, margin_m, size_m - margin_m)

    return layout(rng, np.arange(n_users)), layout


# --------------------------------------------------------------------------------------------
# The site families: the walkable ground's streets and squares (module doc)


@dataclass(frozen=True)
class SiteGround:
    """The walkable ground of a site's area as the site families read it (module doc). Masks
    are (rows, columns) over the ground cells lying wholly inside the area (cell (j, i) is
    ``[i·cell_m, (i+1)·cell_m] × [j·cell_m, (j+1)·cell_m]``); cell lists are flat indices
    ``j·columns + i``, ascending. ``squares`` lists the open ground's 8-connected pieces,
    largest first (ties: the piece whose first cell comes first)."""

    cell_m: float
    walkable: np.ndarray
    clearance_m: np.ndarray
    open: np.ndarray
    street: np.ndarray
    walkable_cells: np.ndarray
    street_cells: np.ndarray
    squares: tuple[np.ndarray, ...]

    @property
    def columns(self) -> int:
        return int(self.walkable.shape[1])


@njit(cache=True, nogil=True)
def _clearance_kernel(wall: np.ndarray, cap: int) -> np.ndarray:
    """Each cell's distance (in cells, centre to centre) to the nearest ``wall`` cell, looked
    for within ``cap`` cells; ``cap + 1`` where none is that close."""
    rows, columns = wall.shape
    out = np.full((rows, columns), cap + 1.0)
    for j in range(rows):
        for i in range(columns):
            best = (cap + 1.0) ** 2
            for dj in range(-cap, cap + 1):
                jj = j + dj
                if jj < 0 or jj >= rows:
                    continue
                for di in range(-cap, cap + 1):
                    ii = i + di
                    if 0 <= ii < columns and wall[jj, ii]:
                        d2 = float(dj * dj + di * di)
                        if d2 < best:
                            best = d2
            out[j, i] = math.sqrt(best)
    return out


@njit(cache=True, nogil=True)
def _dilate_kernel(core: np.ndarray, allowed: np.ndarray, radius: float) -> np.ndarray:
    """The ``allowed`` cells whose centre lies within ``radius`` cells of a ``core`` cell's."""
    rows, columns = core.shape
    reach = math.floor(radius)
    out = np.zeros((rows, columns), dtype=np.bool_)
    for j in range(rows):
        for i in range(columns):
            if not core[j, i]:
                continue
            for dj in range(-reach, reach + 1):
                jj = j + dj
                if jj < 0 or jj >= rows:
                    continue
                for di in range(-reach, reach + 1):
                    ii = i + di
                    if 0 <= ii < columns and allowed[jj, ii] and dj * dj + di * di <= radius**2:
                        out[jj, ii] = True
    return out


@njit(cache=True, nogil=True)
def _steps_kernel(mask: np.ndarray, start: int, max_steps: int) -> np.ndarray:
    """8-connected breadth-first steps from cell ``start`` (flat index) over ``mask``, at most
    ``max_steps`` (negative: no limit): (rows, columns) int64, -1 where not reached."""
    rows, columns = mask.shape
    steps = np.full(rows * columns, -1, dtype=np.int64)
    queue = np.empty(rows * columns, dtype=np.int64)
    if not mask.ravel()[start]:
        return steps.reshape(rows, columns)
    steps[start] = 0
    queue[0] = start
    head, tail = 0, 1
    while head < tail:
        cell = queue[head]
        head += 1
        if 0 <= max_steps <= steps[cell]:
            continue
        j, i = cell // columns, cell % columns
        for dj in (-1, 0, 1):
            for di in (-1, 0, 1):
                jj, ii = j + dj, i + di
                if 0 <= jj < rows and 0 <= ii < columns and mask[jj, ii]:
                    other = jj * columns + ii
                    if steps[other] < 0:
                        steps[other] = steps[cell] + 1
                        queue[tail] = other
                        tail += 1
    return steps.reshape(rows, columns)


def _pieces(mask: np.ndarray) -> list[np.ndarray]:
    """The 8-connected pieces of ``mask`` as ascending flat cell indices, in the order of their
    first cell."""
    left = mask.copy()
    pieces = []
    for start in np.flatnonzero(mask):
        if left.ravel()[start]:
            cells = np.flatnonzero(_steps_kernel(left, int(start), -1) >= 0)
            left.ravel()[cells] = False
            pieces.append(cells)
    return pieces


_GROUND_CACHE: dict[tuple[object, ...], SiteGround] = {}
_GROUND_CACHE_SIZE = 8


def site_ground(site: Site, area: AreaConfig, families: FamilyConfig) -> SiteGround:
    """The analysis of ``site``'s walkable ground inside ``area`` that the site families draw
    from (module doc), computed once per mask, area and knobs."""
    cell_m = float(site.cell_m)
    columns = min(math.floor(area.size_x_m / cell_m + 1e-9), site.cells_x)
    rows = min(math.floor(area.size_y_m / cell_m + 1e-9), site.cells_y)
    walkable = np.ascontiguousarray(site.walkable[:rows, :columns])
    width_m, length_m = families.street_width_max_m, families.street_length_min_m
    digest = hashlib.sha1(walkable.tobytes()).hexdigest()
    key = (digest, walkable.shape, cell_m, width_m, length_m)
    if key in _GROUND_CACHE:
        return _GROUND_CACHE[key]
    radius_m = width_m / 2.0
    # A disc of radius r fits around a cell whose nearest wall centre is r + half a cell away.
    cap = math.ceil((radius_m + cell_m) / cell_m) + 1
    clearance_m = _clearance_kernel(~walkable, cap) * cell_m
    core = walkable & (clearance_m >= radius_m + cell_m / 2.0)
    open_ground = _dilate_kernel(core, walkable, radius_m / cell_m)
    narrow = walkable & ~open_ground
    street = np.zeros_like(narrow)
    for cells in _pieces(narrow):
        j, i = np.divmod(cells, columns)
        if math.hypot(np.ptp(i) + 1, np.ptp(j) + 1) * cell_m >= length_m:
            street.ravel()[cells] = True
    squares = sorted(_pieces(open_ground), key=lambda cells: (-cells.size, int(cells[0])))
    ground = SiteGround(
        cell_m=cell_m,
        walkable=walkable,
        clearance_m=clearance_m,
        open=open_ground,
        street=street,
        walkable_cells=np.flatnonzero(walkable),
        street_cells=np.flatnonzero(street),
        squares=tuple(squares),
    )
    for array in (
        walkable, clearance_m, open_ground, street, ground.walkable_cells, ground.street_cells,
        *squares,
    ):  # fmt: skip
        array.setflags(write=False)
    if len(_GROUND_CACHE) >= _GROUND_CACHE_SIZE:
        _GROUND_CACHE.pop(next(iter(_GROUND_CACHE)))
    _GROUND_CACHE[key] = ground
    return ground


def _in_cells(
    rng: np.random.Generator, ground: SiteGround, cells: np.ndarray, n: int, margin_m: float
) -> np.ndarray:
    """``n`` users (n, 2), each in a cell drawn uniformly from ``cells`` (flat indices), uniform
    inside it at least ``margin_m`` from its edges."""
    picked = cells[rng.integers(0, cells.size, size=n)]
    j, i = np.divmod(picked, ground.columns)
    offset = rng.uniform(margin_m, ground.cell_m - margin_m, size=(n, 2))
    return np.column_stack([i * ground.cell_m + offset[:, 0], j * ground.cell_m + offset[:, 1]])


def _site_family_xy(
    rng: np.random.Generator,
    family: str,
    n_users: int,
    ground: SiteGround,
    margin_m: float,
    families: FamilyConfig,
    environment: str,
) -> np.ndarray:
    """Users' positions (U, 2) of a site family (module doc); InputError naming ``family``
    when the site has no ground of the kind the family needs."""

    def missing(what: str) -> InputError:
        return InputError(f"family: {family!r}: {environment} has {what} in the area")

    cell_m = ground.cell_m
    if family == "streets":
        if ground.street_cells.size == 0:
            raise missing(
                f"no street (walkable passages narrower than {families.street_width_max_m:g} m, "
                f"at least {families.street_length_min_m:g} m long)"
            )
        n_stretches = int(rng.integers(1, families.street_segments_max + 1))
        stretches = []
        for _ in range(n_stretches):
            seed = int(ground.street_cells[rng.integers(0, ground.street_cells.size)])
            length_m = _log_uniform(
                rng, families.street_segment_min_m, families.street_segment_max_m
            )
            reach = int(length_m / 2.0 // cell_m)
            stretches.append(np.flatnonzero(_steps_kernel(ground.street, seed, reach) >= 0))
        member = rng.integers(0, n_stretches, size=n_users)
        xy = np.empty((n_users, 2))
        for k, cells in enumerate(stretches):
            mine = np.flatnonzero(member == k)
            xy[mine] = _in_cells(rng, ground, cells, mine.size, margin_m)
        return xy
    if family == "squares":
        if not ground.squares:
            raise missing(
                f"no open walkable ground (nowhere a {families.street_width_max_m:g} m wide "
                "disc fits between buildings)"
            )
        available = min(families.squares_max, len(ground.squares))
        used = np.sort(rng.permutation(available)[: int(rng.integers(1, available + 1))])
        cells = np.concatenate([ground.squares[k] for k in used])
        return _in_cells(rng, ground, cells, n_users, margin_m)
    # crowd
    if ground.walkable_cells.size == 0:
        raise missing("no walkable ground")
    centre = int(ground.walkable_cells[rng.integers(0, ground.walkable_cells.size)])
    share = rng.uniform(families.crowd_share_min, families.crowd_share_max)
    in_crowd = min(n_users, max(n_users // 2 + 1, round(share * n_users)))
    rows, columns = ground.walkable.shape
    cj, ci = divmod(centre, columns)
    jj, ii = np.mgrid[0:rows, 0:columns]
    disc = ground.walkable & (
        (jj - cj) ** 2 + (ii - ci) ** 2 <= (families.crowd_radius_m / cell_m) ** 2
    )
    cells = np.flatnonzero(_steps_kernel(disc, centre, -1) >= 0)
    crowd = _in_cells(rng, ground, cells, in_crowd, margin_m)
    rest = _in_cells(rng, ground, ground.walkable_cells, n_users - in_crowd, margin_m)
    return np.vstack([crowd, rest])


def _loads(
    rng: np.random.Generator,
    n_users: int,
    skew: float,
    total_load_bps: float,
    config: GeneratorConfig,
) -> np.ndarray:
    weights = rng.exponential(1.0, size=n_users) ** skew
    weight_sum = float(weights.sum())
    shares = weights / weight_sum if weight_sum > 0 else np.full(n_users, 1.0 / n_users)
    floor_share = config.min_load_share / n_users
    shares = floor_share + (1.0 - n_users * floor_share) * shares
    load_bps = total_load_bps * shares
    load_bps *= total_load_bps / load_bps.sum()  # remove rounding drift in the sum
    return load_bps


def _draw(
    rng: np.random.Generator,
    family: str,
    n_users: int,
    area: AreaConfig,
    total_load_bps: float,
    config: GeneratorConfig,
    families: FamilyConfig,
) -> tuple[np.ndarray, np.ndarray, str]:
    """Users' positions, loads, and the family drawn (for ``mixture``, the one it picked).
    On a site, users inside buildings are then drawn again (module doc); the site families
    draw on walkable ground directly."""
    if family in SITE_FAMILIES:
        site = area_site(area)
        if site is None:
            raise InputError(_needs_site(family, area.environment))
        ground = site_ground(site, area, families)
        margin_m = min(config.edge_margin_m, ground.cell_m / 4.0)
        xy_m = _site_family_xy(rng, family, n_users, ground, margin_m, families, area.environment)
        skew = rng.uniform(0.0, config.load_skew_max)
        return xy_m, _loads(rng, n_users, skew, total_load_bps, config), family
    if family == "mixture":
        mixture = families.mixture_families
        family = mixture[int(rng.integers(0, len(mixture)))]
    size_m = np.array([area.size_x_m, area.size_y_m])
    margin_m = np.minimum(config.edge_margin_m, size_m / 4.0)
    if family == "exponential":
        xy_m, skew, layout = _exponential_xy(rng, n_users, size_m, margin_m, config)
    else:
        if family == "uniform":
            xy_m, layout = _uniform_xy(rng, n_users, size_m, margin_m)
        elif family == "hotspots":
            xy_m, layout = _hotspots_xy(rng, n_users, size_m, margin_m, families)
        else:
            xy_m, layout = _corners_xy(rng, n_users, size_m, margin_m, families)
        skew = rng.uniform(0.0, config.load_skew_max)
    load_bps = _loads(rng, n_users, skew, total_load_bps, config)
    site = area_site(area)
    if site is not None:
        from sim.sites.ground import place_on_walkable

        xy_m = place_on_walkable(
            site, xy_m, lambda which: layout(rng, which), area.size_x_m, area.size_y_m
        )
    return xy_m, load_bps, family


def _label(family: str, drawn: str) -> str:
    return family if family != "mixture" else f"mixture-{drawn}"


def _check_family(family: object, name: str = "family") -> str:
    if not isinstance(family, str) or family not in (*FAMILIES, *SITE_FAMILIES):
        raise InputError(
            f"{name}: unknown family {family!r} (choose from {', '.join(FAMILIES)}; on a site "
            f"also {', '.join(SITE_FAMILIES)})"
        )
    return family


def _needs_site(family: str, environment: str, name: str = "family") -> str:
    return (
        f"{name}: {family!r} needs a site (environment site:PATH: its streets, squares and "
        f"walkable ground), got environment {environment!r}"
    )


def check_family_area(family: str, area: AreaConfig, name: str = "family") -> None:
    """InputError of one line naming ``name`` for an unknown family, or a site family
    (:data:`SITE_FAMILIES`) asked for off a site."""
    _check_family(family, name)
    if family in SITE_FAMILIES and site_path(area.environment) is None:
        raise InputError(_needs_site(family, area.environment, name))


def _check_users(n_users: object, name: str = "n_users") -> int:
    if (
        isinstance(n_users, bool)
        or not isinstance(n_users, int | np.integer)
        or not 1 <= n_users <= MAX_USERS
    ):
        raise InputError(f"{name}: must be a whole number in 1..{MAX_USERS}, got {n_users!r}")
    return int(n_users)


def _check_total_load(total_load_bps: object) -> float:
    if (
        isinstance(total_load_bps, bool)
        or not isinstance(total_load_bps, int | float | np.integer | np.floating)
        or not (math.isfinite(total_load_bps) and total_load_bps > 0)
    ):
        raise InputError(f"total_load_bps: must be a positive number, got {total_load_bps!r}")
    return float(total_load_bps)


def _stream(seed: int, index: int) -> np.random.Generator:
    return np.random.default_rng(np.random.SeedSequence(seed, spawn_key=(index,)))


def generate_scenarios(
    n: int,
    n_users: int,
    seed: int,
    area: AreaConfig = _DEFAULT_AREA,
    total_load_bps: float = TrafficConfig.total_load_bps,
    config: GeneratorConfig = GeneratorConfig(),
    family: str = "exponential",
    family_config: FamilyConfig | None = None,
) -> list[Scenario]:
    """Draw ``n`` scenarios of ``n_users`` users (1..300) each from ``family`` (see
    :data:`FAMILIES`; on a site also :data:`SITE_FAMILIES`).

    Ids are ``s0000``, ``s0001``, ... for the ``exponential`` family (as they always were),
    ``s0000-<family>`` for the others, and ``s0000-mixture-<family drawn>`` for ``mixture``.

    Deterministic given the arguments. Scenario i is drawn from its own stream
    ``default_rng(SeedSequence(seed, spawn_key=(i,)))``, so a set is a prefix of any larger set
    drawn with the same seed, users, area, configs and family. Every user lies strictly inside
    the area, every load is positive and the loads sum to ``total_load_bps`` (to rounding).
    Bad arguments raise :class:`InputError` naming the argument.
    """
    if n < 0:
        raise InputError(f"n: must be >= 0, got {n}")
    n_users = _check_users(n_users)
    total_load_bps = _check_total_load(total_load_bps)
    check_family_area(family, area)
    families = FamilyConfig() if family_config is None else family_config
    width = max(4, len(str(n - 1)))
    scenarios = []
    for i in range(n):
        xy_m, load_bps, drawn = _draw(
            _stream(seed, i), family, n_users, area, total_load_bps, config, families
        )
        suffix = "" if family == "exponential" else f"-{_label(family, drawn)}"
        scenarios.append(Scenario(f"s{i:0{width}d}{suffix}", xy_m, load_bps))
    return scenarios


# A spawn key no scenario stream uses (a set never has 2**32 scenarios): the sampler's picks.
_PICK_KEY = 2**32


@dataclass(frozen=True)
class ScenarioSampler:
    """Draws one scenario at a time, for domain randomisation in training.

    :meth:`sample` takes one seed from the caller's generator, then from that seed alone picks a
    family from ``families`` and a user count in ``users`` (an inclusive range), both uniformly,
    and draws the scenario: the same seed always gives the same scenario, and the caller's
    generator advances by exactly one draw whatever the sampler's settings. With one family and
    one user count nothing is picked, and the users equal
    ``generate_scenarios(1, n_users, seed, ..., family=family)[0]``. The id,
    ``<family>-<U>u-<seed>`` (``mixture-<drawn>-...`` for a mixture), says how to draw it again.

    A family may be listed more than once to weight it; the site families
    (:data:`SITE_FAMILIES`) only with a site's area. Bad fields raise :class:`InputError`
    naming the field.
    """

    families: tuple[str, ...] = ("exponential",)
    users: tuple[int, int] = (3, 3)
    area: AreaConfig = field(default_factory=AreaConfig)
    total_load_bps: float = TrafficConfig.total_load_bps
    config: GeneratorConfig = field(default_factory=GeneratorConfig)
    family_config: FamilyConfig = field(default_factory=FamilyConfig)

    def __post_init__(self) -> None:
        families = self.families
        if isinstance(families, str):
            families = (families,)
        try:
            families = tuple(families)
        except TypeError:
            raise InputError(
                f"families: must be a sequence of family names, got {self.families!r}"
            ) from None
        if not families:
            raise InputError(f"families: need at least one of {', '.join(FAMILIES)}")
        for family in families:
            _check_family(family, "families")
        users = self.users
        try:
            lo, hi = users
        except (TypeError, ValueError):
            raise InputError(f"users: must be a (min, max) pair, got {users!r}") from None
        lo = _check_users(lo, "users")
        hi = _check_users(hi, "users")
        if lo > hi:
            raise InputError(f"users: min {lo} is above max {hi}")
        if not isinstance(self.area, AreaConfig):
            raise InputError(f"area: must be an AreaConfig, got {type(self.area).__name__}")
        for family in families:
            check_family_area(family, self.area, "families")
        if not isinstance(self.config, GeneratorConfig):
            raise InputError(f"config: must be a GeneratorConfig, got {type(self.config).__name__}")
        if not isinstance(self.family_config, FamilyConfig):
            raise InputError(
                f"family_config: must be a FamilyConfig, got {type(self.family_config).__name__}"
            )
        object.__setattr__(self, "families", families)
        object.__setattr__(self, "users", (lo, hi))
        object.__setattr__(self, "total_load_bps", _check_total_load(self.total_load_bps))

    def pick(self, seed: int) -> tuple[str, int]:
        """The family and user count :meth:`sample` uses for ``seed``."""
        (lo, hi), families = self.users, self.families
        if lo == hi and len(set(families)) == 1:
            return families[0], lo
        pick_rng = _stream(seed, _PICK_KEY)
        family = families[int(pick_rng.integers(0, len(families)))]
        return family, int(pick_rng.integers(lo, hi + 1))

    def sample(self, rng: np.random.Generator) -> Scenario:
        """One scenario; deterministic given the state of ``rng`` (advanced by one draw)."""
        seed = int(rng.integers(2**63 - 1))
        family, n_users = self.pick(seed)
        xy_m, load_bps, drawn = _draw(
            _stream(seed, 0),
            family,
            n_users,
            self.area,
            self.total_load_bps,
            self.config,
            self.family_config,
        )
        return Scenario(f"{_label(family, drawn)}-{n_users}u-{seed}", xy_m, load_bps)


def check_scenario_area(scenario: Scenario, area: AreaConfig, where: str = "") -> None:
    """InputError of one line when a user of ``scenario`` cannot stand in ``area``: on a site
    (``site:PATH``), inside a building (``{where}users[3]: (120.0, 45.0) is inside a building on
    site:/path``) or off the site. Nothing to check elsewhere (the open field and the towns take
    any position)."""
    site = area_site(area)
    if site is None:
        return
    from sim.sites.ground import check_walkable

    check_walkable(site, scenario.users_xy_m, area.environment, where)


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
